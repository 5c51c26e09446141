"""Run time against error: which method gets how close, how soon?

On the same measurement of a phantom (beads, line-sphere) seen by the same optics, without
aberrations, with pupil aberrations (Fig. S6's settings: all 17 Zernike terms) and with
aberrations and lenslet shifts (Fig. S7's: 4DGAT estimates both), each method's volume PSNR /
SSIM against the truth is sampled along one run (callbacks, not re-runs) against the wall time
spent computing it; the time spent on the samples themselves is kept out of the curves and
reported apart (``eval_s``). Methods, as named in the JSON:

* ``RL``, ``SHB``: Richardson-Lucy and Algorithm S1 with the ideal PSF (what a user without
  self-estimation has), sampled at log-spaced iterations;
* ``3DGAT``: the static stage with the ideal PSF held fixed; ``4DGAT``: with the optics
  estimated (JPGM: the Zernike coefficients, and under Fig. S7's settings the lenslet shifts
  too), whose ``sigma`` = ||c - c_gt|| / ||c_gt|| and PSF-stack error ``psf_error`` =
  ||h - h_gt|| / ||h_gt|| are sampled too (the ideal PSF's is the case's
  ``ideal_psf_error``); both
  timed from the start (their SHB seed included);
* ``SHB+4DGAT-PSF``: SHB with the PSF 4DGAT estimated, its clock starting where 4DGAT ended;
* ``4DGAT+skip``: 4DGAT skipping what converged optics do not need (``optics.tolerance`` 1e-4,
  ``optics.parameter_tolerance`` 2e-4: inner JPGM steps stop on their plateau, events stop after
  two quiet ones), on the aberrated scenes (every scene without ``--quick``).

The scenes and settings are the Fig. S6 and S7 recipes' (``configs/base/common.yaml``,
``configs/base/optics_quick.yaml``, ``configs/figS<N>.yaml``, ``configs/figS<N>_quick.yaml``;
without aberrations Fig. S6's with ``aberrations`` off): the small CPU optics, 31 x 64 x 64
voxels, 800 static steps. Per case the summary gives each method's best PSNR, the seconds it
needs to reach SHB's best PSNR (``time to SHB peak``) as a ratio to SHB's own, and the
crossover: the first time 4DGAT's PSNR beats the best that RL, SHB and 3DGAT reach in their
whole runs. Each method's final volume is also scored registered to the truth
(``final_psnr_aligned``, with the shift ``final_shift_zyx``; :func:`fgat.recon.metrics.
registered_psnr`; NaN when the volume does not register): a joint estimate of the lenslet
shifts fixes the scene only up to a translation (the gauge of :func:`fgat.recon.estimation.
remove_scene_gauge`), and so does the ideal PSF, whose frame is where the true shifts put it.
Below :data:`REGISTERED_SAMPLE_VOXELS` voxels (the CPU scale) every sample is registered too
(``psnr_registered``, dotted on the plot), and the summary repeats the times, ratios and
crossover on those scores (``..._registered``): how soon each method gets how close once the
translation no reconstruction can see is taken out.

    python benchmarks/time_vs_error.py [--quick | --paper] [--phantom P ...] [--settings S ...]
        [--seed N] [--steps N] [--device auto] [--out benchmarks/results/time_vs_error]

``--quick`` (2 CPU cores, under 10 minutes): beads and line-sphere, each under the three
settings, 200 RL/SHB iterations. Without it, 500 iterations and 1600 static steps.

``--paper``: the recipes at the paper's scale (``configs/base/paper.yaml``,
``configs/base/optics_paper.yaml``: 20x/0.45, 300 x 300 x 101 voxels, the recipe's 2,000 static
steps with Table S7's JPGM schedule), 500 RL/SHB iterations, on a GPU (``--device auto`` takes
CUDA when present; on 2 CPU cores the 3,600 JPGM updates of one 4DGAT run alone take about 6
hours), with the paper's Table S7 times marked on the plot. ``--phantom`` and ``--settings``
choose the scenes (default: all of them).

``--merge JSON [JSON ...]`` runs nothing: it writes the cases of earlier runs (their
``time_vs_error.json``, one scene each for instance, alike in device, scale, seed, RL/SHB
iterations and static steps) as one JSON, CSV and plot into ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from fgat._core.devices import resolve_device
from fgat.app.lightning_cli import resolved_config
from fgat.app.recipes.benchmark import static_engine, synchronize, write_json
from fgat.app.recipes.optics import config_args, recipe_configs
from fgat.io.files import write_csv
from fgat.optics.acquisition import crop_guard
from fgat.recon import StaticReconstruction, names, phantom_scene
from fgat.recon.deconvolution import deconvolve
from fgat.recon.metrics import compare_volumes, registered_psnr, scoring_pair
from fgat.sim.simulation import SimulationConfig
from fgat.viz.figures import pyplot, save_figure

SETTINGS = {
    "ideal optics": ("figS6", False),
    "aberrated": ("figS6", True),
    "joint": ("figS7", True),
}
"""Each scene's recipe and whether its optics are perturbed (Fig. S6: Zernike terms; Fig. S7:
Zernike terms and lenslet shifts)."""
PHANTOMS = {"beads": None, "line_sphere": "configs/simulate/line_sphere.yaml"}
METHODS = ("RL", "SHB", "3DGAT", "4DGAT", "SHB+4DGAT-PSF", "4DGAT+skip")
SKIP = {"tolerance": 1e-4, "parameter_tolerance": 2e-4}
REGISTERED_SAMPLE_VOXELS = 2_000_000
"""Samples of volumes up to this many voxels are also scored registered to the truth (about 50 ms
each at 31 x 64 x 64 on 2 CPU cores); larger ones only at the end of a run (2.3-2.4 s each at
the paper's 300 x 300 x 101 there)."""
TABLE_S7_S = {"3DGAT": 2000 * 0.07, "4DGAT": 40 * 60.0}
"""The paper's static-stage times on a GPU at its scale (Table S7): 2,000 regular steps of about
0.07 s (3DGAT's whole run), and the full static stage with JPGM self-estimation, about 40 min."""


@dataclasses.dataclass
class Curve:
    """Samples of one method's run: compute seconds, scores, and the seconds spent sampling."""

    time_s: list[float] = dataclasses.field(default_factory=list)
    psnr: list[float] = dataclasses.field(default_factory=list)
    ssim: list[float] = dataclasses.field(default_factory=list)
    sigma: list[float] = dataclasses.field(default_factory=list)
    psf_error: list[float] = dataclasses.field(default_factory=list)
    psnr_registered: list[float] = dataclasses.field(default_factory=list)
    eval_s: float = 0.0
    converged_at: int | None = None  # 4DGAT+skip: the step after which events were skipped
    aligned_psnr: float = math.nan  # the final volume's, registered to the truth (sub-voxel)
    shift_zyx: list[float] | None = None  # that registration's shift, voxels

    def sample(
        self,
        elapsed: float,
        volume,
        truth: torch.Tensor,
        sigma: float = math.nan,
        psf_error: float = math.nan,
    ) -> None:
        """Score ``volume`` against ``truth`` (float64, on the device that made ``volume``: a
        paper-size volume's SSIM takes seconds on a CPU, milliseconds on a GPU), with the
        estimated optics' ``sigma`` and relative PSF-stack error when there are any, and up to
        :data:`REGISTERED_SAMPLE_VOXELS` voxels registered to ``truth`` too (NaN beyond, or
        where the volume does not register)."""
        start = time.perf_counter()
        volume, truth = scoring_pair(torch.as_tensor(volume), truth)
        scores = compare_volumes(volume, truth)
        registered = math.nan
        if truth.numel() <= REGISTERED_SAMPLE_VOXELS:
            registered = registered_psnr(volume.cpu().numpy(), truth.cpu().numpy(), max_shift=None)[
                0
            ]
        self.time_s.append(elapsed)
        self.psnr.append(scores["psnr"])
        self.psnr_registered.append(registered)
        self.ssim.append(scores["ssim"])
        self.sigma.append(sigma)
        self.psf_error.append(psf_error)
        self.eval_s += time.perf_counter() - start

    def align(self, volume, truth: torch.Tensor) -> None:
        """Score the run's final ``volume`` again registered to ``truth``
        (:func:`~fgat.recon.metrics.registered_psnr`): the PSNR without the translation of the scene
        that the lenslet shifts' gauge leaves open (no reconstruction can see it)."""
        start = time.perf_counter()
        volume = torch.as_tensor(volume).detach().cpu().double().numpy()
        self.aligned_psnr, shift = registered_psnr(volume, truth.cpu().numpy(), max_shift=None)
        self.shift_zyx = None if shift is None else list(shift)
        self.eval_s += time.perf_counter() - start


def log_spaced(count: int) -> set[int]:
    """About 25 iteration counts from 1 to ``count``, log-spaced."""
    return {int(k) for k in np.unique(np.geomspace(1, count, 25).round())}


def run_deconvolution(
    scene,
    psf,
    method: str,
    iterations: int,
    truth: torch.Tensor,
    offset: float = 0.0,
    psf_error: float = math.nan,
) -> Curve:
    """RL or SHB on ``scene`` with ``psf`` (whose error, when known, its samples carry) on
    ``truth``'s device, sampled at log-spaced iterations."""
    curve, wanted, device = Curve(), log_spaced(iterations), truth.device
    operator = scene.operator(torch.as_tensor(psf, device=device))
    measurement = torch.as_tensor(scene.measurement, device=device)
    synchronize(device)
    clock = {"start": time.perf_counter(), "paused": 0.0}
    final = {}

    def callback(k, estimate):
        if k + 1 in wanted:
            synchronize(device)
            pause = time.perf_counter()
            elapsed = pause - clock["start"] - clock["paused"]
            final["volume"] = volume = crop_guard(estimate, scene.guard_px)
            curve.sample(offset + elapsed, volume, truth, psf_error=psf_error)
            clock["paused"] += time.perf_counter() - pause

    deconvolve(measurement, operator, iterations, method=method.lower(), callback=callback)
    curve.align(final["volume"], truth)
    return curve


def sample_every(steps: int) -> int:
    """Static steps between samples: 25, or about 32 samples a run for longer runs."""
    return max(25, steps // 32)


def run_static(
    scene,
    model: dict,
    steps: int,
    estimate: str,
    truth: torch.Tensor,
    skip: dict | None = None,
) -> tuple[Curve, StaticReconstruction]:
    """The static stage on ``truth``'s device (``estimate``: none for 3DGAT, zernike for 4DGAT;
    ``skip``: optics tolerances), timed from the engine's construction (its SHB seed), sampled
    every :func:`sample_every` steps."""
    model = {**model, "baseline_iterations": 0}
    optics = {**model["optics"], **(skip or {}), "estimate": estimate, "identifiability": False}
    curve, every, device = Curve(), sample_every(steps), truth.device
    start = time.perf_counter()
    engine = static_engine(scene, model, optics, steps, device)
    synchronize(device)
    elapsed = time.perf_counter() - start

    def sample():
        errors = {}
        if engine.jpgm is not None and engine.true_psf is not None:
            errors = engine.optics_errors()
        optics = (errors.get(key, math.nan) for key in (names.ZERNIKE_RESIDUAL, names.PSF_ERROR))
        curve.sample(elapsed, engine.volume(), truth, *optics)

    sample()
    for step in range(1, steps + 1):
        start = time.perf_counter()
        engine.step()
        synchronize(device)
        elapsed += time.perf_counter() - start
        if step % every == 0:
            sample()
    curve.align(engine.volume(), truth)
    return curve, engine


def recipe_config(figure: str, paper: bool = False, seed: int = 0) -> dict:
    """``figure``'s recipe resolved from the config files ``reproduce/optics.py`` lays for it: at
    the CPU scale, or at the paper's (20x/0.45, 300 x 300 x 101, Table S7's schedule)."""
    configs = config_args(recipe_configs(figure, quick=not paper))
    return resolved_config(["fit", *configs, f"--seed_everything={seed}"])


def case_scene(phantom: str, settings: str, seed: int, paper: bool = False):
    """The simulation of ``settings``' recipe with ``phantom`` (aberrations off for ideal
    optics) and the recipe's resolved config."""
    figure, aberrated = SETTINGS[settings]
    config = recipe_config(figure, paper, seed)
    simulation = dict(config["data"]["init_args"]["simulation"], seed=seed)
    if PHANTOMS[phantom] is not None:
        simulation["phantom"] = yaml.safe_load(Path(PHANTOMS[phantom]).read_text())["phantom"]
    if not aberrated:
        simulation["aberrations"] = None
    scene = phantom_scene(SimulationConfig(**simulation), psf=config["data"]["init_args"]["psf"])
    return scene, config


def first_time(curve: Curve, level: float, key: str = "psnr") -> float:
    """Seconds at which ``curve``'s ``key`` (``psnr`` or ``psnr_registered``) first reaches
    ``level`` dB (NaN: never)."""
    return next((t for t, p in zip(curve.time_s, getattr(curve, key)) if p >= level), math.nan)


def best(values: list[float]) -> float:
    """The largest finite value (NaN: none)."""
    finite = [v for v in values if math.isfinite(v)]
    return max(finite) if finite else math.nan


def reach(curves: dict[str, Curve], key: str) -> dict:
    """On the scores ``key``: SHB's best, each method's seconds to reach it and their ratio to
    SHB's own, and 4DGAT's crossover, the first time it beats the best that RL, SHB and 3DGAT
    reach in their whole runs (NaN: never, or no scores)."""
    bests = {method: best(getattr(curve, key)) for method, curve in curves.items()}
    target = bests["SHB"]
    reference = first_time(curves["SHB"], target, key)
    others = best([bests[m] for m in ("RL", "SHB", "3DGAT")])
    seconds = {method: first_time(curve, target, key) for method, curve in curves.items()}
    return {
        "shb_peak": target,
        "best": bests,
        "seconds": seconds,
        "ratio": {method: t / reference for method, t in seconds.items()},
        "crossover_psnr": others,
        "crossover_s": first_time(curves["4DGAT"], others + 1e-9, key),
    }


def summarize(curves: dict[str, Curve]) -> dict:
    """Best PSNR, seconds to SHB's best as a ratio to SHB's, and 4DGAT's crossover, on the raw
    PSNR and (``_registered``) on the PSNR registered to the truth."""
    raw, registered = reach(curves, "psnr"), reach(curves, "psnr_registered")
    rows = [
        {
            "method": method,
            "best_psnr": raw["best"][method],
            "best_psnr_registered": registered["best"][method],
            "final_psnr": curve.psnr[-1],
            "final_sigma": curve.sigma[-1],
            "final_psf_error": curve.psf_error[-1],
            "final_psnr_aligned": curve.aligned_psnr,
            "final_shift_zyx": curve.shift_zyx,
            "total_s": curve.time_s[-1],
            "eval_s": curve.eval_s,
            "time_to_shb_peak_s": raw["seconds"][method],
            "ratio_to_shb": raw["ratio"][method],
            "time_to_shb_peak_registered_s": registered["seconds"][method],
            "ratio_to_shb_registered": registered["ratio"][method],
        }
        for method, curve in curves.items()
    ]
    summary = {
        "shb_peak_psnr": raw["shb_peak"],
        "shb_peak_psnr_registered": registered["shb_peak"],
        "rows": rows,
        "crossover_psnr": raw["crossover_psnr"],
        "crossover_s": raw["crossover_s"],
        "crossover_psnr_registered": registered["crossover_psnr"],
        "crossover_registered_s": registered["crossover_s"],
    }
    if "4DGAT+skip" in curves:
        full, skip = curves["4DGAT"], curves["4DGAT+skip"]
        summary["skip"] = {
            "seconds_saved": full.time_s[-1] - skip.time_s[-1],
            "speedup": full.time_s[-1] / skip.time_s[-1],
            "psnr_change_db": skip.psnr[-1] - full.psnr[-1],
            "sigma_change": skip.sigma[-1] - full.sigma[-1],
            "converged_at_step": skip.converged_at,
        }
    return summary


def run_case(
    phantom: str,
    settings: str,
    seed: int,
    iterations: int,
    steps: int | None,
    skip: bool,
    device: torch.device,
    paper: bool = False,
) -> dict:
    """One scene, every method; ``steps`` ``None``: the recipe's ``trainer.max_steps``."""
    scene, config = case_scene(phantom, settings, seed, paper)
    model = config["model"]["init_args"]
    steps = steps or int(config["trainer"]["max_steps"])
    estimate = model["optics"]["estimate"]
    truth = torch.as_tensor(scene.truth, dtype=torch.float64, device=device)
    curves = {}

    def done(method: str, curve: Curve) -> None:
        curves[method] = curve
        print(
            f"  {method}: best {max(curve.psnr):.2f} dB, {curve.time_s[-1]:.1f} s "
            f"(+{curve.eval_s:.1f} s scoring)",
            flush=True,
        )

    run_deconvolution(scene, scene.psf, "RL", 2, truth)  # untimed: a GPU's first FFT plans
    for method in ("RL", "SHB"):
        done(method, run_deconvolution(scene, scene.psf, method, iterations, truth))
    done("3DGAT", run_static(scene, model, steps, "none", truth)[0])
    curve, engine = run_static(scene, model, steps, estimate, truth)
    done("4DGAT", curve)
    psf = engine.psf.detach()
    ideal_psf_error = engine.optics_start().get(names.PSF_ERROR_INITIAL, math.nan)
    del engine
    shb = run_deconvolution(
        scene, psf, "SHB", iterations, truth, curve.time_s[-1], curve.psf_error[-1]
    )
    done("SHB+4DGAT-PSF", shb)
    if skip:
        curve, engine = run_static(scene, model, steps, estimate, truth, SKIP)
        curve.converged_at = engine.optics_converged_at
        done("4DGAT+skip", curve)
    figure, aberrated = SETTINGS[settings]
    return {
        "phantom": phantom,
        "settings": settings,
        "recipe": figure,
        "estimate": estimate,
        "aberrations": aberrated,
        "static_steps": steps,
        "ideal_psf_error": ideal_psf_error,
        "curves": {m: dataclasses.asdict(c) for m, c in curves.items()},
        "summary": summarize(curves),
    }


MERGE_KEYS = ("device_name", "scale", "seed", "iterations", "static_steps")
"""What results must share to be merged into one table and plot."""


def read_result(path: Path) -> dict:
    """One ``time_vs_error.json``, checked for its ``cases`` and :data:`MERGE_KEYS`."""
    try:
        result = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: not a readable time_vs_error.py result ({error})") from None
    fields = ("cases", *MERGE_KEYS)
    missing = [key for key in fields if key not in result] if isinstance(result, dict) else fields
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)} field; expected a time_vs_error.json")
    return result


