"""``fgat simulate``, ``fgat calibrate``, ``fgat calibrate-depth`` and ``fgat deconvolve``:
simulated measurements, calibration folders from images, and RL/SHB reconstructions.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import time
from pathlib import Path

from fgat.app.arguments import add_device, add_output_folder, number_type, parse_depths


def add_simulate(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulated FLFM acquisition of a phantom",
        description="Simulate a phantom seen through a system's JPGM PSF with camera noise and "
        "write truth, PSF stack, sensor image, views, lenslet centres and every parameter to "
        "OUT.",
    )
    parser.add_argument("--config", required=True, help="simulation YAML (see configs/simulate/)")
    add_output_folder(parser, "write into a non-empty OUT, replacing only fgat's own files there")
    parser.set_defaults(run=_run_simulate)


def _run_simulate(args) -> int:
    from fgat._core.resources import DiskFullError  # imported when used: keeps start-up fast
    from fgat.sim.simulation import (  # imported when used: keeps start-up fast
        SimulationConfig,
        check_output_folder,
        simulate,
        write_simulation,
    )

    config = SimulationConfig.from_yaml(args.config)
    out = check_output_folder(args.out, overwrite=args.overwrite)
    start = time.perf_counter()
    try:
        result = simulate(config, out)
    except DiskFullError:
        raise
    except ValueError as error:  # what needs the system or the phantom, checked before computing
        raise ValueError(f"{args.config}: {error}") from None
    write_simulation(result, out, overwrite=args.overwrite)
    axes = "(T, Z, Y, X)" if result.is_sequence else "(Z, Y, X)"
    print(
        f"{result.system.name}: {config.phantom['kind']} phantom {result.truth.shape} {axes}, "
        f"{result.views.shape[-3]} views, sensor {result.sensor.shape}, "
        f"peak {float(result.sensor.max()):.0f} counts, "
        f"in {time.perf_counter() - start:.1f} s -> {out}"
    )
    return 0


def add_calibrate(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="lenslet centres, view gains, camera model from images",
        description="Fit a hexagonal lattice to a brightfield image of the MLA or to the "
        "fluorescence image itself (frames summed), refine every lenslet, measure the camera "
        "(offset, read noise, hot pixels) and the per-view gains, and write OUT/centers.csv "
        "(fgat's view order), OUT/calibration.yaml (everything fgat reads back: centres file, "
        "lattice, residuals, gains, camera, depth axis, view order), OUT/hot_pixels.ome.tif "
        "(when there are hot pixels), OUT/lattice.yaml (the fit's report and quality) and "
        "OUT/overlay.png. Nothing is written when the fit is poor: fewer than 80% of the views "
        "found (a view stands 7 noise std above the background and lies within 0.2 pitch of the "
        "lattice), a median view contrast under 7 or centres more than 0.1 pitch RMS off the "
        "lattice (fgat.instrument.lattice.MIN_VIEWS_FOUND, MIN_VIEW_CONTRAST, "
        "MAX_RESIDUAL_RMS).",
    )
    parser.add_argument("--image", required=True, help="TIFF (H, W) or frames (T, H, W)")
    count = parser.add_mutually_exclusive_group(required=True)
    count.add_argument(
        "--system",
        help="system name or YAML: its lenslet count, pitch and rotation; a fitted pitch more "
        "than 5%% off the system's, or a rotation more than 2.9 deg off, is refused with the "
        "system fields that would match it (mla_pitch_convention, mla_orientation, "
        "mla_rotation_deg)",
    )
    count.add_argument(
        "--n-lenslets", type=number_type(integer=True, minimum=1), help="lenslets of the MLA"
    )
    parser.add_argument(
        "--pitch-px",
        type=number_type(minimum=1),
        help="expected lenslet pitch in pixels (optional)",
    )
    parser.add_argument(
        "--dark",
        metavar="DARK.tif",
        help="dark frame(s) (H, W) or (T, H, W) of the camera: offset, read noise and hot "
        "pixels (default: estimated from the image's dark regions, and labelled so); a level "
        "more than 5 read-noise std above the image's own background, or more than 1%% hot "
        "pixels, is warned about, a level above 99%% of the image's pixels refused",
    )
    parser.add_argument(
        "--flat",
        metavar="FLAT.tif",
        help="white-light image of the MLA (H, W) or (T, H, W): per-view gains from each "
        "lenslet's mean over 0.4 pitch (default: from the image itself with --system, which "
        "assumes the sample inside every view's field; none with --n-lenslets)",
    )
    parser.add_argument(
        "--pixel-flat",
        metavar="FLAT.tif",
        help="uniformly lit frame(s) of the camera without the MLA pattern (H, W) or (T, H, W): "
        "the relative sensitivity of every pixel (mean 1, after the --dark offset), divided "
        "out of every image before use (default: uniform)",
    )
    parser.add_argument(
        "--depth-axis",
        choices=("up", "down"),
        default="up",
        help="Z order of reconstructed volumes, stored in calibration.yaml: up (default, "
        "fgat's: index 0 at the most negative depth, nearest the objective) or down (flipped)",
    )
    add_output_folder(parser, "replace an existing calibration in OUT", out_help="output folder")
    parser.set_defaults(run=_run_calibrate)


def _run_calibrate(args) -> int:
    import numpy as np  # loaded when used: keeps start-up fast

    from fgat.app.calibration_report import (  # imported when used: keeps start-up fast
        write_calibration,
    )
    from fgat.app.monitor import current  # imported when used: keeps start-up fast
    from fgat.instrument.calibration import (  # imported when used: keeps start-up fast
        CALIBRATION_FILE,
        gains_from_flat,
        gains_from_image,
        low_gain_warning,
    )
    from fgat.instrument.camera import (  # imported when used: keeps start-up fast
        FLAT_FILE,
        HOT_PIXEL_FILE,
        camera_from_dark,
        camera_from_image,
        dark_frame_warning,
        flat_field,
    )
    from fgat.instrument.lattice import (  # imported when used: keeps start-up fast
        check_lenslet_count,
        fit_hexagonal_lattice,
        lattice_mismatch,
        lattice_quality,
        number_like,
        rotation_from_system_deg,
        view_psf_energy,
    )
    from fgat.io.files import (  # imported when used: keeps start-up fast
        check_output_file,
        check_writable_folder,
    )
    from fgat.io.images import read_tiff  # imported when used: keeps start-up fast
    from fgat.optics.lenslets import (  # imported when used: keeps start-up fast
        largest_view_size,
        lenslet_image,
    )
    from fgat.optics.systems import load_system  # imported when used: keeps start-up fast

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: a file, expected a folder for the calibration")
    if out.is_dir():
        names = (
            "centers.csv",
            "lattice.yaml",
            "overlay.png",
            CALIBRATION_FILE,
            HOT_PIXEL_FILE,
            FLAT_FILE,
        )
        for name in names:
            check_output_file(out / name, overwrite=args.overwrite, option="--out")
    else:  # made, with its parents, once the lattice has passed its checks
        existing = next(folder for folder in out.absolute().parents if folder.exists())
        if not existing.is_dir():
            raise ValueError(f"--out {out}: {existing} is a file, expected folders")
        check_writable_folder(existing, f"--out {out}")
    frames = read_tiff(args.image, ndim=(2, 3), axes="(H, W) or (T, H, W)")
    image = lenslet_image(frames, 1, str(args.image), frames=True)
    extra = {}
    for option in ("dark", "flat", "pixel_flat"):
        path = getattr(args, option)
        if path is not None:
            extra[option] = read_tiff(path, ndim=(2, 3), axes="(H, W) or (T, H, W)")
            if extra[option].shape[-2:] != image.shape:
                flag = "--" + option.replace("_", "-")
                raise ValueError(
                    f"{flag} {path}: {extra[option].shape[-2]} x {extra[option].shape[-1]} "
                    f"pixels, but --image {args.image} is {image.shape[0]} x {image.shape[1]}"
                )
    n_lenslets, count_option = args.n_lenslets, "--n-lenslets"
    pitch = args.pitch_px
    system = None
    if args.system is not None:
        system = load_system(args.system)
        n_lenslets, count_option = system.n_lenslets, f"--system {args.system}: n_lenslets"
        if pitch is None:
            pitch = system.pitch_px
    check_lenslet_count(n_lenslets, image.shape, count_option)
    start = time.perf_counter()
    if "dark" in extra:
        camera = camera_from_dark(extra["dark"])
        camera_source = f"dark frame(s) {args.dark}"
        warning = dark_frame_warning(camera, frames, f"--dark {args.dark}")
        if warning is not None:
            print(f"warning: {warning}", file=sys.stderr)
    else:
        camera = camera_from_image(frames)
        camera_source = f"estimated from the image {args.image} (no dark frame)"
    try:
        fit = fit_hexagonal_lattice(image, n_lenslets, pitch)
    except ValueError as error:
        raise ValueError(f"--image {args.image}: {error}") from None
    quality = lattice_quality(image, fit, camera.hot_pixels)
    problem = quality.problem()
    if problem is not None:
        raise ValueError(f"--image {args.image}: no lattice of {n_lenslets} lenslets: {problem}")
    if system is not None:
        mismatch = lattice_mismatch(fit, system)
        if mismatch is not None:
            raise ValueError(f"--image {args.image} against --system {args.system}: {mismatch}")
        numbered = number_like(fit, system.lattice_rotation_deg)
        if numbered is not fit:
            fit, quality = numbered, lattice_quality(image, numbered, camera.hot_pixels)
    if "pixel_flat" in extra:
        dark = extra["dark"] if "dark" in extra else camera.offset
        camera = dataclasses.replace(camera, flat=flat_field(extra["pixel_flat"], dark))
        camera_source += f", pixel flat field {args.pixel_flat}"
    gains, gains_source = None, None
    if "flat" in extra:
        dark_camera = camera if "dark" in extra else None  # else the flat's own dark regions
        gains = gains_from_flat(extra["flat"], fit.centers, 0.4 * fit.lattice.pitch, dark_camera)
        gains_source = f"white-light MLA image {args.flat}"
    elif system is not None:
        energy = view_psf_energy(system, fit.centers)
        view_size = largest_view_size(fit.centers, image.shape)
        gains = gains_from_image(frames, fit.centers, view_size, energy, camera)
        gains_source = (
            f"estimated from the image {args.image} (flux per view over the PSF energy per "
            "view at depth 0 with the lenslets on the measured centres; assumes the sample "
            "inside every view's field)"
        )
    faint = None if gains is None else low_gain_warning(gains)
    current().check("before the calibration was written")
    made = None if out.exists() else next(f for f in (out, *out.parents) if f.parent.exists())
    out.mkdir(parents=True, exist_ok=True)
    try:
        paths = write_calibration(
            fit,
            out,
            image,
            str(args.image),
            gains=gains,
            gains_source=gains_source,
            camera=camera,
            camera_source=camera_source,
            depth_axis=args.depth_axis,
            quality=quality,
        )
    except BaseException:
        if made is not None:  # the folders this run made, with what it wrote into them
            shutil.rmtree(made, ignore_errors=True)
        raise
    lattice = fit.lattice
    print(
        f"{n_lenslets} lenslets: pitch {lattice.pitch:.2f} px, rotation "
        f"{lattice.rotation_deg:.2f} deg, view 0 at ({lattice.center[0]:.2f}, "
        f"{lattice.center[1]:.2f}); residuals median {np.median(fit.residuals):.2f} px, max "
        f"{fit.residuals.max():.2f} px"
        + (
            f"; views {np.flatnonzero(~quality.found).tolist()} not found"
            if not quality.found.all()
            else ""
        )
    )
    print(quality.summary())
    if system is not None:
        turn = rotation_from_system_deg(lattice, system)
        print(
            f"system {system.name}: pitch {system.pitch_px:.2f} px (measured / system "
            f"{lattice.pitch / system.pitch_px:.4f}), rotation {system.lattice_rotation_deg:.2f} "
            f"deg (measured - system {turn:+.2f} deg)"
        )
    print(
        "gains: none (give --flat, or --system to estimate them from the image)"
        if gains is None
        else f"gains: min {gains.min():.3f} (view {int(gains.argmin())}), max 1 (view "
        f"{int(gains.argmax())}), {gains_source}"
    )
    if faint is not None:
        print(f"warning: gains: {faint}", file=sys.stderr)
    print(
        f"camera: offset {camera.offset:.2f} counts, read noise {camera.read_noise:.2f} counts, "
        f"{camera_source}"
    )
    hot = 0 if camera.hot_pixels is None else int(camera.hot_pixels.sum())
    if not hot:  # no other run's map beside this calibration (there only with --overwrite)
        (out / HOT_PIXEL_FILE).unlink(missing_ok=True)
    print(f"hot pixels: {hot}" + (f" -> {out / HOT_PIXEL_FILE}" if hot else ""))
    if not fit.brightfield:
        print(
            "fluorescence image: the centres are fixed up to where the sample is (a common "
            "shift: its mean lateral position; a common radial scale: its mean depth's "
            "parallax), which moves the volume by as much; a white-light MLA image fixes them "
            "absolutely, and the fit's lenslet-shift estimation refines each lens"
        )
    print(f"depth axis: {args.depth_axis}")
    print(f"{time.perf_counter() - start:.1f} s -> {', '.join(str(p) for p in paths.values())}")
    return 0


def add_calibrate_depth(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate-depth",
        help="depth scale of the parallax from a bead z-stack",
        description="Track one sub-resolution bead (the brightest) through a z-stack of sensor "
        "frames in every view, fit each view's centroid slope against the positions, compare "
        "them with the same slopes of the system's JPGM bead stack and fit one factor on the "
        "pupil phase per um (depth_scale) that makes the model match every view. A stage or "
        "objective step changes the immersion layer, not the depth in the sample: the model "
        "uses the immersion medium's phase for it, and the factor then applies to depths in the "
        "sample. The fit is refused when the bead is fainter than 8 times the noise or when the "
        "views misfit one factor by more than 5% of their parallax (a wrong pupil radius, pitch "
        "or refractive index changes the parallax ring by ring). The factor, with its "
        "provenance, is written into CALIBRATION/calibration.yaml, and psf, deconvolve and fit "
        "apply it whenever they read that calibration.",
    )
    parser.add_argument("--stack", required=True, help="TIFF (Z, H, W): one frame per position")
    parser.add_argument(
        "--positions-um",
        type=parse_depths,
        required=True,
        help="stage or objective position of each frame in um: -3,0,3 or start:stop:count",
    )
    parser.add_argument(
        "--motion",
        choices=("stage", "objective"),
        default="stage",
        help="what moved: stage (default; a larger position moves the sample away from the "
        "objective) or objective (a larger position moves the objective towards the sample)",
    )
    parser.add_argument("--system", required=True, help="system name or YAML")
    parser.add_argument(
        "--calibration",
        required=True,
        help="calibration folder from fgat calibrate (its centres; updated in place)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace a depth_scale the calibration holds"
    )
    parser.set_defaults(run=_run_calibrate_depth)


def _run_calibrate_depth(args) -> int:
    import numpy as np  # loaded when used: keeps start-up fast

    from fgat.instrument.calibration import (  # imported when used: keeps start-up fast
        read_calibration,
        save_calibration,
    )
    from fgat.io.images import read_tiff  # imported when used: keeps start-up fast
    from fgat.optics.depth_scale import (  # imported when used: keeps start-up fast
        calibrate_depth_scale,
    )
    from fgat.optics.systems import load_system  # imported when used: keeps start-up fast

    system = load_system(args.system)
    calibration = read_calibration(args.calibration)
    if calibration.depth_scale is not None and not args.overwrite:
        raise ValueError(
            f"--calibration {args.calibration}: already holds depth_scale "
            f"{calibration.depth_scale:g}; pass --overwrite to replace it"
        )
    if calibration.n_views != system.n_lenslets:
        raise ValueError(
            f"--calibration {args.calibration}: {calibration.n_views} lenslet centres, but "
            f"system {system.name!r} has {system.n_lenslets} lenslets (n_lenslets)"
        )
    stack = read_tiff(args.stack, ndim=3, axes="(Z, H, W) bead z-stack")
    if len(stack) != len(args.positions_um):
        raise ValueError(
            f"--stack {args.stack}: {len(stack)} frames, but --positions-um gives "
            f"{len(args.positions_um)} positions"
        )
    if calibration.camera is not None:
        stack = calibration.camera.correct(stack)
        stack = np.where(calibration.camera.valid(stack.shape) > 0, stack, np.median(stack))
    try:
        fit = calibrate_depth_scale(
            stack, args.positions_um, system, calibration.centers, motion=args.motion
        )
    except ValueError as error:
        raise ValueError(f"--stack {args.stack}: {error}") from None
    scale = system.depth_scale * fit.scale
    positions = args.positions_um
    source = (
        f"{args.stack}, {args.motion} positions {min(positions):g}..{max(positions):g} um "
        f"({len(positions)}), system {system.name!r}: factor {fit.scale:.4f} +- "
        f"{fit.scale_error:.4f} on its depth_scale {system.depth_scale:g}, misfit "
        f"{fit.residual:.3f} of the parallax, bead {fit.snr:.0f} x noise"
    )
    save_calibration(
        dataclasses.replace(calibration, depth_scale=scale, depth_scale_source=source),
        args.calibration,
    )
    rings = ", ".join(f"{ring:g}: {ratio:.3f}" for ring, ratio in fit.ring_ratios.items())
    print(
        f"depth scale {scale:.4f} +- {fit.scale_error * system.depth_scale:.4f} "
        f"({int(fit.used.sum())} views, misfit {fit.residual:.3f} of the parallax; measured over "
        f"model by ring distance in pitches {rings}) -> {args.calibration}/calibration.yaml"
    )
    return 0


def add_deconvolve(subparsers) -> None:
    parser = subparsers.add_parser(
        "deconvolve",
        help="RL / SHB deconvolution of an FLFM image (Note S6)",
        description="Reconstruct a volume from an FLFM sensor image with scaled-heavy-ball RL "
        "(Algorithm S1) or plain Richardson-Lucy. The PSF comes from a file (--psf) or is "
        "computed at the lenslet centres from a system (--system with --depths-um); the centres, "
        "per-view gains and camera model from a calibration folder (--calibration) or files.",
    )
    parser.add_argument("--measurement", required=True, help="sensor image (TIFF, 2D)")
    optics = parser.add_mutually_exclusive_group(required=True)
    optics.add_argument("--psf", help="PSF stack (V, Z, h, w) OME-TIFF, e.g. from fgat psf")
    optics.add_argument(
        "--system", help="system name or YAML: the JPGM PSF at the centres (with --depths-um)"
    )
    parser.add_argument(
        "--depths-um",
        type=parse_depths,
        help="PSF planes for --system: -6,0,6 or start:stop:count",
    )
    parser.add_argument(
        "--calibration",
        help="folder written by fgat calibrate: centres, per-view gains, camera offset and hot "
        "pixels, depth axis (explicit options take precedence)",
    )
    parser.add_argument(
        "--centers",
        help="lenslet centres: CSV with a row,col / col,row / x,y header (0-based), or .mat "
        "(row, col; 1-based)",
    )
    parser.add_argument(
        "--out",
        required=True,
        help="output volume OME-TIFF (Z, Y, X) (an existing file only with --overwrite); the "
        "data residual and how the iteration stopped go beside it as <name>.residual.json",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    parser.add_argument(
        "--method",
        choices=("shb", "rl"),
        default="shb",
        help="shb: scaled-heavy-ball RL (Algorithm S1, default); rl: plain Richardson-Lucy",
    )
    parser.add_argument(
        "--iterations",
        type=number_type(integer=True, minimum=1),
        default=50,
        help="iterations to run, the limit with --tol or --holdout (default 50)",
    )
    parser.add_argument(
        "--background",
        type=number_type(),
        help="camera offset subtracted first (counts; default the camera model's from --dark or "
        "--calibration, else 0); view pixels below it are clipped to 0 and their number is "
        "printed",
    )
    parser.add_argument("--dark", help="dark frame(s) TIFF: camera offset and hot pixels")
    parser.add_argument(
        "--guard-px",
        type=_guard,
        default="auto",
        help="guard band around the views in pixels, or auto (the PSF's 99%%-energy radius, at "
        "most half the view): objects beyond the field of view no longer pile into the border "
        "voxels; 0 reconstructs on the views' grid",
    )
    parser.add_argument(
        "--depth-axis",
        choices=("up", "down"),
        help="plane order of the volume (default the calibration's, else up: index 0 is the "
        "first depth)",
    )
    parser.add_argument(
        "--view-size",
        type=number_type(integer=True, minimum=1),
        help="lateral size of each view and of the volume (default: the view_size of the "
        "simulation's params.yaml beside --measurement, else the truth's, else the largest "
        "square that fits between the centres); a --truth of another size is refused",
    )
    parser.add_argument(
        "--tol",
        type=number_type(above=0),
        help="stop when the Poisson cost changes by less than this",
    )
    parser.add_argument(
        "--holdout",
        type=number_type(above=0, maximum=0.5),
        help="leave this share of the pixels out of the update (e.g. 0.1) and stop 20 "
        "iterations after their Poisson cost's minimum, returning that iterate: stops before "
        "the noise is fitted, with --iterations as the limit",
    )
    parser.add_argument(
        "--truth", help="ground-truth volume: report PSNR and SSIM (max-normalised)"
    )
    parser.add_argument(
        "--allow-long",
        action="store_true",
        help="run even when the time estimated before the iterations exceeds 24 hours "
        "(refused otherwise, as a likely typo in --iterations)",
    )
    add_device(parser)
    parser.set_defaults(run=_run_deconvolve)


def _guard(text: str):
    """``auto`` or a number of pixels >= 0."""
    if text == "auto":
        return text
    try:
        return number_type(integer=True, minimum=0)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected 'auto' or a number of pixels >= 0, got {text!r}"
        ) from None


def _run_deconvolve(args) -> int:
    import torch  # torch loaded when used: keeps start-up fast

    from fgat._core.devices import resolve_device  # imported when used: keeps start-up fast
    from fgat._core.resources import (  # imported when used: keeps start-up fast
        check_disk_space,
        check_memory,
    )
    from fgat.app.monitor import current  # imported when used: keeps start-up fast
    from fgat.app.report import (  # imported when used: keeps start-up fast
        deconvolution_ending,
        report_lines,
        report_path,
        residual_report,
        write_report,
    )
    from fgat.instrument.calibration import (  # imported when used: keeps start-up fast
        read_calibration,
    )
    from fgat.instrument.measurement import (  # imported when used: keeps start-up fast
        measurement_model,
    )
    from fgat.instrument.views import (  # imported when used: keeps start-up fast
        check_truth_shape,
        choose_view_size,
    )
    from fgat.io.files import check_output_file  # imported when used: keeps start-up fast
    from fgat.io.images import (  # imported when used: keeps start-up fast
        read_tiff,
        volume_entries,
        write_tiff,
    )
    from fgat.optics.acquisition import MeasuredOperator  # imported when used: keeps start-up fast
    from fgat.optics.systems import load_system  # imported when used: keeps start-up fast
    from fgat.recon.costs import (  # imported when used: keeps start-up fast
        check_long_run,
        deconvolution_cost,
        deconvolution_memory,
    )
    from fgat.recon.deconvolution import deconvolve  # imported when used: keeps start-up fast
    from fgat.recon.metrics import (  # imported when used: keeps start-up fast
        compare_volumes,
        relative_residual,
    )

    started = time.perf_counter()
    check_output_file(args.out, overwrite=args.overwrite, option="--out")
    check_output_file(report_path(args.out), overwrite=args.overwrite, option="--out's report")
    if args.system is not None and args.depths_um is None:
        raise ValueError("--system needs --depths-um (the PSF planes, um)")
    if args.calibration is None and args.centers is None:
        raise ValueError("give --centers (a file) or --calibration (a folder from fgat calibrate)")
    device = resolve_device(args.device)
    sensor = read_tiff(args.measurement, ndim=2, axes="(H, W) sensor image")
    model = measurement_model(
        calibration=None if args.calibration is None else read_calibration(args.calibration),
        centers=args.centers,
        psf=args.psf,
        system=None if args.system is None else load_system(args.system),
        depths_um=args.depths_um,
        background=args.background,
        dark=args.dark,
        depth_axis=args.depth_axis,
    )
    psf = model.psf
    truth = read_tiff(args.truth, ndim=3, axes="(Z, Y, X)") if args.truth else None
    size, origin = choose_view_size(
        args.view_size,
        "--view-size",
        args.measurement,
        None if truth is None else (args.truth, truth.shape),
        model.centers,
        sensor.shape,
    )
    if truth is not None:
        check_truth_shape("--truth", args.truth, truth.shape, (psf.shape[1], size, size), origin)
    check_disk_space(args.out, psf.shape[1] * size * size * 4, what=f"--out {args.out}")
    views, mask = model.views(sensor[None].astype("float32"), size)
    views = torch.from_numpy(views[0])
    offset = f"{'--background' if args.background is not None else 'camera offset'} "
    offset += f"{model.camera.offset:g}"
    signal = views.clamp(min=0) if mask is None else views.clamp(min=0) * torch.from_numpy(mask)
    if not float(signal.max()) > 0:
        raise ValueError(
            f"--measurement {args.measurement}: every view pixel is at or below the {offset}; "
            "nothing is left to deconvolve (check --background, --dark or the calibration)"
        )
    guard = model.guard(args.guard_px, size)
    shape = (psf.shape[1], size + 2 * guard, size + 2 * guard)
    check_memory(
        "the FLFM operator and the deconvolution",
        deconvolution_memory(psf.shape, shape),
        device=device,
        hint="a smaller --view-size, --guard-px or fewer PSF depths",
    )
    below = int((views < 0).sum())
    if below:
        print(
            f"{offset}: {below} of {views.numel()} view pixels "
            f"({below / views.numel():.1%}) are below it and are clipped to 0"
        )
    gains = None if model.gains is None else torch.as_tensor(model.gains, dtype=torch.float32)
    operator = MeasuredOperator(
        torch.from_numpy(psf).to(device),
        (size, size),
        guard_px=guard,
        gains=None if gains is None else gains.to(device),
    )
    estimate = deconvolution_cost(
        operator,
        args.iterations,
        device=str(device),
        setup_seconds=time.perf_counter() - started,
        options={
            "planes": "fewer --depths-um or PSF planes",
            "iterations": "--iterations, or --tol",
            "size": "--view-size, --guard-px",
            "device": "--device cuda",
        },
    )
    print("\n".join(estimate.lines()))
    check_long_run(estimate, allow=args.allow_long, lever="--iterations")
    weights = None if mask is None else torch.from_numpy(mask).to(device)
    done = 0  # iterations run
    monitor = current()

    def progress(k: int, _volume) -> None:
        nonlocal done
        done = k + 1
        bar.update(1)
        monitor.check(f"after iteration {done} of {args.iterations}")

    desc = f"{args.method.upper()} deconvolution"
    with monitor.bar(total=args.iterations, desc=desc, unit="it") as bar:
        grid = deconvolve(
            views.to(device),
            operator,
            args.iterations,
            method=args.method,
            weights=weights,
            tol=args.tol,
            holdout=args.holdout,
            callback=progress,
        )
    volume = operator.crop(grid)
    converged, stopped = deconvolution_ending(done, args.iterations, args.tol, args.holdout)
    report = residual_report(
        relative_residual(operator, grid, views.clamp(min=0).to(device), weights),
        converged=converged,
        stopped=stopped,
        method=args.method,
        iterations=done,
        max_iterations=args.iterations,
        tol=args.tol,
        holdout=args.holdout,
        volume=str(args.out),
    )
    write_tiff(
        args.out,
        volume.cpu().numpy(),
        axes="ZYX",
        voxel_size_um=model.voxel_size_um,
        metadata=volume_entries(model.depth_axis, model.depths_um),
    )
    try:  # the volume and its report are one output: neither is left without the other
        written = write_report(report_path(args.out), report)
    except BaseException:
        os.unlink(args.out)
        raise
    print(
        f"volume {tuple(volume.shape)} (Z, Y, X), depth axis {model.depth_axis}, guard band "
        f"{guard} px"
        + ("" if mask is None else f", {int((mask == 0).sum())} hot view pixels left out")
        + f" -> {args.out}"
    )
    print(f"{report_lines(report)} -> {written}")
    if truth is not None:
        scores = compare_volumes(volume.cpu().numpy(), truth)
        print(
            f"PSNR {scores['psnr']:.2f} dB, SSIM {scores['ssim']:.4f} (volume); "
            f"x-y MIP PSNR {scores['psnr_xy']:.2f} dB, SSIM {scores['ssim_xy']:.4f}"
        )
    return 0
