"""Fig. 3j: apparent tubule widths (Note S8.2) of SHB, 3DGAT, SHB with the 4DGAT-estimated PSF
and 4DGAT under aberrations, on a tubule phantom of known diameter.

The phantom (:func:`tube_phantom`) is a few smooth tubes (quadratic Bezier curves, gently
inclined in z) with a Gaussian cross-section of standard deviation ``sigma_um``, drawn in
micrometres on the simulation's grid, so every tube has the same known diameter, its FWHM
``2 sqrt(2 ln 2) sigma_um`` (2.35 um by default, near the 1.9 um lateral resolution of
Table S1's 20x system, where the methods' apparent widths part as in Fig. 3j; ``--sigma-um``
changes it; at 2.4 samples per FWHM the interpolated FWHM reads such a profile about 10% wide,
on the truth and on every method alike, so widths are compared with the truth's measured ones).
It is written as an OME-TIFF under ``--out`` and fed to the
simulation as a ``reticular`` phantom (a volume read from a TIFF; on the same grid the
resampling is the identity), imaged through the Fig. S6 optics (random Zernike aberrations,
``configs/figS6.yaml``) and fitted twice as ``reproduce/optics.py`` does: 4DGAT (``optics.estimate
= zernike``) and 3DGAT (the ideal PSF). Each fit is a fingerprinted MLflow trial
(:func:`fgat.app.trials.fit_trial`): the phantom file's bytes are part of the fingerprint, so
a finished trial is not fitted again while its configuration and phantom are unchanged. SHB with
the ideal PSF is the 4DGAT run's baseline (``shb.ome.tif``); SHB with the 4DGAT-estimated PSF
(the run's ``psf.ome.tif``) is computed here the same way (same views, iterations, mask and guard
band; a few seconds, not cached).

Segments (:func:`select_segments`) are chosen from the truth alone: points on the tubes' centre
lines whose x-y distance to every other tube (and to the far parts of their own tube) is at
least ``isolation_um``, away from the field edge, at least ``spacing_um`` apart along a tube, with
the local axis direction of the centre line. The same segments are measured
(:func:`fgat.analysis.morphology.tubule_widths`) on the truth's x-y MIP, on the raw central view
of the light field (the simulation's views are cropped on the volume's lateral grid, one sensor
pixel per sample voxel, and the central lenslet's view has no parallax, so no rescaling is
needed) and on the x-y MIP of each reconstruction. Outputs in ``--out`` (default
``reproduce/results/fig3j[_quick]``): ``widths.csv`` (segment, method, width_um, reason),
``segments.csv``, ``summary.json`` (median width per method, median |width - truth width| over
the segments, the closest method of the five, wall time) and ``widths.png`` (box plots on the
4DGAT MIP with the profiles).

    python reproduce/fig3j.py --quick [--seed 0] [--out DIR] [--tracking-uri sqlite:///mlflow.db]

Without ``--quick`` it runs at the paper's scale (20x/0.45, 300 x 300 x 101; meant for a GPU).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import torch
from scipy.spatial import cKDTree

from fgat.analysis.morphology import Segment, tubule_widths
from fgat.app.callbacks.mlflow import FINGERPRINT
from fgat.app.fingerprint import fingerprint
from fgat.app.lightning_cli import resolved_config, tracking_uri
from fgat.app.recipes.optics import add_trial_arguments, config_args, recipe_configs, trial_args
from fgat.app.trials import fanout_from, run_fits
from fgat.io.files import write_csv
from fgat.io.images import read_tiff, write_tiff
from fgat.optics.acquisition import crop_guard
from fgat.optics.systems import load_system, parse_depths
from fgat.recon.deconvolution import deconvolve
from fgat.recon.scene import phantom_scene
from fgat.sim.simulation import SimulationConfig
from fgat.viz.analysis import plot_tubule_widths

FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
METHODS = ("raw LF (central view)", "SHB", "3DGAT", "SHB (4DGAT PSF)", "4DGAT")
TRUTH = "truth"
PLOT_LABELS = {METHODS[0]: "raw LF\n(central view)", METHODS[3]: "SHB\n(4DGAT PSF)"}


@dataclass(frozen=True)
class TubeSettings:
    """The phantom and the segment selection, in micrometres.

    Attributes
    ----------
    n_tubes : int
        Number of tubes.
    sigma_um : float
        Standard deviation of every tube's Gaussian cross-section; the diameter (FWHM) is
        ``2 sqrt(2 ln 2) sigma_um``.
    bend_um : float
        Largest offset of a tube's Bezier control point from its chord's midpoint (curvature).
    tilt_um : float
        Largest change of a tube's depth from one end to the other.
    isolation_um : float
        Smallest x-y distance from a segment centre to any other tube.
    half_length_um : float
        Half-length of each profile.
    spacing_um : float
        Smallest distance along a tube between two segments.
    edge_um : float
        Smallest distance of a profile's end from the field edge.
    """

    n_tubes: int = 4
    sigma_um: float = 1.0  # FWHM 2.35 um: near the 20x system's 1.9 um lateral resolution
    bend_um: float = 10.0
    tilt_um: float = 6.0
    isolation_um: float = 10.0
    half_length_um: float = 5.0
    spacing_um: float = 4.0
    edge_um: float = 4.0

    @property
    def diameter_um(self) -> float:
        return FWHM_PER_SIGMA * self.sigma_um


# Overrides of the fits: tubes need more Gaussians than the optics recipes' beads.
QUICK_FIT = ("--model.init_args.n_gaussians=800",)
FULL_FIT = ("--model.init_args.n_gaussians=8000",)


def centre_lines(
    shape: tuple[int, int, int],
    voxel_size_um: tuple[float, float, float],
    settings: TubeSettings,
    seed: int,
    samples: int = 4000,
) -> list[np.ndarray]:
    """Per tube, ``(samples, 3)`` centre-line points ``(z, y, x)`` in micrometres (voxel ``i`` at
    ``i * voxel`` on each axis): a quadratic Bezier curve in x-y from one side of the field to the
    opposite one (or an adjacent one), at a depth in the middle 60% of the volume, inclined by up to
    ``tilt_um``."""
    rng = np.random.default_rng(seed)
    extent = (np.asarray(shape) - 1) * np.asarray(voxel_size_um)
    lines = []
    for _ in range(settings.n_tubes):
        # two different sides of the field (0: top, 1: right, 2: bottom, 3: left)
        sides = rng.choice(4, size=2, replace=False)
        ends = []
        for side in sides:
            along = rng.uniform(0.15, 0.85)
            y, x = {0: (0, along), 1: (along, 1), 2: (1, along), 3: (along, 0)}[int(side)]
            ends.append(np.array([y, x]) * extent[1:])
        start, end = ends
        middle = (start + end) / 2 + rng.uniform(-settings.bend_um, settings.bend_um, 2)
        t = np.linspace(0.0, 1.0, samples)[:, None]
        yx = (1 - t) ** 2 * start + 2 * t * (1 - t) * middle + t**2 * end
        z0 = rng.uniform(0.2, 0.8) * extent[0]
        tilt = rng.uniform(-settings.tilt_um, settings.tilt_um)
        z = np.clip(z0 + tilt * (t[:, 0] - 0.5), 0.0, extent[0])
        lines.append(np.column_stack([z, yx]))
    return lines


def tube_phantom(
    shape: tuple[int, int, int],
    voxel_size_um: tuple[float, float, float],
    settings: TubeSettings,
    seed: int,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """The tube volume ``(Z, Y, X)`` (float32, maximum 1: each voxel the largest of the tubes'
    ``exp(-d^2 / (2 sigma^2))``, ``d`` its distance in micrometres to a centre line) and the
    centre lines (:func:`centre_lines`)."""
    lines = centre_lines(shape, voxel_size_um, settings, seed)
    grid = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1)
    points = (grid * np.asarray(voxel_size_um)).reshape(-1, 3)
    reach = 5.0 * settings.sigma_um
    volume = np.zeros(len(points))
    for line in lines:
        distance, _ = cKDTree(line).query(points, distance_upper_bound=reach)
        inside = np.isfinite(distance)
        volume[inside] = np.maximum(
            volume[inside], np.exp(-0.5 * (distance[inside] / settings.sigma_um) ** 2)
        )
    volume = volume.reshape(shape)
    return (volume / volume.max()).astype(np.float32), lines


def select_segments(
    lines: list[np.ndarray],
    shape_yx: tuple[int, int],
    pixel_um: float,
    settings: TubeSettings,
) -> pd.DataFrame:
    """Isolated tubule segments of the centre lines, in pixels of the x-y grid.

    A centre-line point qualifies when its x-y distance to every other tube's centre line, and to
    the points of its own tube farther than ``isolation_um`` along it (a tube bending back), is at
    least ``isolation_um``, and its profile (``half_length_um`` each side, perpendicular to the
    local axis) stays ``edge_um`` inside the field; along each tube, qualifying points are taken
    greedily ``spacing_um`` apart. Returns the columns of
    :data:`fgat.analysis.morphology.SEGMENT_COLUMNS` plus ``tube``."""
    rows = []
    half = settings.half_length_um / pixel_um
    low = settings.edge_um / pixel_um
    high = np.asarray(shape_yx, dtype=float) - 1 - low
    for index, line in enumerate(lines):
        yx = line[:, 1:]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(yx, axis=0), axis=1))])
        others = [other[:, 1:] for k, other in enumerate(lines) if k != index]
        clearance = np.full(len(yx), np.inf)
        if others:
            clearance = cKDTree(np.concatenate(others)).query(yx)[0]
        tangent = np.gradient(yx, axis=0)
        last = -np.inf
        for i in range(len(yx)):
            if arc[i] - last < settings.spacing_um or clearance[i] < settings.isolation_um:
                continue
            far = np.abs(arc - arc[i]) > settings.isolation_um
            if far.any() and np.linalg.norm(yx[far] - yx[i], axis=1).min() < settings.isolation_um:
                continue
            angle = math.atan2(tangent[i, 0], tangent[i, 1])
            segment = Segment(tuple(yx[i] / pixel_um), angle, half)
            ends = np.array(segment.profile_endpoints())
            if np.any(ends < low) or np.any(ends > high):
                continue
            rows.append(
                {
                    "tube": index,
                    "center_y": segment.center_yx[0],
                    "center_x": segment.center_yx[1],
                    "axis_angle_rad": angle,
                    "half_length_px": half,
                }
            )
            last = arc[i]
    return pd.DataFrame(
        rows, columns=["tube", "center_y", "center_x", "axis_angle_rad", "half_length_px"]
    )


def grid_of(configs: list[str], seed: int) -> tuple[tuple[int, int, int], tuple[float, ...]]:
    """The simulation grid ``(Z, Y, X)`` and voxel size (um) of ``configs``."""
    resolved = resolved_config(
        ["fit", *config_args(configs), f"--data.init_args.simulation.seed={seed}"]
    )
    simulation = SimulationConfig(**resolved["data"]["init_args"]["simulation"])
    depths = parse_depths(simulation.depths_um)
    voxel = load_system(simulation.system).grid_voxel_size_um(depths)
    return (len(depths), simulation.view_size, simulation.view_size), tuple(voxel)


def finished_run(uri: str, experiment: str, args: list[str]) -> mlflow.entities.Run:
    """The latest finished run of ``experiment`` with the fingerprint of ``args``."""
    digest = fingerprint(resolved_config(args)).digest
    client = mlflow.MlflowClient(uri)
    found = client.get_experiment_by_name(experiment)
    runs = client.search_runs(
        [found.experiment_id],
        filter_string=f"attributes.status = 'FINISHED' and tags.`{FINGERPRINT}` = '{digest}'",
        order_by=["attributes.start_time DESC"],
    )
    if not runs:
        raise SystemExit(f"{experiment}: no finished run with fingerprint {digest[:8]}")
    return runs[0]


def artifact(run, name: str, folder: Path, uri: str) -> Path:
    return Path(
        mlflow.artifacts.download_artifacts(
            run_id=run.info.run_id,
            artifact_path=name,
            dst_path=str(folder / run.info.run_name),
            tracking_uri=uri,
        )
    )


def shb_with_psf(args: list[str], psf_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """SHB of the trial's simulated views with the PSF stack ``psf_path`` as the static stage's
    baseline is computed (iterations, mask, guard band; in counts), and the central raw view
    (counts above the background)."""
    resolved = resolved_config(args)
    simulation = SimulationConfig(**resolved["data"]["init_args"]["simulation"])
    iterations = resolved["model"]["init_args"]["baseline_iterations"]
    scene = phantom_scene(simulation, str(psf_path))
    mask = None if scene.mask is None else torch.tensor(scene.mask, dtype=torch.float32)
    volume = deconvolve(
        torch.tensor(scene.measurement, dtype=torch.float32),
        scene.operator(torch.tensor(scene.psf, dtype=torch.float32)),
        iterations,
        method="shb",
        weights=mask,
    )
    system = load_system(simulation.system)
    centers = np.asarray(system.lenslet_centers_px())
    central = int(np.argmin(np.linalg.norm(centers - np.asarray(system.optical_axis_px), axis=1)))
    views = np.asarray(scene.measurement) * scene.scale
    return crop_guard(volume.numpy(), scene.guard_px) * scene.scale, views[central]


def summarise(widths: pd.DataFrame, diameter_um: float) -> dict:
    """Median width per method, median |width - truth's width| over the segments measured on
    both, and the closest of the five methods."""
    table = widths.pivot(index="segment", columns="method", values="width_um")
    methods = (TRUTH, *METHODS)
    summary = {
        "diameter_um": diameter_um,
        "median_width_um": {m: float(np.nanmedian(table[m])) for m in methods},
        "median_abs_error_um": {
            m: float(np.nanmedian((table[m] - table[TRUTH]).abs())) for m in METHODS
        },
        "measured": {m: int(np.isfinite(table[m]).sum()) for m in methods},
    }
    errors = summary["median_abs_error_um"]
    summary["closest"] = min(errors, key=lambda m: np.inf if math.isnan(errors[m]) else errors[m])
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="CPU scale")
    parser.add_argument("--seed", type=int, default=0, help="phantom, optics and noise draw")
    parser.add_argument(
        "--sigma-um",
        type=float,
        default=TubeSettings.sigma_um,
        help="the tubes' Gaussian cross-section s.d. in um (FWHM 2.355 x this)",
    )
    add_trial_arguments(parser)
    parser.set_defaults(out=None)
    args = parser.parse_args()
    started = time.perf_counter()
    experiment = "fig3j" + ("_quick" if args.quick else "")
    out = Path(args.out or f"reproduce/results/{experiment}")
    out.mkdir(parents=True, exist_ok=True)
    configs = recipe_configs("figS6", args.quick)
    uri = tracking_uri(args.tracking_uri)
    settings = TubeSettings(sigma_um=args.sigma_um)
    shape, voxel = grid_of(configs, args.seed)
    truth, lines = tube_phantom(shape, voxel, settings, args.seed)
    phantom_path = out / f"tubes_seed{args.seed}.ome.tif"
    if not phantom_path.is_file() or not np.array_equal(read_tiff(phantom_path), truth):
        write_tiff(phantom_path, truth, axes="ZYX")
    phantom = json.dumps({"kind": "reticular", "path": str(phantom_path)})
    trials = {
        method: [
            *trial_args(configs, experiment, uri, args.seed, method, "zernike"),
            f"--data.init_args.simulation.phantom={phantom}",
            *(QUICK_FIT if args.quick else FULL_FIT),
        ]
        for method in ("4DGAT", "3DGAT")
    }
    if not args.summary_only:
        fits = [
            (trial, f"runs/{experiment}/{method}-seed{args.seed}")
            for method, trial in trials.items()
        ]
        run_fits(fits, fanout_from(args), refit=args.refit, label=experiment)
    four, three = (finished_run(uri, experiment, trials[m]) for m in ("4DGAT", "3DGAT"))
    downloads = out / "runs"
    shb_estimated, raw = shb_with_psf(
        trials["4DGAT"], artifact(four, "psf.ome.tif", downloads, uri)
    )
    images = {
        TRUTH: truth,
        METHODS[0]: raw,
        "SHB": read_tiff(artifact(four, "shb.ome.tif", downloads, uri), ndim=3),
        "3DGAT": read_tiff(artifact(three, "volume.ome.tif", downloads, uri), ndim=3),
        "SHB (4DGAT PSF)": shb_estimated,
        "4DGAT": read_tiff(artifact(four, "volume.ome.tif", downloads, uri), ndim=3),
    }
    segments = select_segments(lines, shape[1:], voxel[2], settings)
    if segments.empty:
        raise SystemExit("no isolated tubule segment in this phantom: try another --seed")
    write_csv(out / "segments.csv", list(segments.columns), segments.to_dict("records"))
    tables = []
    for method, image in images.items():
        size = voxel if np.ndim(image) == 3 else voxel[1:]
        table = tubule_widths(image, segments, voxel_size_um=size)
        tables.append(table.assign(method=method))
    widths = pd.concat(tables)[["segment", "method", "width_um", "reason"]]
    write_csv(out / "widths.csv", list(widths.columns), widths.to_dict("records"))
    summary = summarise(widths, settings.diameter_um)
    summary.update(
        seed=args.seed,
        quick=args.quick,
        segments=len(segments),
        wall_time_s=round(time.perf_counter() - started, 1),
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    profiles = [
        Segment(*row).profile_endpoints()
        for row in zip(
            zip(segments.center_y, segments.center_x),
            segments.axis_angle_rad,
            segments.half_length_px,
        )
    ]
    plot_tubule_widths(
        images["4DGAT"].max(axis=0),
        profiles,
        {PLOT_LABELS.get(m, m): widths.width_um[widths.method == m].to_numpy() for m in images},
        out / "widths.png",
        title=f"tubule widths, seed {args.seed} (known diameter {settings.diameter_um:.2f} um)",
    )
    print(f"{'method':22s} {'median width um':>16s} {'median |error| um':>18s} {'measured':>9s}")
    for method in images:
        error = summary["median_abs_error_um"].get(method, 0.0)
        print(
            f"{method:22s} {summary['median_width_um'][method]:16.3f} {error:18.3f} "
            f"{summary['measured'][method]:>5d}/{len(segments)}"
        )
    verdict = "met" if summary["closest"] == "4DGAT" else "NOT met"
    print(
        f"closest to the truth: {summary['closest']} (target: 4DGAT, {verdict}); "
        f"wall time {summary['wall_time_s']} s -> {out}"
    )