def merge_results(paths: list[Path]) -> tuple[list[dict], dict]:
    """The cases of several results and their shared metadata, in the order given.

    Raises
    ------
    ValueError
        A file that is not a result, results that differ in one of :data:`MERGE_KEYS` (naming
        the file, the field and both values) or that hold the same scene twice.
    """
    results = [read_result(path) for path in paths]
    meta = {key: value for key, value in results[0].items() if key != "cases"}
    cases, seen = [], {}
    for path, result in zip(paths, results):
        for key in MERGE_KEYS:
            if result[key] != meta[key]:
                raise ValueError(
                    f"{path}: {key} is {result[key]!r} but {paths[0]} has {meta[key]!r}; only "
                    f"results alike in {', '.join(MERGE_KEYS)} are merged"
                )
        for case in result["cases"]:
            scene = (case["phantom"], case["settings"])
            if scene in seen:
                raise ValueError(f"{path}: {scene} is in {seen[scene]} already")
            seen[scene] = path
            cases.append(case)
    return cases, meta


REGISTERED_LABEL = "dotted: registered to the truth"
"""Legend entry of the registered curves, drawn dotted in their method's colour."""
LEGEND_ROW_IN = 0.22
"""Height of one row of the figure's legend, inches."""


def plot(cases: list[dict], path: Path, marks: dict[str, float] | None = None) -> None:
    """PSNR against seconds (log axis), one panel per case (a row per phantom, a column per
    setting), one curve per method; ``marks``: the paper's time of a method (s), a dashed
    vertical line in that method's colour."""
    plt = pyplot()
    phantoms = list(dict.fromkeys(case["phantom"] for case in cases))
    settings = list(dict.fromkeys(case["settings"] for case in cases))
    figure, axes = plt.subplots(
        len(phantoms),
        len(settings),
        figsize=(4.2 * len(settings), 3.4 * len(phantoms) + LEGEND_ROW_IN * 4),
        squeeze=False,
    )
    used = set()
    for case in cases:
        where = phantoms.index(case["phantom"]), settings.index(case["settings"])
        used.add(where)
        axis = axes[where]
        for method in METHODS:
            if method not in case["curves"]:
                continue
            curve = case["curves"][method]
            style = "--" if method == "4DGAT+skip" else "-"
            (line,) = axis.plot(curve["time_s"], curve["psnr"], style, marker=".", label=method)
            registered = curve_column(curve, "psnr_registered")
            if any(math.isfinite(value) for value in registered):
                axis.plot(curve["time_s"], registered, ":", color=line.get_color(), linewidth=1)
                axis.plot([], [], ":", color="0.4", linewidth=1, label=REGISTERED_LABEL)
            if method in (marks or {}):
                label = f"{method}, paper (Table S7)"
                axis.axvline(marks[method], color=line.get_color(), linestyle="--", label=label)
        summary = case["summary"]
        if math.isfinite(summary["crossover_s"]):
            axis.axvline(summary["crossover_s"], color="0.5", linestyle=":", linewidth=1)
        axis.set_xscale("log")
        axis.set_xlabel("compute time (s)")
        axis.set_ylabel("volume PSNR (dB)")
        axis.set_title(f"{case['phantom']}, {case['settings']}")
        axis.grid(alpha=0.3)
    for where, axis in np.ndenumerate(axes):
        axis.set_visible(where in used)
    labels = {}
    for axis in axes.flat:
        for handle, label in zip(*axis.get_legend_handles_labels()):
            labels.setdefault(label, handle)
    if REGISTERED_LABEL in labels:  # after the methods
        labels[REGISTERED_LABEL] = labels.pop(REGISTERED_LABEL)
    columns = max(1, min(len(labels), 3 * len(settings)))
    figure.legend(labels.values(), labels.keys(), loc="lower center", ncol=columns, fontsize=8)
    legend_in = LEGEND_ROW_IN * (math.ceil(len(labels) / columns) + 1)
    figure.tight_layout(rect=(0, legend_in / figure.get_figheight(), 1, 1))
    save_figure(figure, path)


