"""Fig. S9: RMS sweep of JPGM self-estimation (run by ``reproduce/figS9.sh``).

Every (RMS, seed) trial is one fit of ``configs/figS9.yaml`` (with ``--quick`` also
``configs/figS9_quick.yaml``) on its scale's bases (:func:`fgat.app.recipes.optics.recipe_configs`)
into one MLflow experiment (run name ``rms<R>-seed<S>``, aberrations rescaled to R waves RMS from
seed S, bead scene from seed S); a trial that already finished with the same fingerprint
(resolved configuration and inputs) is skipped (``--refit`` fits it again), so a killed sweep
resumes and a changed config runs again. The summary (``reproduce/figS9_summary.py``,
:func:`fgat.app.recipes.figS9_summary.main`) then reads the runs back and draws
panels a-e.

    python reproduce/figS9.py [--quick] [--seeds 0 1 2 3 4] [--levels 0.5 1.0 1.5 2.0] [--refit]

Other options (e.g. ``--trainer.accelerator=gpu``) are passed to every fit (and change its
fingerprint).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fgat.app.lightning_cli import tracking_uri
from fgat.app.process import run_recipe
from fgat.app.recipes import figS9_summary
from fgat.app.recipes.optics import config_args, recipe_configs
from fgat.app.trials import add_fanout_arguments, add_refit_argument, fanout_from, run_fits

LEVELS = {"figS9": (0.5, 1.0, 1.5, 2.0), "figS9_quick": (0.05, 0.1, 0.15, 0.2)}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small CPU optics, RMS 0.05-0.2 waves")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--levels", type=float, nargs="+", default=None, help="RMS levels in waves")
    parser.add_argument("--tracking-uri", default=None)
    add_fanout_arguments(parser)
    add_refit_argument(parser)
    args, extra = parser.parse_known_args()
    experiment = "figS9_quick" if args.quick else "figS9"
    configs = recipe_configs("figS9", args.quick)
    missing = [config for config in configs if not Path(config).is_file()]
    if missing:
        raise SystemExit(f"{', '.join(missing)} not found: run from the repository root")
    uri = tracking_uri(args.tracking_uri)
    fits = [
        (
            [
                "fit",
                *config_args(configs),
                f"--mlflow.experiment={experiment}",
                f"--mlflow.tracking_uri={uri}",
                f"--mlflow.run_name=rms{rms}-seed{seed}",
                f"--seed_everything={seed}",
                f"--data.init_args.simulation.seed={seed}",
                f"--data.init_args.simulation.aberrations={{terms: 17, rms: {rms}, seed: {seed}}}",
                *extra,
            ],
            f"runs/{experiment}/rms{rms}-seed{seed}",
        )
        for rms in args.levels or LEVELS[experiment]
        for seed in args.seeds
    ]
    run_fits(fits, fanout_from(args), refit=args.refit, label=experiment)
    figS9_summary.main(["--experiment", experiment, "--tracking-uri", uri])


if __name__ == "__main__":
    run_recipe(main, "figS9")
