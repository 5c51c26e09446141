"""Figs. S5-S8: JPGM self-estimation of the optics, 4DGAT against 3DGAT and SHB.

For each seed (one draw of the true optics and of the bead scene) the recipe's configs
(:func:`recipe_configs`) are fitted twice into one MLflow experiment: 4DGAT (the figure's
``optics.estimate``) and 3DGAT (``estimate = none``: the ideal PSF throughout); every run also
logs SHB with the ideal PSF. The summary reads
the runs back from MLflow and writes, under ``--out/<figure>[_quick]/``:

* ``summary.csv``: per seed, sigma = ||c - c_gt|| / ||c_gt||, the largest intercept and slope
  errors (pixels; also without what a moved scene explains, see
  ``fgat.recon.estimation.remove_scene_gauge``), the relative PSF error of the estimated and of
  the ideal stack, and volume PSNR (as it is and registered to the truth, without the scene's
  translation that a joint estimate leaves open) / SSIM / x-y MIP SSIM of 4DGAT, 3DGAT and SHB;
* ``psf_views.csv``: the relative error of each view's PSF, estimated and ideal;
* ``seed<k>/mips.png``: x-y and x-z MIPs of 3DGAT, 4DGAT, SHB and the truth, plus the 4DGAT
  run's pupil-phase, Zernike-bar and per-view PSF figures.

The command line:

    python reproduce/optics.py figS6 --quick [--seeds 0 1 2] [--tracking-uri sqlite:///mlflow.db]

A trial that already finished with the same fingerprint (resolved configuration and inputs, the
``fgat.app.fingerprint`` tag of its MLflow run) is not fitted again (``--refit`` forces it), so a
killed recipe resumes where it stopped, and a changed config or code default runs again.

Figures: figS5 (lenslet shifts only), figS6 (aberrations only, four trials), figS7 (joint, strong
aberrations and shifts), figS8 (joint, seven-term truth, 17 terms estimated). Without ``--quick``
they run at the paper's scale (20x/0.45, 300 x 300 x 101; meant for a GPU):
``configs/base/common.yaml``, ``configs/base/paper.yaml``, ``configs/base/optics_paper.yaml``,
``configs/<figure>.yaml``; with it at the CPU scale: ``configs/base/common.yaml``,
``configs/base/optics_quick.yaml``, ``configs/<figure>.yaml``, ``configs/<figure>_quick.yaml``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from fgat.app.lightning_cli import resolved_config, tracking_uri
from fgat.app.pipeline import option_words
from fgat.app.trials import add_fanout_arguments, add_refit_argument, fanout_from, run_fits
from fgat.io.files import write_csv
from fgat.io.images import read_tiff
from fgat.optics.systems import load_system, parse_depths
from fgat.recon import names
from fgat.sim.simulation import SimulationConfig, make_phantom
from fgat.viz.volumes import plot_mips

if TYPE_CHECKING:  # MLflow is imported where runs are read, as in fgat.app.callbacks.mlflow
    import mlflow

RECIPES = {
    "figS5": ("shifts", (0,)),
    "figS6": ("zernike", (0, 1, 2, 3)),
    "figS7": ("joint", (0,)),
    "figS8": ("joint", (0,)),
}
METHODS = ("4DGAT", "3DGAT")
SCORES = {
    "psnr": names.PSNR,
    "psnr_registered": names.PSNR_REGISTERED,
    "ssim": names.SSIM,
    "ssim_xy": names.SSIM_XY,
}
OPTICS = {
    "sigma": names.ZERNIKE_RESIDUAL,
    **dict(
        zip(
            (
                "intercept_error_px",
                "intercept_error_gauge_free_px",
                "slope_error_px",
                "slope_error_gauge_free_px",
            ),
            names.SHIFT_ERRORS,
        )
    ),
    "psf_error": names.PSF_ERROR,
    "psf_error_ideal": names.PSF_ERROR_INITIAL,
}
FIGURES = ("pupil_phase.png", "zernike.png", "psf_ideal.png", "psf_estimated.png", "psf_truth.png")


def recipe_configs(figure: str, quick: bool) -> list[str]:
    """The config files of ``figure`` (``figS5`` ... ``figS9``), laid in this order: the paper's
    scale, or with ``quick`` the CPU one (the figure's overlay, then its ``_quick`` one)."""
    if quick:
        return [
            "configs/base/common.yaml",
            "configs/base/optics_quick.yaml",
            f"configs/{figure}.yaml",
            f"configs/{figure}_quick.yaml",
        ]
    return [
        "configs/base/common.yaml",
        "configs/base/paper.yaml",
        "configs/base/optics_paper.yaml",
        f"configs/{figure}.yaml",
    ]


def config_args(configs: list[str]) -> list[str]:
    """``--config`` options laying ``configs`` in order."""
    return option_words("--config", configs)


def trial_args(
    configs: list[str], experiment: str, uri: str, seed: int, method: str, estimate: str
) -> list[str]:
    """The ``fit`` of ``configs`` as ``method`` (4DGAT: ``estimate``; 3DGAT: optics fixed)."""
    return [
        "fit",
        *config_args(configs),
        f"--mlflow.experiment={experiment}",
        f"--mlflow.tracking_uri={uri}",
        f"--mlflow.run_name={method}-seed{seed}",
        f"--seed_everything={seed}",
        f"--data.init_args.simulation.seed={seed}",
        f"--model.init_args.optics.estimate={estimate if method == '4DGAT' else 'none'}",
    ]


def add_trial_arguments(parser: argparse.ArgumentParser) -> None:
    """The options every trial recipe takes: ``--tracking-uri``, ``--summary-only``, ``--refit``,
    ``--out`` and where the trials run (``--parallel``, ``--address``, ...:
    :func:`fgat.app.trials.add_fanout_arguments`)."""
    add_fanout_arguments(parser)
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument(
        "--summary-only", action="store_true", help="read existing runs, fit nothing"
    )
    add_refit_argument(parser)
    parser.add_argument("--out", default="reproduce/results")


def latest_runs(experiment: str, uri: str) -> dict[str, mlflow.entities.Run]:
    """The latest finished run of each run name in ``experiment``."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    client = mlflow.MlflowClient(uri)
    found = client.get_experiment_by_name(experiment)
    runs = {}
    if found is None:
        return runs
    for record in client.search_runs(
        [found.experiment_id],
        filter_string="attributes.status = 'FINISHED'",
        order_by=["attributes.start_time ASC"],
    ):
        runs[record.info.run_name] = record
    return runs


def summary_rows(runs: dict, seeds) -> tuple[list[dict], list[dict]]:
    """Per-seed scores of 4DGAT, 3DGAT and SHB with the optics errors, and per-view PSF errors."""
    rows, views = [], []
    for seed in seeds:
        run_names = {method: f"{method}-seed{seed}" for method in METHODS}
        missing = [name for name in run_names.values() if name not in runs]
        if missing:
            raise SystemExit(f"no finished MLflow run named {', '.join(missing)}")
        four, three = (runs[run_names[method]].data.metrics for method in METHODS)
        row = {
            "seed": seed,
            **{key: four.get(metric, float("nan")) for key, metric in OPTICS.items()},
        }
        for key, metric in SCORES.items():  # NaN where a run predates a score
            row[f"{key}_4dgat"], row[f"{key}_3dgat"] = (
                run.get(metric, float("nan")) for run in (four, three)
            )
            row[f"{key}_shb"] = four.get(metric + names.SHB, float("nan"))
        rows.append(row)
        n_views = sum(1 for name in four if name.startswith("psf/error_view"))
        views += [
            {
                "seed": seed,
                "view": v,
                "psf_error": four[f"psf/error_view{v}"],
                "psf_error_ideal": four[f"psf/error_initial_view{v}"],
            }
            for v in range(n_views)
        ]
    return rows, views


def truth_volume(configs: list[str], seed: int):
    """The phantom of the simulation of ``configs`` for ``seed`` (what the runs were fitted to), its
    voxel size (um) and its kind."""
    resolved = resolved_config(
        ["fit", *config_args(configs), f"--data.init_args.simulation.seed={seed}"]
    )
    simulation = SimulationConfig(**resolved["data"]["init_args"]["simulation"])
    depths = parse_depths(simulation.depths_um)
    volume = make_phantom(simulation, (len(depths), simulation.view_size, simulation.view_size))
    return (
        volume,
        load_system(simulation.system).grid_voxel_size_um(depths),
        simulation.phantom["kind"],
    )


def seed_figures(runs: dict, seed: int, configs: list[str], folder: Path, uri: str) -> None:
    """MIPs of 3DGAT, 4DGAT, SHB and the truth, and the 4DGAT run's optics figures."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    folder.mkdir(parents=True, exist_ok=True)
    four, three = runs[f"4DGAT-seed{seed}"], runs[f"3DGAT-seed{seed}"]
    volumes = {}
    for label, record, artifact in (
        ("3DGAT (ideal PSF)", three, "volume.ome.tif"),
        ("4DGAT (estimated optics)", four, "volume.ome.tif"),
        ("SHB (ideal PSF)", four, "shb.ome.tif"),
    ):
        path = mlflow.artifacts.download_artifacts(
            run_id=record.info.run_id,
            artifact_path=artifact,
            dst_path=str(folder / record.info.run_name),
            tracking_uri=uri,
        )
        volumes[label] = read_tiff(path, ndim=3)
    volumes["ground truth"], voxel_size_um, kind = truth_volume(configs, seed)
    plot_mips(
        volumes,
        folder / "mips.png",
        title=f"seed {seed}: {kind} phantom",
        voxel_size_um=voxel_size_um,
    )
    logged = {
        artifact.path for artifact in mlflow.MlflowClient(uri).list_artifacts(four.info.run_id)
    }
    for name in sorted(logged & set(FIGURES)):
        mlflow.artifacts.download_artifacts(
            run_id=four.info.run_id, artifact_path=name, dst_path=str(folder), tracking_uri=uri
        )


def print_table(rows: list[dict]) -> None:
    print(
        f"{'seed':>4} {'sigma':>7} {'b err px':>9} {'(gauge-free)':>12} "
        f"{'PSF err':>8} {'ideal':>7} "
        f"{'PSNR 4DGAT':>11} {'3DGAT':>6} {'SHB':>6} {'registered 4DGAT':>17} {'3DGAT':>6} "
        f"{'SHB':>6}"
    )
    for r in rows:
        print(
            f"{r['seed']:>4} {r['sigma']:>7.3f} {r['intercept_error_px']:>9.3f} "
            f"{r['intercept_error_gauge_free_px']:>12.3f} "
            f"{r['psf_error']:>8.3f} {r['psf_error_ideal']:>7.3f} {r['psnr_4dgat']:>11.2f} "
            f"{r['psnr_3dgat']:>6.2f} {r['psnr_shb']:>6.2f} {r['psnr_registered_4dgat']:>17.2f} "
            f"{r['psnr_registered_3dgat']:>6.2f} {r['psnr_registered_shb']:>6.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("figure", choices=sorted(RECIPES))
    parser.add_argument(
        "--quick",
        action="store_true",
        help="CPU scale (configs/base/optics_quick.yaml, configs/<figure>_quick.yaml)",
    )
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=None, help="default: the figure's trials"
    )
    add_trial_arguments(parser)
    args = parser.parse_args()
    estimate, default_seeds = RECIPES[args.figure]
    seeds = args.seeds or list(default_seeds)
    experiment = args.figure + ("_quick" if args.quick else "")
    configs = recipe_configs(args.figure, args.quick)
    missing = [config for config in configs if not Path(config).is_file()]
    if missing:
        raise SystemExit(f"{', '.join(missing)} not found: run from the repository root")
    uri = tracking_uri(args.tracking_uri)
    if not args.summary_only:
        fits = [
            (
                trial_args(configs, experiment, uri, seed, method, estimate),
                f"runs/{experiment}/{method}-seed{seed}",
            )
            for seed in seeds
            for method in METHODS
        ]
        run_fits(fits, fanout_from(args), refit=args.refit, label=experiment)
    runs = latest_runs(experiment, uri)
    rows, views = summary_rows(runs, seeds)
    out = Path(args.out) / experiment
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "summary.csv", list(rows[0]), rows)
    if views:
        write_csv(out / "psf_views.csv", list(views[0]), views)
    else:
        print(f"no run logged per-view PSF errors (no JPGM event): {out / 'psf_views.csv'} skipped")
    for seed in seeds:
        seed_figures(runs, seed, configs, out / f"seed{seed}", uri)
    print_table(rows)
    print(f"summary -> {out / 'summary.csv'}")