CSV_COLUMNS = ("time_s", "psnr", "psnr_registered", "ssim", "sigma", "psf_error")
"""A curve's samples, one CSV column each (``psnr_registered`` and ``psf_error`` NaN in results
that predate them)."""


def curve_column(curve: dict, key: str) -> list[float]:
    return curve.get(key, [math.nan] * len(curve["time_s"]))


def write_results(cases: list[dict], out: Path, meta: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "time_vs_error.json", {**meta, "cases": cases})
    write_csv(
        out / "time_vs_error.csv",
        ["phantom", "settings", "method", *CSV_COLUMNS],
        [
            [case["phantom"], case["settings"], method, *row]
            for case in cases
            for method, curve in case["curves"].items()
            for row in zip(*(curve_column(curve, key) for key in CSV_COLUMNS))
        ],
    )
    plot(cases, out / "time_vs_error.png", meta.get("paper_times_s"))


def print_case(case: dict) -> None:
    summary = case["summary"]
    print(
        f"\n{case['phantom']}, {case['settings']}: SHB peak {summary['shb_peak_psnr']:.2f} dB, "
        f"ideal PSF's error {case.get('ideal_psf_error', math.nan):.4f}"
    )
    print(
        f"{'method':>14} {'best dB':>8} {'final dB':>8} {'aligned':>7} {'sigma':>7} "
        f"{'PSF err':>7} "
        f"{'total s':>8} {'to SHB peak s':>13} {'x SHB':>6} {'best reg':>8} {'x reg':>6} "
        f"{'eval s':>7}"
    )
    for row in summary["rows"]:
        print(
            f"{row['method']:>14} {row['best_psnr']:>8.2f} {row['final_psnr']:>8.2f} "
            f"{row.get('final_psnr_aligned', math.nan):>7.2f} {row['final_sigma']:>7.4f} "
            f"{row.get('final_psf_error', math.nan):>7.4f} "
            f"{row['total_s']:>8.2f} "
            f"{row['time_to_shb_peak_s']:>13.2f} {row['ratio_to_shb']:>6.1f} "
            f"{row.get('best_psnr_registered', math.nan):>8.2f} "
            f"{row.get('ratio_to_shb_registered', math.nan):>6.1f} {row['eval_s']:>7.2f}"
        )
    for suffix, scores in (("", "PSNR"), ("_registered", "registered PSNR")):
        psnr = summary.get(f"crossover_psnr{suffix}", math.nan)
        if not math.isfinite(psnr):
            continue
        crossover = summary[f"crossover{suffix}_s"]
        when = f"after {crossover:.1f} s" if math.isfinite(crossover) else "never"
        print(f"4DGAT passes the best {scores} of RL, SHB and 3DGAT ({psnr:.2f} dB) {when}")
    if "skip" in summary:
        skip = summary["skip"]
        step = skip["converged_at_step"]
        events = "every event ran" if step is None else f"events skipped after step {step}"
        print(
            f"skipping what converged optics do not need: {skip['seconds_saved']:.1f} s saved "
            f"({skip['speedup']:.1f}x), final PSNR {skip['psnr_change_db']:+.2f} dB, sigma "
            f"{skip['sigma_change']:+.4f}, {events}"
        )


