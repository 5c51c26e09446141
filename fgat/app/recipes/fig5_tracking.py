"""Fig. 5h-j on a phantom with a known answer: speed classes and anomalous diffusion of cells.

A 1:5 mixture of magnetically driven (drift along +x plus diffusion) and free (Brownian) cells
(:func:`fgat.analysis.tracking.driven_and_free_tracks`) is drawn as Gaussian blobs on the grid of
the small CPU system (``load_system("small")``, 31 x 64 x 64 voxels of 1.5 x 0.975 x 0.975 um,
depths -22.5..22.5 um, as in configs/base/common.yaml), projected through the FLFM forward model
(the ideal JPGM PSF stack of :func:`fgat.sim.simulation.true_psf_model`, placed on the sensor and
cropped back as :func:`fgat.sim.simulation.simulate` does) with fgat's camera
(:func:`fgat.sim.simulation.camera`: one photon scale per sequence, Poisson noise on a background,
independent noise per frame), reconstructed by each of ``methods``: 4DGAT (:func:`dynamic_volumes`:
the static stage on the middle frame, then the HexPlane + MLP deformation fitted to all frames,
one temporal plane sample per frame; the known PSF) and, as the baseline, SHB frame by frame
(:func:`fgat.recon.deconvolution.deconvolve`); each method's volumes are analysed as in Note S8.9:
``track`` (trackpy 3D locate and link), ``mean_speeds`` of sliding windows, ``speed_threshold``
(density minimum of the log mean speeds), ``msd`` and ``anomalous_exponent`` per trajectory.

The non-quick setting (``FULL``: 20 fields, 240 cells, 100 SHB iterations per frame) is the same
pipeline as ``--quick`` (``QUICK``: 5 fields, 60 cells, 50 iterations; see README for its time),
with more cells in the speed distribution.

Motion (``TrackingConfig``): 25 frames 0.1 s apart; every cell diffuses with D = 0.5 um^2/s (free
cells: mean sliding speed about 2 um/s over the 5-frame window), driven cells also drift at
15 um/s along +x (36 um over the recording, inside the 62 um field), so the true antimode falls
near 7 um/s, close to the paper's 8.27 um/s; cells are blobs of 1.2 um std, imaged at
10^4 photons at the brightest sensor pixel on a background of 100 (configs/base/common.yaml).

Phantom. The small system sees 62 x 62 x 46 um, so the phantom is split into independent fields
of view (``n_fields`` acquisitions of ``cells_per_field`` cells each, pooled for the speed
distribution, as cells pooled over several recordings). Every cell takes its random walk from
``driven_and_free_tracks`` (one seed per field); the recipe then chooses the starting points
(random sequential placement) so that every cell stays inside the reconstructed volume away
from its edges (driven cells start on the low-x side and cross towards +x) and no two cells come
closer than ``min_distance_um`` at any frame (axial distances counted at half weight, the
reconstruction being longer along z): tracking errors from cells that touch are not what this
figure measures. Cells that leave the grid anyway end their tracks there (counted in the
summary).

Truth. The true threshold is ``speed_threshold`` (the same KDE antimode) of the true cells' mean
speeds, computed with the same sliding window on the noiseless phantom positions; true alphas
likewise. A found track is matched to the true cell of its field nearest to its first position at
its first frame; each true cell is represented by its longest matched track, and a cell without
a track counts as misclassified.

    python reproduce/fig5_tracking.py [--quick] [--seed N] [--out DIR]

writes to OUT (default reproduce/results/fig5_tracking[_quick]/) summary.json (every method's
summary, the headline method's pass/fail: 4DGAT's when it ran) and, per method in OUT/<method>/,
trajectories.csv (found tracks), truth_trajectories.csv, cells.csv (per true cell: mean speed,
alpha and class, true and found), summary.json, speed_histogram.png, msd_curves.png and
trajectories.png; and prints each method's numbers beside the acceptance targets (alpha of free
cells within 0.15 of 1, of driven cells above 1.6; threshold within 15% of the true antimode;
>= 90% of cells in the right class).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from fgat.analysis.tracking import (
    anomalous_exponent,
    driven_and_free_tracks,
    mean_speeds,
    msd,
    speed_threshold,
    track,
)
from fgat.app.recipes.flfm_phantoms import (
    fit_static,
    flfm_optics,
    grid,
    image_sequence,
    recipe_main,
)
from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.io.files import atomic_path, write_csv
from fgat.recon import Scene
from fgat.recon.deconvolution import deconvolve
from fgat.recon.dynamic import DynamicReconstruction, DynamicSettings
from fgat.recon.scene import normalized_measurement
from fgat.viz.analysis import plot_msd_curves, plot_trajectories
from fgat.viz.figures import pyplot, save_figure

CLASSES = ("free", "driven")
METHODS = ("shb", "4dgat")
TARGETS = {
    "alpha_free_tolerance": 0.15,
    "alpha_driven_min": 1.6,
    "threshold_tolerance": 0.15,
    "fraction_right_min": 0.90,
}


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """One run of the recipe (``QUICK``, ``FULL``; tests shrink it)."""

    n_fields: int = 10
    cells_per_field: int = 12  # 1:5 -> 2 driven, 10 free per field
    n_frames: int = 25
    frame_interval_s: float = 0.1
    diffusion_um2_s: float = 0.5  # every cell (driven_and_free_tracks: one D for all)
    drift_um_s: float = 15.0  # driven cells, along +x
    cell_sigma_um: float = 1.2  # Gaussian blob std (FWHM 2.8 um)
    min_distance_um: float = 7.0  # between any two cells at any frame (z at half weight)
    edge_margin_um: tuple = (10.0, 8.0, 8.0)  # (z, y, x) from the grid's faces at the start
    system: str = "small"
    depths_um: str = "-22.5:22.5:31"
    view_size: int = 64
    photons: float = 10000.0  # configs/base/common.yaml
    background: float = 100.0
    methods: tuple = ("shb", "4dgat")
    iterations: int = 50  # SHB per frame
    n_gaussians: int = 1500  # 4DGAT: canonical Gaussians of the static stage (middle frame)
    init_iterations: int = 20  # SHB iterations seeding them
    static_steps: int = 300
    dynamic_steps: int = 1500  # deformation steps, one frame each (60 passes over 25 frames)
    hexplane_resolution: int = 16  # spatial planes (the temporal ones: one per frame)
    window: int = 5  # sliding-speed window, frames
    diameter_um: tuple = (11.0, 8.5, 8.5)  # trackpy masks: ~7 std of the reconstructed blobs
    separation_um: tuple = (6.0, 4.0, 4.0)
    search_range_um: float = 4.0
    min_track_frames: int = 12  # shorter tracks are stubs, left out of the analysis
    seed: int = 0


QUICK = TrackingConfig(n_fields=5)
FULL = TrackingConfig(n_fields=20, iterations=100)


def main(results: Path, argv: list[str] | None = None) -> None:
    """The command line (:func:`fgat.app.recipes.flfm_phantoms.recipe_main`).

    Parameters
    ----------
    results : Path
        The folder of the recipes' results (``reproduce/results``): the default ``--out`` is
        ``results/fig5_tracking[_quick]``.
    argv : list of str, optional
        The arguments (default: the command line's).
    """
    recipe_main(
        argv,
        globals(),
        name="fig5_tracking",
        results=results,
        quick_help="5 fields of 12 cells, 4DGAT and SHB (50 iterations)",
    )


def _pair_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-frame distance of two ``(T, 3)`` tracks with the axial difference at half weight."""
    step = a - b
    return np.sqrt((step[..., 0] / 2) ** 2 + step[..., 1] ** 2 + step[..., 2] ** 2)


def place_cells(
    walks: np.ndarray, driven: np.ndarray, extent_um: np.ndarray, config: TrackingConfig, rng
) -> np.ndarray:
    """Starting points for the ``(N, T, 3)`` walks (from 0): uniform in the grid less the edge
    margins (driven cells: the x range that their whole walk stays inside), drawn again until no
    earlier-placed cell comes within ``min_distance_um`` at any frame; driven cells go first."""
    margin = np.asarray(config.edge_margin_um, dtype=np.float64)
    starts = np.zeros((len(walks), 3))
    placed: list[int] = []
    for cell in np.argsort(~driven, kind="stable"):
        low = margin - walks[cell].min(axis=0).clip(max=0)
        high = extent_um - margin - walks[cell].max(axis=0).clip(min=0)
        if np.any(high <= low):
            raise ValueError(
                f"a walk of {np.ptp(walks[cell], axis=0).round(1)} um does not fit the "
                f"{extent_um.round(1)} um grid with margins {margin}: fewer frames or less drift"
            )
        for _ in range(10000):
            start = rng.uniform(low, high)
            if all(
                _pair_distance(start + walks[cell], starts[other] + walks[other]).min()
                >= config.min_distance_um
                for other in placed
            ):
                break
        else:
            raise ValueError(
                f"cannot place {len(walks)} cells {config.min_distance_um} um apart in the grid: "
                "fewer cells_per_field or a smaller min_distance_um"
            )
        starts[cell] = start
        placed.append(int(cell))
    return starts[:, None, :] + walks


def phantom(config: TrackingConfig) -> tuple[np.ndarray, np.ndarray]:
    """True positions ``(F, N, T, 3)`` (z, y, x um) and ``(F, N)`` driven flags of all fields."""
    _, _, shape, voxel = grid(config)
    extent = np.asarray(shape) * voxel
    positions, flags = [], []
    for field in range(config.n_fields):
        tracks, driven = driven_and_free_tracks(
            config.cells_per_field,
            n_frames=config.n_frames,
            frame_interval_s=config.frame_interval_s,
            diffusion_um2_s=config.diffusion_um2_s,
            drift_um_s=config.drift_um_s,
            seed=config.seed * 1000 + field,
        )
        walks = tracks - tracks[:, :1]
        rng = np.random.default_rng([config.seed, field, 1])
        positions.append(place_cells(walks, driven, extent, config, rng))
        flags.append(driven)
    return np.stack(positions), np.stack(flags)


def render(centres_um: np.ndarray, shape, voxel_um: np.ndarray, sigma_um: float) -> np.ndarray:
    """Volume ``(Z, Y, X)`` of unit-peak Gaussian blobs of std ``sigma_um`` at ``(N, 3)`` centres
    (voxel ``i`` centred at ``(i + 0.5) voxel``); blobs outside the grid add only their tails."""
    axes = [(np.arange(n) + 0.5) * v for n, v in zip(shape, voxel_um)]
    volume = np.zeros(shape)
    for centre in centres_um:
        z, y, x = (np.exp(-0.5 * ((a - c) / sigma_um) ** 2) for a, c in zip(axes, centre))
        volume += z[:, None, None] * y[None, :, None] * x[None, None, :]
    return volume


def reconstruct_field(
    positions: np.ndarray, field: int, config: TrackingConfig, optics: dict
) -> dict[str, np.ndarray]:
    """``{method: (T, Z, Y, X)}`` volumes of one field: blobs -> views -> sensor with fgat's
    camera (the sequence's photon scale, noise seed ``(seed + field, frame)``) -> views ->
    SHB per frame and 4DGAT (:func:`dynamic_volumes`), as ``config.methods`` asks."""
    shape, voxel, operator = optics["shape"], optics["voxel"], optics["op"]
    frames = (
        render(positions[:, frame], shape, voxel, config.cell_sigma_um)
        for frame in range(config.n_frames)
    )
    sensor = image_sequence(frames, config, optics, config.seed * 1000 + field)
    volumes = {}
    if "shb" in config.methods:
        volumes["shb"] = np.stack(
            [
                deconvolve(
                    torch.from_numpy(views),
                    operator,
                    config.iterations,
                    background=config.background,
                ).numpy()
                for views in sensor
            ]
        )
    if "4dgat" in config.methods:
        volumes["4dgat"] = dynamic_volumes(sensor, config, optics)
    return volumes


def dynamic_volumes(sensor: np.ndarray, config: TrackingConfig, optics: dict) -> np.ndarray:
    """4DGAT on one field's views ``(T, V, Y, X)``: the static stage on the middle frame
    (canonical Gaussians seeded from SHB, the known PSF, no densification), then the HexPlane +
    MLP deformation fitted to every frame; the volumes ``(T, Z, Y, X)`` at the frame times, in
    units of the reference frame's peak view."""
    reference = config.n_frames // 2
    views, scale = normalized_measurement(sensor, config.background, reference=reference)
    scene = Scene(
        measurement=views[reference],
        scale=scale,
        psf=optics["psf"].numpy(),
        voxel_size_um=tuple(float(v) for v in optics["voxel"]),
        name="tracking field",
        frames=views,
        times=np.linspace(0.0, 1.0, config.n_frames),
        reference=reference,
    )
    static = fit_static(scene, config, steps=config.static_steps, n_gaussians=config.n_gaussians)
    resolution = (config.hexplane_resolution,) * 3
    dynamic = DynamicReconstruction.from_static(
        scene,
        static.cloud,
        static.psf,
        hexplane=HexPlaneSettings(
            spatial_resolution=resolution, temporal_resolution=config.n_frames
        ),
        settings=DynamicSettings(seed=config.seed),
    )
    torch.manual_seed(config.seed)  # the order of the frames in each pass
    for _ in range(config.dynamic_steps):
        dynamic.step()
    return dynamic.volumes()


def truth_table(positions: np.ndarray, driven: np.ndarray, config: TrackingConfig) -> pd.DataFrame:
    """The noiseless phantom tracks as a trajectory table (one ``particle`` per cell: ``field *
    cells_per_field + cell``), with ``field``, ``cell`` and ``driven``."""
    n_fields, n_cells, n_frames, _ = positions.shape
    field, cell, frame = np.meshgrid(
        np.arange(n_fields), np.arange(n_cells), np.arange(n_frames), indexing="ij"
    )
    table = pd.DataFrame(
        {
            "field": field.ravel(),
            "cell": cell.ravel(),
            "particle": (field * n_cells + cell).ravel(),
            "frame": frame.ravel(),
            "t_s": frame.ravel() * config.frame_interval_s,
            "driven": driven[field.ravel(), cell.ravel()],
        }
    )
    table[["z", "y", "x"]] = positions.reshape(-1, 3)
    return table


def track_alpha(table: pd.DataFrame) -> float:
    """alpha of one particle's track (frames in a row, gaps as NaN; default fit range)."""
    frames = table["frame"].to_numpy()
    positions = np.full((frames.max() - frames.min() + 1, 3), np.nan)
    positions[frames - frames.min()] = table[["z", "y", "x"]].to_numpy()
    lags, values = msd(positions)
    return anomalous_exponent(lags, values)


def per_track(table: pd.DataFrame, window: int) -> pd.DataFrame:
    """Per particle: field, first frame and position, frames, mean speed (um/s) and alpha."""
    speeds = mean_speeds(table, window)
    rows = []
    for particle, group in table.groupby("particle"):
        first = group.iloc[0]
        rows.append(
            {
                "particle": particle,
                "field": int(first["field"]),
                "first_frame": int(first["frame"]),
                "z0": first["z"],
                "y0": first["y"],
                "x0": first["x"],
                "frames": len(group),
                "mean_speed_um_s": speeds.get(particle, np.nan),
                "alpha": track_alpha(group),
            }
        )
    return pd.DataFrame(rows)


def match_tracks(found: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """``found``'s per-track table with ``cell`` and ``match_um``: the true cell of the same
    field nearest to the track's first position at its first frame."""
    found = found.copy()
    cells, distances = [], []
    for row in found.itertuples():
        candidates = truth[(truth["field"] == row.field) & (truth["frame"] == row.first_frame)]
        step = candidates[["z", "y", "x"]].to_numpy() - np.array([row.z0, row.y0, row.x0])
        distance = np.linalg.norm(step, axis=1)
        cells.append(int(candidates["cell"].iloc[np.argmin(distance)]))
        distances.append(float(distance.min()))
    found["cell"], found["match_um"] = cells, distances
    return found


def cells_outside(positions: np.ndarray, extent_um: np.ndarray) -> int:
    """Cells whose true centre leaves the grid ``[0, extent]`` in some frame."""
    outside = np.any((positions < 0) | (positions > extent_um), axis=(-1, -2))
    return int(outside.sum())


def run(config: TrackingConfig, out: Path, *, log=print) -> dict:
    """The whole recipe into ``out`` (one folder per method); returns the summary (also written
    as summary.json): every method's own summary under ``methods``, the headline method's
    (4DGAT when it ran) ``passed``."""
    start = time.perf_counter()
    unknown = sorted(set(config.methods) - set(METHODS))
    if not config.methods or unknown:
        raise ValueError(f"methods must be some of {METHODS}, got {config.methods!r}")
    out.mkdir(parents=True, exist_ok=True)
    positions, driven = phantom(config)
    optics = flfm_optics(config)
    shape, voxel = optics["shape"], optics["voxel"]
    tables = {method: [] for method in config.methods}
    for field in range(config.n_fields):
        for method, volumes in reconstruct_field(positions[field], field, config, optics).items():
            tables[method].append(locate_and_link(volumes, field, voxel, config))
        log(
            f"field {field + 1}/{config.n_fields}: "
            + ", ".join(f"{m} {t[-1]['particle'].nunique()} tracks" for m, t in tables.items())
            + f" ({time.perf_counter() - start:.0f} s)"
        )
    truth = truth_table(positions, driven, config)
    summaries = {}
    for method, found in tables.items():
        trajectories = pd.concat(found, ignore_index=True)
        summary, cells, tracks = analyse(trajectories, truth, positions, shape, voxel, config)
        summary["wall_s"] = time.perf_counter() - start
        write_outputs(out / method, trajectories, truth, cells, tracks, summary, config)
        summaries[method] = summary
    headline = "4dgat" if "4dgat" in summaries else config.methods[0]
    summary = {
        "config": dataclasses.asdict(config),
        "methods": summaries,
        "headline": headline,
        "passed": summaries[headline]["passed"],
        "wall_s": time.perf_counter() - start,
    }
    with atomic_path(out / "summary.json") as temporary:
        temporary.write_text(json.dumps(summary, indent=2, default=float))
    return summary


def locate_and_link(volumes: np.ndarray, field: int, voxel, config: TrackingConfig):
    """:func:`track` on one field's volumes ``(T, Z, Y, X)``, particles numbered per field."""
    # trackpy's band pass zeroes values below 1/255 of float volumes: unit-peak volumes
    volumes = volumes / max(float(volumes.max()), 1e-30)
    found = track(
        volumes,
        voxel_size_um=voxel,
        frame_interval_s=config.frame_interval_s,
        diameter_um=config.diameter_um,
        search_range_um=config.search_range_um,
        separation_um=config.separation_um,
        minmass=None,
    )
    found.insert(0, "field", field)
    found["particle"] = field * 10000 + found["particle"]
    return found


def analyse(trajectories, truth, positions, shape, voxel, config: TrackingConfig):
    """One method's tracks against the truth: ``(summary, cells, tracks)``, the summary with the
    threshold, classes, alphas and tracking counts beside the targets."""
    lengths = trajectories.groupby("particle")["frame"].transform("size")
    kept = trajectories[lengths >= config.min_track_frames]
    if kept.empty:
        raise ValueError(f"no track of {config.min_track_frames} frames or more was found")
    tracks = match_tracks(per_track(kept, config.window), truth)
    true_cells = per_track(truth, config.window)
    true_cells["cell"] = truth.groupby("particle")["cell"].first().to_numpy()
    true_cells["driven"] = truth.groupby("particle")["driven"].first().to_numpy()

    threshold = speed_threshold(tracks["mean_speed_um_s"].dropna())
    true_threshold = speed_threshold(true_cells["mean_speed_um_s"])
    tracks["class_found"] = np.where(tracks["mean_speed_um_s"] > threshold, "driven", "free")

    best = tracks.sort_values("frames", ascending=False).drop_duplicates(["field", "cell"])
    cells = true_cells.merge(
        best, on=["field", "cell"], how="left", suffixes=("_true", "_found")
    ).sort_values(["field", "cell"])
    cells["class_true"] = np.where(cells["driven"], "driven", "free")
    cells["class_found"] = cells["class_found"].fillna("none")
    cells["correct"] = cells["class_found"] == cells["class_true"]
    n_cells = len(cells)
    tracked = cells["particle_found"].notna()

    alpha = {}
    for name in CLASSES:
        chosen = cells[(cells["class_true"] == name) & tracked]["alpha_found"]
        alpha[name] = {
            "mean": float(chosen.mean()),
            "median": float(chosen.median()),
            "sd": float(chosen.std()),
            "n": int(chosen.size),
            "true_mean": float(cells[cells["class_true"] == name]["alpha_true"].mean()),
        }
    threshold_error = abs(threshold - true_threshold) / true_threshold
    fraction_right = float(cells["correct"].sum() / n_cells)
    summary = {
        "threshold_um_s": threshold,
        "true_antimode_um_s": true_threshold,
        "true_antimode_method": (
            "speed_threshold (Scott-bandwidth KDE of log mean speeds, density minimum between the "
            f"two highest modes) of the true cells' mean speeds, window {config.window} frames, "
            "on the noiseless phantom positions"
        ),
        "threshold_relative_error": threshold_error,
        "fraction_right": fraction_right,
        "fraction_right_of_tracked": float(cells[tracked]["correct"].mean()),
        "alpha": alpha,
        "tracking": {
            "cells": n_cells,
            "driven_cells": int(cells["driven"].sum()),
            "cells_tracked": int(tracked.sum()),
            "cells_leaving_grid": cells_outside(positions, np.asarray(shape) * voxel),
            "tracks_found": int(trajectories["particle"].nunique()),
            "tracks_kept": int(len(tracks)),
            "stubs_dropped": int(trajectories["particle"].nunique() - len(tracks)),
            "cells_with_several_tracks": int((tracks.groupby(["field", "cell"]).size() > 1).sum()),
            "tracks_matched_farther_than_2um": int((tracks["match_um"] > 2.0).sum()),
            "mean_track_frames_of_cells": float(cells["frames_found"].mean()),
            "frames": config.n_frames,
        },
        "targets": TARGETS,
        "passed": {
            "alpha_free": abs(alpha["free"]["mean"] - 1) <= TARGETS["alpha_free_tolerance"],
            "alpha_driven": alpha["driven"]["mean"] > TARGETS["alpha_driven_min"],
            "threshold": threshold_error <= TARGETS["threshold_tolerance"],
            "fraction_right": fraction_right >= TARGETS["fraction_right_min"],
        },
    }
    return summary, cells, tracks


def speed_histogram(speeds: dict, path: Path, lines: dict) -> Path:
    """Mean speeds per class stacked on log-spaced bins (log x), with vertical ``lines``
    (``{label: speed}``: the threshold found and the true antimode)."""
    plt = pyplot()
    from matplotlib import ticker  # matplotlib loaded when a figure is drawn: keeps start-up fast

    every = np.concatenate([np.asarray(v, dtype=float) for v in speeds.values()])
    every = every[np.isfinite(every) & (every > 0)]
    bins = np.logspace(np.log10(every.min()) - 0.05, np.log10(every.max()) + 0.05, 31)
    figure, axis = plt.subplots(figsize=(5.4, 3.8))
    axis.hist(list(speeds.values()), bins=bins, stacked=True, label=list(speeds))
    for (label, speed), style in zip(lines.items(), ("--", ":")):
        axis.axvline(speed, color="black", linestyle=style, label=label)
    axis.set_xscale("log")
    axis.xaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.xaxis.set_major_formatter(ticker.ScalarFormatter())
    axis.xaxis.set_minor_formatter(ticker.NullFormatter())
    axis.set_xlabel("mean speed (um/s)")
    axis.set_ylabel("tracks")
    axis.legend(fontsize=8)
    figure.suptitle("Mean speeds of the tracks, by true class", fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)


def _rows(table: pd.DataFrame, columns: list[str]):
    return table[columns].itertuples(index=False, name=None)


def write_outputs(out, trajectories, truth, cells, tracks, summary, config) -> None:
    """CSV tables, summary.json and the three figures of one method, in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    columns = ["field", "particle", "frame", "t_s", "z", "y", "x", "mass"]
    write_csv(out / "trajectories.csv", columns, _rows(trajectories, columns))
    columns = ["field", "cell", "particle", "frame", "t_s", "z", "y", "x", "driven"]
    write_csv(out / "truth_trajectories.csv", columns, _rows(truth, columns))
    table = cells.rename(
        columns={
            "particle_found": "track",
            "frames_found": "track_frames",
            "mean_speed_um_s_true": "mean_speed_true_um_s",
            "mean_speed_um_s_found": "mean_speed_um_s",
            "alpha_found": "alpha",
        }
    )
    table["track"] = table["track"].astype("Int64")
    table["track_frames"] = table["track_frames"].astype("Int64")
    columns = ["field", "cell", "track", "track_frames", "match_um", "mean_speed_um_s", "alpha"]
    columns += ["class_found", "class_true", "correct", "mean_speed_true_um_s", "alpha_true"]
    write_csv(out / "cells.csv", columns, _rows(table, columns))
    with atomic_path(out / "summary.json") as temporary:
        temporary.write_text(json.dumps(summary, indent=2, default=float))

    matched = tracks.merge(
        cells[["field", "cell", "class_true"]], on=["field", "cell"], how="left"
    ).set_index("particle")
    classes = matched["class_true"]
    speeds = {
        name: matched.loc[classes == name, "mean_speed_um_s"].dropna().to_numpy()
        for name in CLASSES
    }
    speed_histogram(
        speeds,
        out / "speed_histogram.png",
        {
            f"threshold {summary['threshold_um_s']:.2f} um/s": summary["threshold_um_s"],
            f"true antimode {summary['true_antimode_um_s']:.2f} um/s": summary[
                "true_antimode_um_s"
            ],
        },
    )
    curves, paths = {name: [] for name in CLASSES}, {name: [] for name in CLASSES}
    kept = trajectories[trajectories["particle"].isin(matched.index)]
    for particle, group in kept.groupby("particle"):
        name = classes[particle]
        frames = group["frame"].to_numpy()
        positions = np.full((frames.max() - frames.min() + 1, 3), np.nan)
        positions[frames - frames.min()] = group[["z", "y", "x"]].to_numpy()
        lags, values = msd(positions)
        curves[name].append((lags * config.frame_interval_s, values))
        if group["field"].iloc[0] == 0:
            paths[name].append(group[["x", "y"]].to_numpy())
    alpha = summary["alpha"]
    plot_msd_curves(
        {
            f"{name}: alpha {alpha[name]['mean']:.2f} (mean), {alpha[name]['median']:.2f} "
            "(median)": curves[name]
            for name in CLASSES
        },
        out / "msd_curves.png",
        title="MSD of the tracks (Eq. S62), coloured by true class",
    )
    plot_trajectories(
        paths, out / "trajectories.png", title="Tracks of field 0, coloured by true class"
    )


def report(summary: dict) -> str:
    """Every method's numbers beside the acceptance targets (the headline method's decide)."""
    return "\n\n".join(
        f"{method.upper()}{' (headline)' if method == summary['headline'] else ''}\n"
        + method_report(part)
        for method, part in summary["methods"].items()
    )


def method_report(summary: dict) -> str:
    """The short table of one method's numbers beside the acceptance targets."""
    alpha, tracking, passed = summary["alpha"], summary["tracking"], summary["passed"]
    rows = [
        ("alpha free (mean)", f"{alpha['free']['mean']:.3f}", "1 +- 0.15", passed["alpha_free"]),
        ("alpha driven (mean)", f"{alpha['driven']['mean']:.3f}", "> 1.6", passed["alpha_driven"]),
        (
            "threshold (um/s)",
            f"{summary['threshold_um_s']:.2f} vs {summary['true_antimode_um_s']:.2f} "
            f"({100 * summary['threshold_relative_error']:.1f}%)",
            "within 15%",
            passed["threshold"],
        ),
        (
            "cells right class",
            f"{100 * summary['fraction_right']:.1f}%",
            ">= 90%",
            passed["fraction_right"],
        ),
    ]
    lines = [f"{'quantity':22s} {'found':28s} {'target':10s} pass"]
    lines += [f"{a:22s} {b:28s} {c:10s} {'yes' if d else 'NO'}" for a, b, c, d in rows]
    lines.append(
        f"alpha median free {alpha['free']['median']:.3f}, driven {alpha['driven']['median']:.3f}"
        f" (truth means {alpha['free']['true_mean']:.3f}, {alpha['driven']['true_mean']:.3f})"
    )
    lines.append(
        f"cells {tracking['cells']} ({tracking['driven_cells']} driven), tracked "
        f"{tracking['cells_tracked']}, leaving the grid {tracking['cells_leaving_grid']}; tracks "
        f"found {tracking['tracks_found']}, kept {tracking['tracks_kept']}, stubs "
        f"{tracking['stubs_dropped']}, cells with several tracks "
        f"{tracking['cells_with_several_tracks']}; wall {summary['wall_s']:.0f} s"
    )
    return "\n".join(lines)
