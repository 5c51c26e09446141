"""Are the standard errors of the estimated optics honest? Coverage over Figs. S5-S7 quick trials.

Runs the 4DGAT fit of a quick optics recipe (``--figure``: ``figS6``, aberrations only,
``optics.estimate = zernike``, the default; ``figS5``, lenslet shifts only; ``figS7``, both
jointly; ``reproduce/optics.py``'s configs, seeds and MLflow experiment ``<figure>_quick``, so
its trials are shared with ``python reproduce/optics.py <figure> --quick``) for each seed, reads
back the
``identifiability.csv`` each run leaves (per estimated parameter: estimate, standard error at the
end of the fit, truth), and reports the coverage: the fraction of parameters whose true error
``|estimate - truth|`` is within two standard errors (about 95% if the standard errors are
honest), per seed and over all, for the Zernike coefficients and, when estimated, the shifts.
Writes under ``--out/identifiability_coverage/<figure>/``:

* ``identifiability.csv``: every run's rows with a ``seed`` column;
* ``coverage.csv``: per seed and group, parameters, within 2 s.e., coverage, the coverage of
  the noise part of the standard error alone (``stderr_noise``, without the joint correction),
  the median of ``|error| / s.e.``, the residual's uniform noise level.

    python reproduce/identifiability_coverage.py [--figure figS6] [--seeds 0 1 ... 9]
        [--tracking-uri URI]

A trial that already finished with the same fingerprint is not fitted again (``--refit`` forces
it); ``--summary-only`` reads the runs back without fitting.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import mlflow
import numpy as np

from fgat.app.lightning_cli import tracking_uri
from fgat.app.process import run_recipe
from fgat.app.recipes import optics
from fgat.app.trials import fanout_from, run_fits
from fgat.io.files import write_csv
from fgat.recon import names

METHOD = "4DGAT"
GROUPS = {"zernike": "zernike/", "shifts": "shift/"}


def seed_rows(run, uri: str, folder: Path) -> list[dict]:
    """The rows of a run's ``identifiability.csv``, numbers as floats."""
    path = mlflow.artifacts.download_artifacts(
        run_id=run.info.run_id,
        artifact_path="identifiability.csv",
        dst_path=str(folder),
        tracking_uri=uri,
    )
    with open(path, newline="") as handle:
        return [
            {key: value if key == "parameter" else float(value) for key, value in row.items()}
            for row in csv.DictReader(handle)
        ]


def coverage(rows: list[dict]) -> dict[str, float]:
    """Parameters, how many have ``|error| <= 2 s.e.``, that fraction, the same fraction for the
    noise part of the standard error alone, and the median ``|error| / s.e.``."""
    error = np.array([abs(row["error"]) for row in rows])
    stderr = np.array([row["stderr"] for row in rows])
    within = int(sum(row["within_2se"] for row in rows))
    return {
        "parameters": len(rows),
        "within_2se": within,
        "coverage": within / len(rows),
        "coverage_noise_only": float(
            np.mean(error <= 2 * np.array([r["stderr_noise"] for r in rows]))
        ),
        "median_error_over_se": float(np.median(error / stderr)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--figure", choices=("figS5", "figS6", "figS7"), default="figS6")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    optics.add_trial_arguments(parser)
    args = parser.parse_args()
    estimate, _ = optics.RECIPES[args.figure]
    experiment = f"{args.figure}_quick"
    configs = optics.recipe_configs(args.figure, quick=True)
    missing = [config for config in configs if not Path(config).is_file()]
    if missing:
        raise SystemExit(f"{', '.join(missing)} not found: run from the repository root")
    uri = tracking_uri(args.tracking_uri)
    if not args.summary_only:
        fits = [
            (
                optics.trial_args(configs, experiment, uri, seed, METHOD, estimate),
                f"runs/{experiment}/{METHOD}-seed{seed}",
            )
            for seed in args.seeds
        ]
        run_fits(fits, fanout_from(args), refit=args.refit, label=experiment)
    runs = optics.latest_runs(experiment, uri)
    out = Path(args.out) / "identifiability_coverage" / args.figure
    out.mkdir(parents=True, exist_ok=True)
    every, table = [], []
    for seed in args.seeds:
        name = f"{METHOD}-seed{seed}"
        if name not in runs:
            raise SystemExit(f"no finished MLflow run named {name} in {experiment}")
        rows = seed_rows(runs[name], uri, out / name)
        if "truth" not in rows[0]:
            raise SystemExit(f"{name}: identifiability.csv has no truth (not a phantom run?)")
        every += [{"seed": seed, **row} for row in rows]
        for group, prefix in GROUPS.items():
            chosen = [row for row in rows if row["parameter"].startswith(prefix)]
            if chosen:
                table.append(
                    {
                        "seed": seed,
                        "group": group,
                        **coverage(chosen),
                        "noise_sigma": runs[name].data.metrics[names.NOISE_SIGMA],
                    }
                )
    write_csv(out / "identifiability.csv", list(every[0]), every)
    write_csv(out / "coverage.csv", list(table[0]), table)
    print(f"{'seed':>4} {'group':>8} {'within 2 s.e.':>14} {'coverage':>9} {'median |e|/se':>14}")
    for row in table:
        print(
            f"{row['seed']:>4} {row['group']:>8} "
            f"{row['within_2se']:>6}/{row['parameters']:<7} {row['coverage']:>9.0%} "
            f"{row['median_error_over_se']:>14.2f}"
        )
    for group, prefix in GROUPS.items():
        chosen = [row for row in every if row["parameter"].startswith(prefix)]
        if chosen:
            total = coverage(chosen)
            print(
                f"{group}: {total['within_2se']} of {total['parameters']} true errors within "
                f"2 s.e. over {len(args.seeds)} seeds: coverage {total['coverage']:.1%} "
                f"(honest: about 95%; {total['coverage_noise_only']:.1%} for the noise part "
                f"alone); median |error| / s.e. {total['median_error_over_se']:.2f}"
            )
    print(f"coverage -> {out / 'coverage.csv'}")


if __name__ == "__main__":
    run_recipe(main, "identifiability_coverage")
