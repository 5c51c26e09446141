"""Numerical stress table: each case ends finite within its stated tolerance, or is refused up
front with a clear message.

* ``scale``: the same measurement times 1e-6 ... 1e6 (and its camera offset with it) through SHB
  (``deconvolve`` on the raw views), the static stage with the optics fixed (3DGAT) and with the
  Zernike coefficients estimated (4DGAT): the normalised reconstruction's PSNR against the truth
  within 0.1 dB of the unscaled one's.
  The dynamic stage on a moving-bead sequence likewise (mean frame PSNR).
* ``gaussians``: degenerate Gaussians (scales at s_min and s_max, quaternions of norm 1e-8, zero
  and 1e30 intensities, Gaussians wholly outside the grid, none at all) voxelized in float64
  against the dense every-voxel reference (relative error <= 1e-10), gradients finite.
* ``precision``: the FLFM operator in float32 against float64 (relative L2 of forward and
  adjoint <= 1e-5), at the small size and, without ``--quick``, the paper's; one view, one depth;
  the JPGM PSF stack in float32 against float64 (relative L2 <= 1e-4) under aberrations, on the
  small system and, without ``--quick``, on 20x/0.45 over the paper's 101 depths.
* ``photons``: SHB and RL on 10 photons per bead with no background: finite, non-negative.
* ``sampling``: aberrations below the pupil-sampling limit give a finite PSF, past it are refused
  naming the sampling (the limit found by bisection on the total amplitude).
* ``rms``: all 17 Zernike terms at 0.5, 1 and 2 waves RMS on 20x/0.45 over the paper's 101
  depths (the small system with ``--quick``): a finite PSF stack, or refused naming the sampling.
* ``depths``: a very thin (3 planes over 0.6 um) and a very thick (41 planes over 240 um) depth
  range: finite, each depth sending at most its unit energy into the views' crops, or refused
  naming the sampling.
* ``edge``: a PSF crop centred on the sensor's first row is computed; one centred a pixel off
  the sensor is refused naming the view.
* ``guard``: a NaN in the Gaussians stops the static step naming the step and the loss term.

The command line:

    python benchmarks/stress.py [--quick] [--out benchmarks/results/stress.json]

``tests/stress`` (marked ``stress``) runs a fast subset of these same cases.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import torch

from fgat.app.recipes.benchmark import parser, write_json
from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.gaussians.densify import Densification
from fgat.gaussians.voxelize import voxelize, voxelize_dense
from fgat.optics.acquisition import crop_guard
from fgat.optics.operator import FLFMOperator
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.recon import (
    DynamicReconstruction,
    DynamicSettings,
    StaticReconstruction,
    StaticSettings,
    phantom_scene,
)
from fgat.recon.deconvolution import deconvolve
from fgat.recon.estimation import OpticsEstimation
from fgat.recon.metrics import compare_volumes
from fgat.recon.scene import normalized_measurement
from fgat.sim.simulation import SimulationConfig, simulate

SMALL = dict(
    system="small",
    depths_um="-12:12:13",
    view_size=32,
    photons=1e4,
    background=100.0,
    phantom={"kind": "beads", "n_beads": 6, "sigma": 1.0, "min_spacing": 6, "margin": [1, 5, 5]},
)
SCALE_TOLERANCE_DB = 0.1


def row(case: str, setting: str, value: float, tolerance: float, ok: bool, finite=True) -> dict:
    return {
        "case": case,
        "setting": setting,
        "value": float(value),
        "tolerance": float(tolerance),
        "finite": bool(finite),
        "ok": bool(ok and finite),
    }


def scaled_scene(scale: float, **simulation):
    """The scene of ``simulation`` as a user's raw views times ``scale`` (offset too) give it:
    the views scaled in float64, an exact multiple of the measurement."""
    config = SimulationConfig(**{**SMALL, **simulation})
    scene = phantom_scene(config)
    raw = simulate(config).views.astype(np.float64) * scale
    measurement, _ = normalized_measurement(raw, config.background * scale)
    return dataclasses.replace(scene, measurement=measurement), raw, config.background * scale


def reconstruct(method: str, scale: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """``method`` (SHB, 3DGAT, 4DGAT) on the measurement times ``scale``: (volume, truth)."""
    aberrations = {"amplitude": 0.05, "seed": 1} if method == "4DGAT" else None
    scene, raw, background = scaled_scene(scale, aberrations=aberrations)
    if method == "SHB":
        operator = scene.operator(torch.as_tensor(scene.psf))
        raw = torch.as_tensor(raw, dtype=torch.float32)  # a float32 camera frame
        volume = deconvolve(raw, operator, 50, background=background)
        return crop_guard(volume, scene.guard_px).numpy(), scene.truth
    engine = fit_static(scene, steps, "zernike" if method == "4DGAT" else "none")
    return engine.volume().numpy(), scene.truth


def fit_static(scene, steps: int, estimate: str = "none") -> StaticReconstruction:
    """The static stage of the scale cases: 150 Gaussians, no densification, ``estimate``'s
    optics events every 20 steps from step 20 (5 inner steps each), run for ``steps`` steps."""
    engine = StaticReconstruction(
        scene,
        StaticSettings(n_gaussians=150, init_iterations=10, baseline_iterations=0),
        Densification(enabled=False),
        OpticsEstimation(estimate=estimate, start=20, every=20, steps=5, identifiability=False),
        total_steps=steps,
    )
    for _ in range(steps):
        engine.step()
    return engine


def scale_rows(methods, scales, steps: int) -> list[dict]:
    rows = []
    for method in methods:
        reference = compare_volumes(*reconstruct(method, 1.0, steps))["psnr"]
        for scale in scales:
            volume, truth = reconstruct(method, scale, steps)
            change = compare_volumes(volume, truth)["psnr"] - reference
            rows.append(
                row(
                    "scale",
                    f"{method} x {scale:g}",
                    change,
                    SCALE_TOLERANCE_DB,
                    abs(change) <= SCALE_TOLERANCE_DB,
                    np.isfinite(volume).all(),
                )
            )
    return rows


SEQUENCE = {
    **SMALL,
    "depths_um": "-9:9:7",
    "frames": 5,
    "phantom": {
        "kind": "moving_beads",
        "n_beads": 5,
        "sigma": 1.0,
        "velocity": [0.0, 6.0, 0.0],
        "rotation_deg": 0.0,
        "min_spacing": 5.0,
        "margin": [2, 9, 5],
    },
}


def dynamic_psnr(scale: float, steps: int) -> tuple[float, bool]:
    """The dynamic stage (after a static stage on the middle frame) on the moving-bead sequence
    times ``scale``: the mean frame PSNR of its normalised volumes, and whether they are
    finite."""
    torch.manual_seed(0)  # the frame order comes from the global generator (as a DataLoader's)
    config = SimulationConfig(**SEQUENCE)
    scene = phantom_scene(config)
    frames, _ = normalized_measurement(
        simulate(config).views.astype(np.float64) * scale,
        config.background * scale,
        scene.reference,
    )
    scene = dataclasses.replace(scene, frames=frames, measurement=frames[scene.reference])
    static = fit_static(scene, steps)
    engine = DynamicReconstruction.from_static(
        scene,
        static.cloud,
        static.psf,
        hexplane=HexPlaneSettings(channels=8, spatial_resolution=(4, 8, 8)),
        settings=DynamicSettings(width=32),
    )
    for _ in range(steps):
        engine.step()
    volumes = engine.volumes()
    scores = [compare_volumes(v, t)["psnr"] for v, t in zip(volumes, scene.truth_frames)]
    return float(np.mean(scores)), bool(np.isfinite(volumes).all())


def dynamic_scale_rows(scales, steps: int) -> list[dict]:
    reference, _ = dynamic_psnr(1.0, steps)
    rows = []
    for scale in scales:
        score, finite = dynamic_psnr(scale, steps)
        change = score - reference
        ok = abs(change) <= SCALE_TOLERANCE_DB
        rows.append(row("scale", f"dynamic x {scale:g}", change, SCALE_TOLERANCE_DB, ok, finite))
    return rows


DEGENERATE = ("s_min", "s_max", "tiny quaternions", "zero and huge intensities", "outside", "none")


def degenerate_gaussians(kind: str) -> tuple:
    """``(means, scales, quats, intensities)`` float64 on the grid of :func:`gaussian_rows`."""
    generator = torch.Generator().manual_seed(0)
    n = 0 if kind == "none" else 20
    means = torch.rand(n, 3, generator=generator, dtype=torch.float64) * torch.tensor(
        [12.0, 20.0, 20.0], dtype=torch.float64
    )
    scales = 0.5 + torch.rand(n, 3, generator=generator, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    intensities = torch.rand(n, generator=generator, dtype=torch.float64)
    if kind == "s_min":
        scales.fill_(0.8)
    elif kind == "s_max":
        scales.fill_(20.0)
    elif kind == "tiny quaternions":
        quats = quats * 1e-8
    elif kind == "zero and huge intensities":
        intensities[::2] = 0.0
        intensities[1::2] = 1e30
    elif kind == "outside":
        means = means + 500.0
    return means, scales, quats, intensities


def gaussian_rows() -> list[dict]:
    grid = dict(shape=(12, 20, 20), voxel_size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0))
    rows = []
    for kind in DEGENERATE:
        inputs = [t.requires_grad_(True) for t in degenerate_gaussians(kind)]
        volume = voxelize(*inputs, **grid)
        reference = voxelize_dense(*[t.detach() for t in inputs], **grid)
        error = float((volume.detach() - reference).norm() / reference.norm().clamp(min=1e-300))
        finite = bool(torch.isfinite(volume).all())
        if volume.requires_grad:  # culled or absent Gaussians leave no graph: zero gradients
            (volume / volume.detach().abs().max().clamp(min=1e-300)).sum().backward()
            finite = finite and all(torch.isfinite(t.grad).all() for t in inputs)
        rows.append(row("gaussians", kind, error, 1e-10, error <= 1e-10, finite))
    return rows


def precision_rows(quick: bool) -> list[dict]:
    sizes = [("one view", 1, 13, 32, 15), ("one depth", 7, 1, 32, 15), ("small", 7, 31, 64, 65)]
    if not quick:
        sizes.append(("paper", 7, 101, 300, 161))
    rows = []
    for name, views, depths, size, psf in sizes:
        generator = torch.Generator().manual_seed(0)
        stack = torch.rand(views, depths, psf, psf, generator=generator, dtype=torch.float64)
        volume = torch.rand(depths, size, size, generator=generator, dtype=torch.float64)
        exact = FLFMOperator(stack, (depths, size, size))
        single = FLFMOperator(stack.float(), (depths, size, size))
        views64 = exact.forward(volume)
        forward = (single.forward(volume.float()).double() - views64).norm() / views64.norm()
        adjoint64 = exact.adjoint(views64)
        back = single.adjoint(views64.float()).double()
        adjoint = (back - adjoint64).norm() / adjoint64.norm()
        error = float(max(forward, adjoint))
        rows.append(row("precision", f"float32 operator, {name}", error, 1e-5, error <= 1e-5))
    return rows


def jpgm_precision_rows(quick: bool) -> list[dict]:
    """The aberrated, shifted JPGM PSF stack in float32 against the same model in float64."""
    cases = [("small", "-22.5:22.5:31")] + ([] if quick else [("20x/0.45", "-75:75:101")])
    rows = []
    for system, depths in cases:
        spec = OpticsSpec(
            load_system(system),
            tuple(parse_depths(depths)),
            zernike={j: 0.05 * (-1) ** j for j in range(5, 22)},
            intercepts={1: [0.3, -0.2]},
            slopes={2: [0.1, 0.4]},
        )
        with torch.no_grad():
            exact = spec.jpgm(dtype=torch.float64)()
            single = spec.jpgm(dtype=torch.float32)().double()
        error = float((single - exact).norm() / exact.norm())
        rows.append(row("precision", f"float32 JPGM, {system}", error, 1e-4, error <= 1e-4))
    return rows


def photon_rows() -> list[dict]:
    scene = phantom_scene(SimulationConfig(**{**SMALL, "photons": 10.0, "background": 0.0}))
    operator = scene.operator(torch.as_tensor(scene.psf))
    rows = []
    for method in ("shb", "rl"):
        volume = deconvolve(torch.as_tensor(scene.measurement), operator, 100, method=method)
        finite = bool(torch.isfinite(volume).all())
        psnr = compare_volumes(crop_guard(volume, scene.guard_px).numpy(), scene.truth)["psnr"]
        ok = finite and float(volume.min()) >= 0
        rows.append(row("photons", f"{method.upper()}, 10 photons, no background", psnr, 0, ok))
    return rows


def refused(amplitude: float) -> str | None:
    """The refusal of ``amplitude`` waves per term on the small system, or ``None``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            result = simulate(
                SimulationConfig(**{**SMALL, "aberrations": {"amplitude": amplitude}})
            )
        except ValueError as error:
            return str(error)
    if not np.isfinite(result.psf).all():
        raise FloatingPointError(f"{amplitude} waves: a non-finite PSF was not refused")
    return None


