"""Fig. 5e-g and Fig. S14 on a phantom with a known answer: volumetric cytometry of four
marker-defined cell classes, compared with the truth and with a simulated flow cytometry count.

Phantom (Note S8.5). :func:`fgat.analysis.cytometry.cell_phantom` draws cells with a nucleus
(Gaussian ball, radius ``nucleus_radius_um``) and two markers, CD11b (membrane stain) and
Ferritin (cytoplasm), in the four classes CD11b-/+ x Ferritin-/+ at 1:1:1:1, on the grid of the
small CPU system (31 x 64 x 64 voxels of 1.5 x 0.975 x 0.975 um, as reproduce/fig5_tracking.py).
The small system sees 62 x 62 x 46 um, so the mixture is split into ``n_fields`` independent
fields of view of ``cells_per_field`` cells (pooled, as cells pooled over several recordings).
Each channel (nuclei, CD11b, Ferritin) is imaged separately through the FLFM forward model
with fgat's camera (:mod:`fgat.app.recipes.flfm_phantoms`: the JPGM PSF under the Fig. S6 quick
aberrations, all 17 Zernike terms uniform in [-0.1, 0.1] waves drawn with the seed, 10^4
photons at the brightest sensor pixel of the channel on a background of 100, Poisson noise; its
own noise seed).

Reconstruction per channel: 4DGAT's static stage (:class:`fgat.recon.
StaticReconstruction`) in two steps, as a user calibrates once per recording: the optics are
self-estimated (Zernike JPGM events, ``optics_steps`` steps of ``optics_gaussians`` Gaussians,
from the ideal PSF) on field 0's nuclei channel; then every channel of every field is fitted
with that estimated PSF fixed (canonical Gaussians seeded from SHB, ``static_steps`` steps, no
densification). The baseline is SHB (:func:`fgat.recon.deconvolution.deconvolve`) with the ideal
PSF, as a user without self-estimation has it. The noiseless phantom channels ("truth") go through
the same analysis.

Analysis (Notes S8.7-S8.8): :func:`~fgat.analysis.cytometry.classify_cells` per field and method
(nuclei as the pan-cell reference, per-marker LoG objects with their own threshold, local
background-corrected signals, +/- calls). Every true cell is matched to the nearest detected
nucleus (mutual nearest neighbours within ``truth_match_um``); a cell is classified correctly
iff it has a match and the match's class is the true one (undetected cells count as wrong).
Class counts (all detected nuclei) are compared by :func:`~fgat.analysis.cytometry.
compare_fractions` (chi-squared test of homogeneity and per-class two-sided Fisher tests) with
(a) the phantom's true counts and (b) a simulated flow cytometry count: a multinomial draw of
``n_flow`` cells from the true class ratio (seeded). Control: the same test against a flow
count of ``n_flow`` cells drawn with ``halved_class`` at half its weight (ratio 0.5:1:1:1 of the
classes), which must come out different (p < 0.05). The reference is large (5000 cells), so the
control's power is set by the measured count N; ``summary.json`` gives the approximate power
(noncentral chi-squared, 3 degrees of freedom, noncentrality ``N M / (N + M)`` times
``sum (p - q)^2 / pooled``): 0.95 at N = 200 (``--quick``) and above 0.99 at N = 500.

    python reproduce/fig5_cytometry.py [--quick] [--seed N] [--out DIR]

writes to OUT (default reproduce/results/fig5_cytometry[_quick]/): cells_<method>.csv (per
detected nucleus: position, marker signals and calls, class, matched true cell and its class),
phantom_cells.csv (per true cell: class and the class found by each method), counts.csv (per
method and class: count, fraction, truth, flow, halved-class reference and Fisher p-values),
summary.json (accuracy per method, chi-squared p against the truth, the flow count and the
halved-class control, the estimated Zernike coefficients' RMS error, wall time),
montage_<method>_xy.png / _xz.png (Fig. S14-like MIPs of field 0: nuclei, CD11b, Ferritin,
merge, circles on the detected cells coloured by class) and
fractions.png (4DGAT's fractions beside the flow count's with Fisher p, Fig. 5g); and prints the
numbers beside the acceptance targets (>= 90% of cells classified correctly from 4DGAT volumes,
chi-squared p > 0.05 against the truth, the halved class detected with p < 0.05).

``--quick`` (``QUICK``: 10 fields of 20 cells, 800 steps estimating the optics, then 300 static
steps per channel, and field 0 once more through ``fgat pipeline --channels all``) takes
16-17 min on one shared core, 6-7 min of it without the pipeline field; the default
(``FULL``: 25 fields of 20 cells, 600 static steps per channel) was not timed with the optics
step.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml
from scipy import stats
from scipy.spatial import cKDTree

from fgat.analysis.cytometry import cell_phantom, classify_cells, compare_fractions, marker_classes
from fgat.app.pipeline import run_pipeline
from fgat.app.recipes.flfm_phantoms import (
    fit_static,
    flfm_optics,
    flfm_true_zernike,
    image_sequence,
    recipe_main,
    sensor_sequence,
)
from fgat.instrument.centres import write_centers
from fgat.io.files import atomic_path, write_csv
from fgat.io.images import read_series, write_tiff
from fgat.recon import Scene, StaticReconstruction
from fgat.recon.deconvolution import deconvolve
from fgat.recon.estimation import OpticsEstimation
from fgat.recon.scene import normalized_measurement
from fgat.viz.analysis import plot_cell_montage, plot_class_fractions

METHODS = ("truth", "shb", "4dgat")
PHANTOM = ("marker_names", "marker_layout", "nucleus_radius_um", "cell_radius_um")
"""Fields of :class:`CytometryConfig` passed on to :func:`cell_phantom`."""
TARGETS = {"accuracy_min": 0.90, "chi2_truth_p_min": 0.05, "halved_p_max": 0.05}


@dataclasses.dataclass(frozen=True)
class CytometryConfig:
    """One run of the recipe (``QUICK``, ``FULL``; tests shrink it)."""

    n_fields: int = 10
    cells_per_field: int = 20  # 1:1:1:1 -> 5 cells of each class per field
    marker_names: tuple = ("CD11b", "Ferritin")
    marker_layout: tuple = ("membrane", "cytoplasm")
    nucleus_radius_um: float = 3.0
    cell_radius_um: float = 6.0  # cells at least 12 um apart
    system: str = "small"
    depths_um: str = "-22.5:22.5:31"
    view_size: int = 64
    photons: float = 10000.0  # configs/base/common.yaml
    background: float = 100.0
    aberrations: dict | None = dataclasses.field(
        default_factory=lambda: {"amplitude": 0.1}  # Fig. S6 quick: 17 terms in [-0.1, 0.1] waves
    )
    optics_steps: int = 800  # the static stage estimating the optics (configs/base/optics_quick)
    optics_gaussians: int = 200
    shb_iterations: int = 50
    static_steps: int = 300  # 4DGAT static stage per channel (0: SHB-initialised Gaussians only)
    n_gaussians: int = 1500
    init_iterations: int = 20  # SHB iterations seeding the Gaussians
    nucleus_sigma_um: float = 1.5  # nucleus Gaussian std (radius / 2)
    marker_sigma_um: float = 3.6  # ~0.6 x cell radius (classify_cells)
    nucleus_threshold: float = 0.2
    marker_threshold: float = 0.2
    match_radius_um: float = 5.0  # nucleus to marker object
    truth_match_um: float = 4.0  # detected nucleus to true cell
    n_flow: int = 5000
    halved_class: str = "CD11b+/Ferritin+"
    pipeline_fields: int = 1  # fields also run the user's way: `fgat pipeline --channels all`
    pipeline_frames: int = 3  # frames of that (T, C, H, W) sequence (cells still)
    pipeline_dynamic_epochs: int = 10
    tracking_uri: str | None = None  # MLflow store of the pipeline runs (default fgat's)
    seed: int = 0


QUICK = CytometryConfig()
FULL = CytometryConfig(n_fields=25, static_steps=600)  # 500 cells


def main(results: Path, argv: list[str] | None = None) -> None:
    """The command line (:func:`fgat.app.recipes.flfm_phantoms.recipe_main`).

    Parameters
    ----------
    results : Path
        The folder of the recipes' results (``reproduce/results``): the default ``--out`` is
        ``results/fig5_cytometry[_quick]``.
    argv : list of str, optional
        The arguments (default: the command line's).
    """
    recipe_main(
        argv,
        globals(),
        name="fig5_cytometry",
        results=results,
        quick_help="10 fields of 20 cells, one also through the pipeline (16-17 min on a core)",
    )


def static_engine(
    views: np.ndarray,
    psf: torch.Tensor,
    optics: dict,
    config: CytometryConfig,
    *,
    steps: int,
    n_gaussians: int,
    estimate: bool = False,
) -> StaticReconstruction:
    """4DGAT's static stage on one channel's views ``(V, Y, X)`` run for ``steps`` steps, with
    the PSF stack ``psf`` fixed, or with ``estimate`` the Zernike coefficients self-estimated
    from the ideal optics ``optics["ideal"]`` (JPGM events of configs/base/optics_quick.yaml)."""
    measurement, scale = normalized_measurement(views, config.background)
    scene = Scene(
        measurement=measurement,
        scale=scale,
        psf=psf.numpy(),
        voxel_size_um=tuple(float(v) for v in optics["voxel"]),
        name="cytometry channel",
        optics=optics["ideal"] if estimate else None,
    )
    estimation = OpticsEstimation(
        estimate="zernike" if estimate else "none",
        start=50,
        every=25,
        steps=15,
        identifiability=False,
    )
    return fit_static(scene, config, steps=steps, n_gaussians=n_gaussians, estimation=estimation)


def estimate_psf(views: np.ndarray, optics: dict, config: CytometryConfig) -> tuple:
    """The PSF stack ``(V, Z, h, w)`` float32 self-estimated from one channel's views, starting
    from the ideal optics, and the RMS error (waves) of its Zernike coefficients against the
    truth's."""
    engine = static_engine(
        views,
        optics["ideal_psf"],
        optics,
        config,
        steps=config.optics_steps,
        n_gaussians=config.optics_gaussians,
        estimate=True,
    )
    indices = engine.jpgm.zernike_indices
    truth = flfm_true_zernike(config, indices)
    estimate = engine.jpgm.zernike_coefficients.detach().double().cpu().numpy()
    return engine.psf.detach().cpu(), float(np.sqrt(np.mean((estimate - truth) ** 2)))


def static_fit(views: np.ndarray, psf: torch.Tensor, optics: dict, config) -> np.ndarray:
    """4DGAT's static stage on one channel's views ``(V, Y, X)`` with the PSF stack ``psf``: the
    volume ``(Z, Y, X)`` of the fitted Gaussians, in the views' counts above the background."""
    engine = static_engine(
        views, psf, optics, config, steps=config.static_steps, n_gaussians=config.n_gaussians
    )
    with torch.no_grad():
        return engine.volume().cpu().numpy().astype(np.float64) * engine.scene.scale


def channel_views(channels: dict, field: int, optics: dict, config: CytometryConfig) -> dict:
    """``{channel: (V, Y, X)}`` noisy views of one field, each channel with its own noise seed."""
    return {
        name: image_sequence([channel], config, optics, (config.seed * 1000 + field) * 10 + k)[0]
        for k, (name, channel) in enumerate(channels.items())
    }


def reconstruct(channels: dict, views: dict, psf: torch.Tensor, optics: dict, config) -> dict:
    """``{method: {channel: (Z, Y, X)}}``: the noiseless phantom ("truth"), SHB with the ideal
    PSF and 4DGAT with the PSF stack ``psf`` it estimated, of every channel."""
    volumes = {"truth": channels, "shb": {}, "4dgat": {}}
    for name, channel_views in views.items():
        volumes["shb"][name] = deconvolve(
            torch.from_numpy(channel_views),
            optics["ideal_op"],
            config.shb_iterations,
            background=config.background,
        ).numpy()
        volumes["4dgat"][name] = static_fit(channel_views, psf, optics, config)
    return volumes


def pipeline_field(channels: dict, field: int, optics: dict, config, out: Path) -> dict:
    """The user's path on one field: its channels imaged as a ``(T, C, H, W)`` sensor sequence
    (``pipeline_frames`` frames of still cells, independent noise per frame) written as an
    OME-TIFF beside the nominal lenslet centres, reconstructed by ``python -m fgat pipeline
    --channels all`` (per channel the static stage with Zernike self-estimation from the ideal
    PSF, then the dynamic stage) and the merged ``(T, C, Z, Y, X)`` result read back:
    ``{channel: (Z, Y, X)}`` of the reference frame. Stages that finished with the same
    configuration and inputs are not run again."""
    folder = out / "pipeline" / f"field{field}"
    folder.mkdir(parents=True, exist_ok=True)
    frames = config.pipeline_frames
    sensor = np.stack(
        [
            sensor_sequence(
                [channel] * frames, config, optics, (config.seed * 1000 + field) * 10 + k
            )
            for k, channel in enumerate(channels.values())
        ],
        axis=1,
    )
    write_tiff(folder / "sensor.ome.tif", sensor, axes="TCYX")
    write_centers(folder / "centers.csv", optics["system"].lenslet_centers_px())
    shared = {
        "seed_everything": config.seed,
        "mlflow.experiment": "fig5_cytometry_pipeline",
        "trainer.default_root_dir": str(folder / "runs"),
        "trainer.num_sanity_val_steps": 0,
        "trainer.enable_model_summary": False,
        "trainer.enable_progress_bar": False,
        "trainer.log_every_n_steps": 50,
        "data.class_path": "fgat.datamodules.FLFMDataModule",
        "data.init_args": {
            "measurement": str(folder / "sensor.ome.tif"),
            "centers": str(folder / "centers.csv"),
            "system": config.system,
            "depths_um": config.depths_um,
            "view_size": config.view_size,
            "background": config.background,
        },
    }
    if config.tracking_uri:
        shared["mlflow.tracking_uri"] = config.tracking_uri
    static = {
        "model.class_path": "fgat.modules.StaticModule",
        "trainer.max_steps": config.optics_steps,
        "trainer.check_val_every_n_epoch": None,
        "trainer.val_check_interval": config.optics_steps,
        "model.init_args.n_gaussians": config.n_gaussians,
        "model.init_args.densification": {"enabled": False},
        "model.init_args.optics": {"estimate": "zernike", "start": 50, "every": 25, "steps": 15},
    }
    dynamic = {
        "model.class_path": "fgat.modules.DynamicModule",
        "model.init_args.static": "set by the pipeline",
        "model.init_args.hexplane.spatial_resolution": [8, 8, 8],
        "model.init_args.hexplane.temporal_resolution": frames,
        "trainer.max_epochs": config.pipeline_dynamic_epochs,
        "trainer.check_val_every_n_epoch": config.pipeline_dynamic_epochs,
    }
    paths = []
    for name, content in (("shared", shared), ("static", static), ("dynamic", dynamic)):
        paths.append(folder / f"{name}.yaml")
        paths[-1].write_text(yaml.safe_dump(content, sort_keys=False))
    result = run_pipeline([str(paths[0])], [str(paths[1])], "all", [], [str(paths[2])])
    volumes = read_series(result.volumes, ndim=5)  # (T, C, Z, Y, X)
    reference = frames // 2
    return {name: volumes[reference, k].astype(np.float64) for k, name in enumerate(channels)}


def classify(volumes: dict, voxel: np.ndarray, config: CytometryConfig) -> pd.DataFrame:
    """:func:`classify_cells` on one method's channels with the recipe's settings."""
    return classify_cells(
        volumes["nuclei"],
        {name: volumes[name] for name in config.marker_names},
        voxel_size_um=voxel,
        sigma_um=config.nucleus_sigma_um,
        thresholds={name: config.marker_threshold for name in config.marker_names},
        match_radius_um=config.match_radius_um,
        nucleus_threshold=config.nucleus_threshold,
        marker_sigma_um=config.marker_sigma_um,
    )


def match_truth(found: pd.DataFrame, truth: pd.DataFrame, radius_um: float) -> pd.DataFrame:
    """``found`` with ``cell`` (the true cell, -1 for none), ``match_um``, ``class_true`` and
    ``correct``: detections and true cells paired as mutual nearest neighbours within
    ``radius_um``."""
    found = found.copy()
    found["cell"], found["match_um"], found["class_true"] = -1, np.nan, "none"
    if len(found) and len(truth):
        axes = ["z", "y", "x"]
        to_cell, cell = cKDTree(truth[axes].to_numpy()).query(found[axes].to_numpy())
        _, back = cKDTree(found[axes].to_numpy()).query(truth[axes].to_numpy())
        paired = (to_cell <= radius_um) & (back[cell] == np.arange(len(found)))
        found.loc[paired, "cell"] = truth["cell"].to_numpy()[cell[paired]]
        found["match_um"] = to_cell
        found.loc[paired, "class_true"] = truth["class"].to_numpy()[cell[paired]]
    found["correct"] = found["class"] == found["class_true"]
    return found


def control_power(n: int, m: int, p: np.ndarray, q: np.ndarray, alpha: float = 0.05) -> float:
    """Approximate power of the chi-squared test of homogeneity between ``n`` cells of fractions
    ``p`` and ``m`` of fractions ``q`` (noncentral chi-squared, ``K - 1`` degrees of freedom)."""
    pooled = (n * p + m * q) / (n + m)
    noncentrality = n * m / (n + m) * float(np.sum((p - q) ** 2 / pooled))
    dof = len(p) - 1
    return float(stats.ncx2.sf(stats.chi2.ppf(1 - alpha, dof), dof, noncentrality))


def run(config: CytometryConfig, out: Path, *, log=print) -> dict:
    """The whole recipe into ``out``; returns the summary (also written as summary.json)."""
    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    optics = flfm_optics(config)
    shape, voxel = optics["shape"], optics["voxel"]
    classes = marker_classes(config.marker_names)
    if config.halved_class not in classes:
        raise ValueError(f"halved_class {config.halved_class!r} is not one of {classes}")
    found = {method: [] for method in METHODS}
    truths, first = [], {}
    psf, zernike_rms_error = optics["psf"], 0.0
    for field in range(config.n_fields):
        channels, truth = cell_phantom(
            shape,
            voxel_size_um=voxel,
            n_cells=config.cells_per_field,
            seed=config.seed * 1000 + field,
            **{name: getattr(config, name) for name in PHANTOM},
        )
        views = channel_views(channels, field, optics, config)
        if field == 0 and config.aberrations:
            psf, zernike_rms_error = estimate_psf(views["nuclei"], optics, config)
            log(
                f"optics estimated from field 0's nuclei: Zernike RMS error "
                f"{zernike_rms_error:.4f} waves ({time.perf_counter() - start:.0f} s)"
            )
        volumes = reconstruct(channels, views, psf, optics, config)
        if field < config.pipeline_fields:
            volumes["pipeline"] = pipeline_field(channels, field, optics, config, out)
        for method, channel_volumes in volumes.items():
            table = match_truth(
                classify(channel_volumes, voxel, config), truth, config.truth_match_um
            )
            table.insert(0, "field", field)
            found.setdefault(method, []).append(table)
        truth.insert(0, "field", field)
        truths.append(truth)
        if field == 0:
            first = volumes
        log(
            f"field {field + 1}/{config.n_fields}: "
            + ", ".join(f"{m} {int(found[m][-1]['correct'].sum())}/{len(truth)}" for m in METHODS)
            + f" correct ({time.perf_counter() - start:.0f} s)"
        )
    truth = pd.concat(truths, ignore_index=True)
    cells = {method: pd.concat(tables, ignore_index=True) for method, tables in found.items()}

    truth_counts = {c: int((truth["class"] == c).sum()) for c in classes}
    rng = np.random.default_rng([config.seed, 2])
    ratio = np.array([truth_counts[c] for c in classes], dtype=float)
    flow = dict(zip(classes, rng.multinomial(config.n_flow, ratio / ratio.sum()).tolist()))
    halved = ratio * np.where(np.array(classes) == config.halved_class, 0.5, 1.0)
    flow_halved = dict(zip(classes, rng.multinomial(config.n_flow, halved / halved.sum()).tolist()))

    results, rows = {}, []
    for method in METHODS:
        table = cells[method]
        counts = {c: int((table["class"] == c).sum()) for c in classes}
        n_found = sum(counts.values())
        if n_found == 0:
            raise ValueError(f"{method}: no nucleus was detected")
        references = {"truth": truth_counts, "flow": flow, "halved": flow_halved}
        tests = {name: compare_fractions(counts, ref) for name, ref in references.items()}
        correct = int(table["correct"].sum())
        results[method] = {
            "accuracy": correct / len(truth),
            "cells_correct": correct,
            "cells_true": len(truth),
            "nuclei_detected": n_found,
            "cells_detected": int((table["cell"] >= 0).sum()),
            "false_detections": int((table["cell"] < 0).sum()),
            "counts": counts,
            "chi2_p_truth": tests["truth"].chi2_pvalue,
            "chi2_p_flow": tests["flow"].chi2_pvalue,
            "chi2_p_halved": tests["halved"].chi2_pvalue,
            "halved_control_power": control_power(
                n_found,
                config.n_flow,
                ratio / ratio.sum(),
                halved / halved.sum(),
            ),
        }
        for k, name in enumerate(classes):
            rows.append(
                (method, name, counts[name], tests["truth"].fractions[k])
                + tuple(
                    value
                    for test in tests.values()
                    for value in (test.reference_counts[k], test.fisher_pvalues[k])
                )
            )
    gat = results["4dgat"]
    summary = {
        "config": dataclasses.asdict(config),
        "methods": results,
        "truth_counts": truth_counts,
        "flow_counts": flow,
        "flow_halved_counts": flow_halved,
        "halved_class": config.halved_class,
        "zernike_rms_error_waves": zernike_rms_error,
        "pipeline": pipeline_summary(cells.get("pipeline"), truth, config),
        "control": (
            f"chi-squared test of each method's counts against a flow count of {config.n_flow} "
            f"cells drawn with {config.halved_class} at half weight"
        ),
        "targets": TARGETS,
        "passed": {
            "accuracy": gat["accuracy"] >= TARGETS["accuracy_min"],
            "chi2_truth": gat["chi2_p_truth"] > TARGETS["chi2_truth_p_min"],
            "halved_detected": gat["chi2_p_halved"] < TARGETS["halved_p_max"],
        },
    }
    summary["wall_s"] = time.perf_counter() - start
    write_outputs(out, cells, truth, rows, summary, first, voxel, config)
    return summary


def pipeline_summary(cells: pd.DataFrame | None, truth: pd.DataFrame, config) -> dict | None:
    """Accuracy of the ``fgat pipeline --channels all`` volumes on the fields it ran on."""
    if cells is None:
        return None
    true_cells = truth[truth["field"] < config.pipeline_fields]
    correct = int(cells["correct"].sum())
    return {
        "fields": config.pipeline_fields,
        "accuracy": correct / len(true_cells),
        "cells_correct": correct,
        "cells_true": len(true_cells),
        "false_detections": int((cells["cell"] < 0).sum()),
    }


def write_outputs(out, cells, truth, rows, summary, first, voxel, config) -> None:
    """CSV tables, summary.json, the montages of field 0 and the fraction bars."""
    names = list(config.marker_names)
    for method, table in cells.items():
        columns = ["field", "nucleus", "z", "y", "x"]
        columns += [f"{n}_{k}" for n in names for k in ("matched", "signal", "positive")]
        columns += ["class", "cell", "match_um", "class_true", "correct"]
        write_csv(
            out / f"cells_{method}.csv",
            columns,
            table[columns].itertuples(index=False, name=None),
        )
    phantom = truth.copy()
    for method, table in cells.items():
        paired = table[table["cell"] >= 0].set_index(["field", "cell"])["class"]
        keys = pd.MultiIndex.from_frame(phantom[["field", "cell"]])
        phantom[f"class_{method}"] = paired.reindex(keys).fillna("none").to_numpy()
    columns = ["field", "cell", "z", "y", "x", "class"] + [f"class_{m}" for m in cells]
    write_csv(out / "phantom_cells.csv", columns, phantom[columns].itertuples(index=False))
    columns = ["method", "class", "count", "fraction", "truth", "fisher_p_truth", "flow"]
    columns += ["fisher_p_flow", "flow_halved", "fisher_p_halved"]
    write_csv(out / "counts.csv", columns, rows)
    with atomic_path(out / "summary.json") as temporary:
        temporary.write_text(json.dumps(summary, indent=2, default=float))

    radius = config.cell_radius_um
    for method, volumes in first.items():
        table = cells[method][cells[method]["field"] == 0]
        labels = table["class"].tolist()
        for view, axis, columns, pixel in (
            ("xy", 0, ["y", "x"], (voxel[1], voxel[2])),
            ("xz", 1, ["z", "x"], (voxel[0], voxel[2])),
        ):
            plot_cell_montage(
                {name: np.max(volume, axis=axis) for name, volume in volumes.items()},
                table[columns].to_numpy(),
                labels,
                out / f"montage_{method}_{view}.png",
                pixel_um=pixel,
                radius_um=radius,
                title=f"{method}, field 0: {view[0]}-{view[1]} MIPs, detected cells by class",
                axes_names=tuple(columns),
            )
    gat = [row for row in rows if row[0] == "4dgat"]
    flow_total = sum(row[6] for row in gat)
    plot_class_fractions(
        [row[1] for row in gat],
        [row[3] for row in gat],
        out / "fractions.png",
        reference_fractions=[row[6] / flow_total for row in gat],
        pvalues=[row[7] for row in gat],
        title=(
            "4DGAT vs simulated flow cytometry, chi-squared p = "
            f"{summary['methods']['4dgat']['chi2_p_flow']:.2g}"
        ),
    )


def report(summary: dict) -> str:
    """The numbers beside the acceptance targets, one line per method."""
    lines = [
        f"{'method':7s} {'accuracy':>9s} {'detected':>9s} {'false':>6s} {'p(truth)':>9s} "
        f"{'p(flow)':>9s} {'p(halved)':>10s} {'power':>6s}"
    ]
    for method, result in summary["methods"].items():
        lines.append(
            f"{method:7s} {100 * result['accuracy']:8.1f}% {result['nuclei_detected']:9d} "
            f"{result['false_detections']:6d} {result['chi2_p_truth']:9.3g} "
            f"{result['chi2_p_flow']:9.3g} {result['chi2_p_halved']:10.3g} "
            f"{result['halved_control_power']:6.2f}"
        )
    passed = summary["passed"]
    gat = summary["methods"]["4dgat"]
    targets = [
        ("4DGAT cells classified correctly", f"{100 * gat['accuracy']:.1f}%", ">= 90%"),
        ("4DGAT chi-squared p vs truth", f"{gat['chi2_p_truth']:.3g}", "> 0.05"),
        (f"halved {summary['halved_class']} p", f"{gat['chi2_p_halved']:.3g}", "< 0.05"),
    ]
    lines.append(f"{'target':36s} {'found':>8s} {'wanted':>8s} pass")
    for (label, value, wanted), ok in zip(targets, passed.values()):
        lines.append(f"{label:36s} {value:>8s} {wanted:>8s} {'yes' if ok else 'NO'}")
    pipeline = summary["pipeline"]
    if pipeline:
        lines.append(
            f"fgat pipeline --channels all, {pipeline['fields']} field(s): "
            f"{pipeline['cells_correct']}/{pipeline['cells_true']} cells right "
            f"({100 * pipeline['accuracy']:.1f}%), {pipeline['false_detections']} false nuclei"
        )
    lines.append(
        f"cells {gat['cells_true']}, truth counts {summary['truth_counts']}, flow "
        f"{summary['flow_counts']}; wall {summary['wall_s']:.0f} s"
    )
    return "\n".join(lines)
