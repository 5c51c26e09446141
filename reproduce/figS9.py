"""Fig. S9: RMS sweep of JPGM self-estimation (run by ``reproduce/figS9.sh``).

Every (RMS, seed) trial is one fit of ``configs/figS9[_quick].yaml`` into one MLflow experiment
(run name ``rms<R>-seed<S>``, aberrations rescaled to R waves RMS from seed S, bead scene from
seed S); trials that already finished are skipped, so a killed sweep resumes. The summary
(``reproduce/figS9_summary.py``) then reads the runs back and draws panels a-e.

    python reproduce/figS9.py [--quick] [--seeds 0 1 2 3 4] [--levels 0.5 1.0 1.5 2.0]
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import mlflow

from fgat.lightning_cli import run, tracking_uri

LEVELS = {"figS9": (0.5, 1.0, 1.5, 2.0), "figS9_quick": (0.05, 0.1, 0.15, 0.2)}


def finished_runs(experiment: str) -> set[str]:
    """Names of the finished runs of ``experiment`` (empty if it does not exist yet)."""
    if mlflow.get_experiment_by_name(experiment) is None:
        return set()
    frame = mlflow.search_runs(experiment_names=[experiment], filter_string="attributes.status = 'FINISHED'")
    return set(frame["tags.mlflow.runName"]) if not frame.empty else set()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small CPU optics, RMS 0.05-0.2 waves")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--levels", type=float, nargs="+", default=None, help="RMS levels in waves")
    parser.add_argument("--tracking-uri", default=None)
    args = parser.parse_args()
    experiment = "figS9_quick" if args.quick else "figS9"
    config = Path(f"configs/{experiment}.yaml")
    if not config.is_file():
        raise SystemExit(f"{config} not found: run from the repository root")
    uri = tracking_uri(args.tracking_uri)
    mlflow.set_tracking_uri(uri)
    done = finished_runs(experiment)
    for rms in args.levels or LEVELS[experiment]:
        for seed in args.seeds:
            name = f"rms{rms}-seed{seed}"
            if name in done:
                print(f"figS9: {name} already finished, skipped")
                continue
            run(["fit", "--config", str(config), f"--mlflow.experiment={experiment}", f"--mlflow.tracking_uri={uri}",
                 f"--mlflow.run_name={name}", f"--seed_everything={seed}", f"--data.init_args.simulation.seed={seed}",
                 f"--data.init_args.simulation.aberrations={{terms: 17, rms: {rms}, seed: {seed}}}",
                 f"--trainer.default_root_dir=runs/{experiment}/{name}"])
    spec = importlib.util.spec_from_file_location("figS9_summary", Path(__file__).with_name("figS9_summary.py"))
    summary = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(summary)
    summary.main(["--experiment", experiment, "--tracking-uri", uri])


if __name__ == "__main__":
    main()