def merge(parser: argparse.ArgumentParser, paths: list[Path], out: Path) -> None:
    """``--merge``: the results at ``paths`` written as one into ``out``, none overwritten."""
    target = (out / "time_vs_error.json").resolve()
    if any(Path(path).resolve() == target for path in paths):
        parser.error(f"--out {out} holds {target.name}, one of the results to merge")
    try:
        cases, meta = merge_results(paths)
    except ValueError as error:
        parser.error(str(error))
    for case in cases:
        print_case(case)
    write_results(cases, out, meta)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    scale = parser.add_mutually_exclusive_group()
    scale.add_argument("--quick", action="store_true", help="200 RL/SHB iterations, 800 steps")
    scale.add_argument(
        "--paper", action="store_true", help="the paper's scale (20x/0.45, 300 x 300 x 101; GPU)"
    )
    parser.add_argument("--phantom", nargs="+", choices=list(PHANTOMS), default=list(PHANTOMS))
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--steps",
        type=int,
        help="static steps of 3DGAT and 4DGAT (default: 800 with --quick, the recipe's 2,000 with "
        "--paper, 1600 otherwise); JPGM events keep their spacing to the end",
    )
    parser.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/time_vs_error"))
    parser.add_argument(
        "--merge", nargs="+", type=Path, metavar="JSON", help="write earlier results as one"
    )
    args = parser.parse_args()
    if args.merge:
        merge(parser, args.merge, args.out)
        return
    try:
        device = resolve_device(args.device)
    except ValueError as error:
        parser.error(str(error))
    iterations, steps = (200, 800) if args.quick else (500, 1600)
    if args.steps is not None and args.steps < 1:
        parser.error(f"--steps {args.steps}: expected a positive number of static steps")
    if args.paper:
        steps = None  # the recipe's
        if device.type != "cuda":
            print(f"--paper on {device}: meant for a GPU, this takes hours", flush=True)
    steps = args.steps or steps
    cases = []
    for phantom in args.phantom:
        for settings in args.settings:
            aberrated = SETTINGS[settings][1]
            skip = aberrated or not (args.quick or args.paper)
            case = run_case(
                phantom, settings, args.seed, iterations, steps, skip, device, args.paper
            )
            cases.append(case)
            print_case(case)
    meta = {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "scale": "paper" if args.paper else "quick" if args.quick else "cpu",
        "paper_times_s": TABLE_S7_S if args.paper else None,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "machine": platform.machine(),
        "seed": args.seed,
        "iterations": iterations,
        "static_steps": steps,
    }
    write_results(cases, args.out, meta)
