"""``fgat design`` and ``fgat psf``: the FLFM design relations (Note S1) and JPGM PSF
stacks of a named or measured system.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time

from fgat.app.arguments import (
    measured_centers,
    number_type,
    parse_depths,
    parse_shifts,
    parse_zernike,
)


def add_design(subparsers) -> None:
    parser = subparsers.add_parser(
        "design",
        help="nominal FLFM design values (Note S1, Table S1)",
        description="Print the FLFM design relations of Note S1 for one or more objectives.",
    )
    parser.add_argument(
        "--objective",
        action="append",
        metavar="MAGx/NA",
        help="objective such as 20x/0.45 (repeatable; default: the three of Table S1)",
    )
    parser.add_argument(
        "--wavelength-um", type=float, default=0.51, help="emission wavelength (default 0.51)"
    )
    parser.add_argument(
        "--f-fourier-mm", type=float, default=300.0, help="Fourier lens focal length (default 300)"
    )
    parser.add_argument(
        "--f-mla-mm", type=float, default=100.0, help="microlens focal length (default 100)"
    )
    parser.add_argument(
        "--mla-pitch-mm", type=float, default=4.0, help="microlens pitch (default 4)"
    )
    parser.add_argument(
        "--pixel-um", type=float, default=6.5, help="camera pixel pitch (default 6.5)"
    )
    parser.add_argument("--json", action="store_true", help="print the design dict(s) as JSON")
    parser.set_defaults(run=_run_design)


def _run_design(args) -> int:
    from fgat.optics.design import (  # imported when used: keeps start-up fast
        flfm_design,
        format_design_table,
        parse_objective,
    )

    objectives = args.objective or ["20x/0.45", "40x/0.90", "60x/1.25"]
    rows = {}
    for objective in objectives:
        magnification, na = parse_objective(objective)
        rows[objective] = flfm_design(
            magnification,
            na,
            wavelength_um=args.wavelength_um,
            f_fourier_mm=args.f_fourier_mm,
            f_mla_mm=args.f_mla_mm,
            mla_pitch_mm=args.mla_pitch_mm,
            pixel_um=args.pixel_um,
        )
    if args.json:
        print(json.dumps(rows[objectives[0]] if len(rows) == 1 else rows, indent=2))
    else:
        print(format_design_table(rows))
    return 0


def add_psf(subparsers) -> None:
    parser = subparsers.add_parser(
        "psf",
        help="JPGM PSF stack of an FLFM system (Note S2) as OME-TIFF",
        description="Compute the per-view, per-depth PSF stack (V, Z, 2r+1, 2r+1) of a system, "
        "aberration-free unless Zernike coefficients or lenslet shifts are given.",
    )
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--objective", help="a Table S1 objective: 20x/0.45, 40x/0.90 or 60x/1.25")
    source.add_argument("--system", help="system name (e.g. small) or YAML")
    parser.add_argument(
        "--depths-um",
        type=parse_depths,
        required=True,
        help="depths in um: -30,-15,0,15,30 or start:stop:count",
    )
    parser.add_argument(
        "--out", required=True, help="output OME-TIFF path (an existing file only with --overwrite)"
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace existing --out and --plot files"
    )
    parser.add_argument(
        "--zernike",
        type=parse_zernike,
        default={},
        metavar="J=C,...",
        help="Zernike coefficients in waves by Noll index, e.g. 5=0.3,8=-0.2",
    )
    parser.add_argument(
        "--intercepts",
        type=parse_shifts,
        default={},
        metavar="V=ROW:COL,...",
        help="per-view intercepts b_v in pixels",
    )
    parser.add_argument(
        "--slopes",
        type=parse_shifts,
        default={},
        metavar="V=ROW:COL,...",
        help="per-view slopes s_v in pixels per unit of xi",
    )
    parser.add_argument(
        "--crop-radius",
        type=number_type(integer=True, minimum=1),
        help="crop half-width r in pixels (default: system's)",
    )
    parser.add_argument(
        "--centers",
        metavar="FILE|CALIBRATION",
        help="measured lenslet centres (a centres CSV/.mat, or a folder written by fgat "
        "calibrate) instead of the system's nominal lattice (its pitch, mla_orientation and "
        "mla_rotation_deg)",
    )
    parser.add_argument(
        "--method",
        choices=("auto", "mft", "asm"),
        default="auto",
        help="asm: angular spectrum over the whole MLA (the reference); mft: matrix Fourier "
        "transform per lenslet window; auto (default): mft where the crosstalk it ignores is "
        "negligible, else asm",
    )
    parser.add_argument(
        "--float64", action="store_true", help="compute in float64 (written as float32)"
    )
    parser.add_argument(
        "--plot", help="also save x-y and x-z maximum projections of every view as PNG"
    )
    parser.set_defaults(run=_run_psf)


def _run_psf(args) -> int:
    from fgat._core.resources import (  # imported when used: keeps start-up fast
        check_disk_space,
        check_memory,
    )
    from fgat.io.files import check_output_file  # imported when used: keeps start-up fast
    from fgat.io.images import (  # imported when used: keeps start-up fast
        volume_entries,
        write_tiff,
    )
    from fgat.optics.systems import load_system  # imported when used: keeps start-up fast

    check_output_file(args.out, overwrite=args.overwrite, option="--out")
    if args.plot:
        check_output_file(args.plot, overwrite=args.overwrite, option="--plot")
    system = load_system(args.objective or args.system or "20x/0.45")  # before PyTorch loads
    import torch  # torch loaded when used: keeps start-up fast

    from fgat.optics.sampling import (  # imported when used: keeps start-up fast
        crop_overlap_note,
        depth_spacing_warning,
    )
    from fgat.optics.spec import OpticsSpec  # imported when used: keeps start-up fast

    if args.centers is not None:
        centers, system = measured_centers(args.centers, system)
    else:
        centers = None
    dtype = torch.float64 if args.float64 else torch.float32
    spec = OpticsSpec(
        system,
        tuple(args.depths_um),
        centers,
        zernike=args.zernike,
        intercepts=args.intercepts,
        slopes=args.slopes,
    )
    options = {"crop_radius_px": args.crop_radius, "method": args.method, "dtype": dtype}
    depths = args.depths_um
    # sized on a model of the two extreme depths, before a plane of the stack is made
    extremes = (min(depths), max(depths)) if len(depths) > 1 else depths
    probe = dataclasses.replace(spec, depths_um=tuple(extremes)).jpgm(**options)
    probe.check_sampling()
    check_memory(
        f"the {len(depths)} planes of the PSF stack",
        probe.memory_bytes(planes=len(depths)),
        hint="fewer --depths-um or a smaller --crop-radius",
    )
    crop = 2 * probe.radius + 1
    stack_bytes = probe.n_views * len(depths) * crop * crop * 4
    check_disk_space(args.out, stack_bytes, what=f"--out {args.out}")
    model = spec.jpgm(**options)
    model.check_sampling()
    with torch.no_grad():
        start = time.perf_counter()
        stack = model()
        elapsed = time.perf_counter() - start
    voxel = system.grid_voxel_size_um(depths)
    write_tiff(
        args.out,
        stack.float().numpy(),
        axes="CZYX",
        voxel_size_um=voxel,
        metadata=volume_entries("up", depths, content="psf"),
    )
    print(
        f"{system.name}: PSF stack {tuple(stack.shape)} (views, depths, rows, cols) by "
        f"{model.resolved_method()} in {elapsed:.2f} s -> {args.out}"
    )
    captured = stack.sum(dim=(0, 2, 3))
    print(
        f"energy captured per depth (sum over views): min {float(captured.min()):.4f}, "
        f"max {float(captured.max()):.4f}"
    )
    overlap = crop_overlap_note(model.centers.cpu().numpy(), model.radius)
    if overlap is not None and float(captured.max()) > 1.0:
        print(f"note: {overlap}")
    spacing = depth_spacing_warning(stack.float().numpy(), depths)
    if spacing is not None:
        print(f"warning: {spacing}", file=sys.stderr)
    if float(captured.min()) < 0.9:
        worst = int(captured.argmin())
        print(
            f"warning: the crops hold only {float(captured[worst]):.0%} of the light at depth "
            f"{depths[worst]:g} um; increase --crop-radius or narrow --depths-um",
            file=sys.stderr,
        )
    if args.plot:
        from fgat.viz.optics import plot_psf_stack  # imported when used: keeps start-up fast

        plot_psf_stack(
            stack.float().numpy(),
            args.plot,
            title=f"{system.name} JPGM PSF",
            depths_um=depths,
            pixel_um=voxel[2],
        )
        print(f"PSF views -> {args.plot}")
    return 0