def sampling_rows(low: float = 1.0, high: float = 16.0, rounds: int = 6) -> list[dict]:
    if refused(low) or not refused(high):
        raise RuntimeError(f"the sampling limit is not between {low} and {high} waves")
    for _ in range(rounds):
        middle = math.sqrt(low * high)
        low, high = (low, middle) if refused(middle) else (middle, high)
    message = refused(high)
    return [
        row("sampling", f"{low:.2f} waves per term: finite PSF", low, 0, True),
        row("sampling", f"{high:.2f} waves: refused", high, 0, message.startswith("sampling:")),
    ]


def psf_outcome(spec: OpticsSpec, **options) -> tuple[float, bool, str]:
    """The JPGM stack of ``spec``: (the largest energy a depth sends into all the views' crops,
    at most the unit energy of Eq. S9; finite; "") or, refused, (nan, True, the message)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            with torch.no_grad():
                stack = spec.jpgm(**options)()
        except ValueError as error:
            return math.nan, True, str(error)
    return float(stack.sum(dim=(0, 2, 3)).max()), bool(torch.isfinite(stack).all()), ""


def depth_range_rows() -> list[dict]:
    """The small system over a very thin and a very thick depth range: a finite stack whose
    depths send at most their unit energy (Eq. S9) into the crops, or refused naming the
    sampling."""
    rows = []
    for name, depths in (("3 planes over 0.6 um", "-0.3:0.3:3"), ("41 over 240 um", "-120:120:41")):
        energy, finite, message = psf_outcome(
            OpticsSpec(load_system("small"), tuple(parse_depths(depths)))
        )
        ok = message.startswith("sampling:") if message else finite and energy <= 1 + 1e-5
        rows.append(row("depths", f"JPGM, {name}", energy, 1, ok, finite))
    return rows


def sensor_edge_rows() -> list[dict]:
    """A PSF crop centred on the sensor's first row (reaching past it) is computed; one centred
    a pixel off the sensor is refused naming the view."""
    system = load_system("small")
    depths = tuple(parse_depths("-6:6:5"))
    row0 = float(OpticsSpec(system, depths).jpgm().crop_centers().detach()[1, 0, 0])
    rows = []
    for offset, label in ((0.0, "crop centred on row 0: finite"), (-1.0, "centred off: refused")):
        spec = OpticsSpec(system, depths, intercepts={1: [offset - row0, 0.0]})
        energy, finite, message = psf_outcome(spec)
        ok = message.startswith("crop of view 1") if offset < 0 else finite and not message
        rows.append(row("edge", label, energy, 0, ok, finite))
    return rows


def rms_rows(quick: bool) -> list[dict]:
    """All 17 Zernike terms at 0.5 to 2 waves RMS (Noll-normalised: RMS = sqrt(sum c_j^2)) on
    20x/0.45 over the paper's 101 depths (the small system's 31 with ``quick``): a finite PSF
    stack, or refused naming the sampling."""
    system, depths = ("small", "-22.5:22.5:31") if quick else ("20x/0.45", "-75:75:101")
    generator = np.random.default_rng(0)
    direction = generator.uniform(-1, 1, 17)
    direction /= np.linalg.norm(direction)
    rows = []
    for rms in (0.5, 1.0, 2.0):
        zernike = {j: float(rms * c) for j, c in zip(range(5, 22), direction)}
        spec = OpticsSpec(load_system(system), tuple(parse_depths(depths)), zernike=zernike)
        energy, finite, message = psf_outcome(spec, method="mft")
        ok = message.startswith("sampling:") if message else finite and energy <= 1 + 1e-5
        rows.append(row("rms", f"{rms:g} waves RMS, {system}", energy, 1, ok, finite))
    return rows


def guard_rows() -> list[dict]:
    scene = phantom_scene(SimulationConfig(**SMALL))
    engine = StaticReconstruction(
        scene,
        StaticSettings(n_gaussians=50, init_iterations=5, baseline_iterations=0),
        Densification(enabled=False),
        total_steps=5,
    )
    engine.step()
    with torch.no_grad():
        engine.cloud.raw_intensities[3] = math.nan
    try:
        engine.step()
    except FloatingPointError as error:
        message = str(error)
    else:
        message = ""
    ok = message.startswith("step 1: loss term 'total' is nan")
    return [row("guard", "NaN intensity: the step stops, naming it", 0, 0, ok)]


def main() -> None:
    args = parser(
        __doc__, "benchmarks/results/stress.json", "decades 1e-6, 1, 1e6 only"
    ).parse_args()
    scales = (1e-6, 1e6) if args.quick else tuple(10.0**k for k in range(-6, 7) if k)
    rows = scale_rows(("SHB", "3DGAT", "4DGAT"), scales, steps=60 if args.quick else 200)
    rows += dynamic_scale_rows(scales, steps=60 if args.quick else 200)
    rows += gaussian_rows() + precision_rows(args.quick) + jpgm_precision_rows(args.quick)
    rows += photon_rows() + depth_range_rows() + sensor_edge_rows() + rms_rows(args.quick)
    rows += sampling_rows() + guard_rows()
    print(f"{'case':>10} {'setting':>46} {'value':>10} {'tolerance':>9} {'finite':>6} {'ok':>4}")
    for r in rows:
        print(
            f"{r['case']:>10} {r['setting']:>46} {r['value']:>10.3g} {r['tolerance']:>9.3g} "
            f"{str(r['finite']):>6} {'yes' if r['ok'] else 'NO':>4}"
        )
    failed = [r for r in rows if not r["ok"]]
    print(f"\n{len(rows) - len(failed)} of {len(rows)} cases finite within their tolerance")
    write_json(
        args.out, {"threads": torch.get_num_threads(), "torch": torch.__version__, "rows": rows}
    )
    if failed:
        raise SystemExit(1)
