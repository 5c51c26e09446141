"""``python -m fgat``: the command line.

Subcommands import what they need when they run, so ``fgat design`` answers without loading
PyTorch.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path


def _parse_depths(text: str) -> list[float]:
    """``"-30,-15,0,15,30"`` or ``"start:stop:count"`` (inclusive, evenly spaced) in um."""
    try:
        if ":" in text:
            start, stop, count = text.split(":")
            count = int(count)
            if count < 1:
                raise ValueError
            if count == 1:
                return [float(start)]
            step = (float(stop) - float(start)) / (count - 1)
            return [float(start) + i * step for i in range(count)]
        return [float(value) for value in text.split(",") if value.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"depths {text!r}: expected comma-separated micrometres (-30,0,30) or start:stop:count") from None


def _parse_zernike(text: str) -> dict[int, float]:
    """``"5=0.3,8=-0.2"``: Noll index = coefficient in waves."""
    try:
        pairs = (item.split("=") for item in text.split(",") if item.strip())
        return {int(j): float(c) for j, c in pairs}
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"zernike {text!r}: expected NOLL=WAVES pairs separated by commas, e.g. 5=0.3,8=-0.2") from None


def _parse_shifts(text: str) -> dict[int, tuple[float, float]]:
    """``"1=0.5:-0.3,4=1:0"``: view = row:col in pixels."""
    try:
        result = {}
        for item in (i for i in text.split(",") if i.strip()):
            view, value = item.split("=")
            row, col = value.split(":")
            result[int(view)] = (float(row), float(col))
        return result
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"shifts {text!r}: expected VIEW=ROW:COL pairs separated by commas, e.g. 1=0.5:-0.3") from None


def _add_design(subparsers) -> None:
    parser = subparsers.add_parser(
        "design", help="nominal FLFM design values (Note S1, Table S1)",
        description="Print the FLFM design relations of Note S1 for one or more objectives.")
    parser.add_argument("--objective", action="append", metavar="MAGx/NA",
                        help="objective such as 20x/0.45 (repeatable; default: the three of Table S1)")
    parser.add_argument("--wavelength-um", type=float, default=0.51)
    parser.add_argument("--f-fourier-mm", type=float, default=300.0)
    parser.add_argument("--f-mla-mm", type=float, default=100.0)
    parser.add_argument("--mla-pitch-mm", type=float, default=4.0)
    parser.add_argument("--pixel-um", type=float, default=6.5)
    parser.add_argument("--json", action="store_true", help="print the design dict(s) as JSON")
    parser.set_defaults(run=_run_design)


def _run_design(args) -> int:
    from fgat.optics.design import flfm_design, format_design_table, parse_objective

    objectives = args.objective or ["20x/0.45", "40x/0.90", "60x/1.25"]
    rows = {}
    for objective in objectives:
        magnification, na = parse_objective(objective)
        rows[objective] = flfm_design(magnification, na, wavelength_um=args.wavelength_um,
                                      f_fourier_mm=args.f_fourier_mm, f_mla_mm=args.f_mla_mm,
                                      mla_pitch_mm=args.mla_pitch_mm, pixel_um=args.pixel_um)
    if args.json:
        print(json.dumps(rows[objectives[0]] if len(rows) == 1 else rows, indent=2))
    else:
        print(format_design_table(rows))
    return 0


def _add_psf(subparsers) -> None:
    parser = subparsers.add_parser(
        "psf", help="JPGM PSF stack of an FLFM system (Note S2) as OME-TIFF",
        description="Compute the per-view, per-depth PSF stack (V, Z, 2r+1, 2r+1) of a system, "
                    "aberration-free unless Zernike coefficients or lenslet shifts are given.")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--objective", help="a Table S1 objective: 20x/0.45, 40x/0.90 or 60x/1.25")
    source.add_argument("--system", help="'small' or a system YAML file")
    parser.add_argument("--depths-um", type=_parse_depths, required=True,
                        help="depths in um: -30,-15,0,15,30 or start:stop:count")
    parser.add_argument("--out", required=True, help="output OME-TIFF path")
    parser.add_argument("--zernike", type=_parse_zernike, default={}, metavar="J=C,...",
                        help="Zernike coefficients in waves by Noll index, e.g. 5=0.3,8=-0.2")
    parser.add_argument("--intercepts", type=_parse_shifts, default={}, metavar="V=ROW:COL,...",
                        help="per-view intercepts b_v in pixels")
    parser.add_argument("--slopes", type=_parse_shifts, default={}, metavar="V=ROW:COL,...",
                        help="per-view slopes s_v in pixels per unit of xi")
    parser.add_argument("--crop-radius", type=int, help="crop half-width r in pixels (default: system's)")
    parser.add_argument("--method", choices=("auto", "mft", "asm"), default="auto")
    parser.add_argument("--float64", action="store_true", help="compute in float64 (written as float32)")
    parser.add_argument("--plot", help="also save x-y and x-z maximum projections of every view as PNG")
    parser.set_defaults(run=_run_psf)


def _run_psf(args) -> int:
    import torch

    from fgat.io import write_tiff
    from fgat.optics.psf import JPGM
    from fgat.optics.systems import load_system
    from fgat.optics.zernike import DEFAULT_INDICES

    for option, path in (("--out", args.out), ("--plot", args.plot)):
        if path and not Path(path).resolve().parent.is_dir():
            raise FileNotFoundError(f"{option} {path}: folder {Path(path).resolve().parent} does not exist")
    system = load_system(args.objective or args.system or "20x/0.45")
    indices = tuple(sorted(set(DEFAULT_INDICES) | set(args.zernike)))
    dtype = torch.float64 if args.float64 else torch.float32
    model = JPGM(system, args.depths_um, zernike_indices=indices, crop_radius_px=args.crop_radius,
                 method=args.method, dtype=dtype)
    with torch.no_grad():
        for j, value in args.zernike.items():
            model.zernike_coefficients[indices.index(j)] = value
        for name, shifts in (("intercepts", args.intercepts), ("slopes", args.slopes)):
            for view, value in shifts.items():
                if not 0 <= view < model.n_views:
                    raise ValueError(f"--{name}: view {view} does not exist (views 0..{model.n_views - 1})")
                getattr(model, name)[view] = torch.tensor(value, dtype=dtype)
        start = time.perf_counter()
        stack = model()
        elapsed = time.perf_counter() - start
    depths = args.depths_um
    dz = abs(depths[1] - depths[0]) if len(depths) > 1 else 1.0
    voxel = system.voxel_size_um
    write_tiff(args.out, stack.float().numpy(), axes="CZYX", voxel_size_um=(dz, voxel, voxel))
    print(f"{system.name}: PSF stack {tuple(stack.shape)} (views, depths, rows, cols) by "
          f"{model.resolved_method()} in {elapsed:.2f} s -> {args.out}")
    captured = stack.sum(dim=(0, 2, 3))
    print(f"energy captured per depth (sum over views): min {float(captured.min()):.4f}, "
          f"max {float(captured.max()):.4f}")
    if float(captured.min()) < 0.9:
        worst = int(captured.argmin())
        print(f"warning: the crops hold only {float(captured[worst]):.0%} of the light at depth "
              f"{depths[worst]:g} um; increase --crop-radius or narrow --depths-um", file=sys.stderr)
    if args.plot:
        from fgat.plots import plot_psf_stack

        plot_psf_stack(stack.float().numpy(), args.plot, title=f"{system.name} JPGM PSF",
                       depths_um=depths, pixel_um=voxel)
        print(f"PSF views -> {args.plot}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fgat", description="fgat: 4DGAT reconstruction of Fourier light-field microscopy volumes.")
    subparsers = parser.add_subparsers(title="subcommands", dest="command", required=True)
    _add_design(subparsers)
    _add_psf(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (ValueError, FileNotFoundError) as error:
        print(f"fgat {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
