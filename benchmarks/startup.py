"""Benchmark what a ``python -m fgat`` process costs around its work: a short fit (the quickstart
recipe cut to 20 steps and 100 Gaussians, logging to a fresh SQLite store) from launch to exit,
split at its last line of output into the run and the exit after it, ended the way ``python -m
fgat`` ends (:func:`fgat.app.process.exit_without_finalising`) against Python's own exit (the same
``main`` under ``sys.exit``), in alternating rounds; and how long a missing ``--config`` takes to
be refused.

    python benchmarks/startup.py [--repeats 3] [--out benchmarks/results/startup.json]
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fgat.app.recipes.benchmark import parser, write_json

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SHORT_FIT = [
    "fit",
    "--config",
    str(CONFIGS / "base" / "common.yaml"),
    "--config",
    str(CONFIGS / "quickstart.yaml"),
    "--trainer.max_steps=20",
    "--trainer.val_check_interval=20",
    "--trainer.enable_progress_bar=false",
    "--trainer.callbacks=[]",
    "--model.init_args.n_gaussians=100",
]
LAUNCHERS = {
    "python -m fgat": ["-m", "fgat"],
    "Python's exit": [
        "-c",
        "import sys; from fgat.app.cli import main; sys.exit(main(sys.argv[1:]))",
    ],
}


def run(launcher: list[str], words: list[str], folder: Path) -> dict:
    """Wall time (s) of ``python <launcher> <words>`` in ``folder``, to its last line of output
    and to its exit."""
    start = time.perf_counter()
    last = start
    process = subprocess.Popen(
        [sys.executable, *launcher, *words],
        cwd=folder,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "MLFLOW_TRACKING_URI": "", "PYTHONUNBUFFERED": "1"},
    )
    lines = []
    for line in process.stdout:
        last = time.perf_counter()
        lines.append(line)
    code = process.wait()
    end = time.perf_counter()
    return {"code": code, "total_s": end - start, "exit_s": end - last, "output": "".join(lines)}


def main() -> None:
    args = parser(__doc__, "benchmarks/results/startup.json", "one round").parse_args()
    rounds = 1 if args.quick else max(1, args.repeats)
    samples = {name: [] for name in LAUNCHERS}
    with tempfile.TemporaryDirectory() as root:
        for index in range(rounds):
            for name, launcher in LAUNCHERS.items():
                folder = Path(root) / f"{index}-{len(samples[name])}-{name[:6].strip()}"
                folder.mkdir()
                words = [*SHORT_FIT, f"--mlflow.tracking_uri=sqlite:///{folder}/mlflow.db"]
                result = run(launcher, words, folder)
                if result["code"] != 0:
                    raise SystemExit(f"{name}: exit code {result['code']}:\n{result['output']}")
                samples[name].append(result)
        refusals = [
            run(LAUNCHERS["python -m fgat"], ["fit", "--config", "missing.yaml"], Path(root))
            for _ in range(rounds)
        ]
    rows = {
        name: {
            "total_s": statistics.median(r["total_s"] for r in runs),
            "total_range_s": [min(r["total_s"] for r in runs), max(r["total_s"] for r in runs)],
            "exit_s": statistics.median(r["exit_s"] for r in runs),
            "exit_range_s": [min(r["exit_s"] for r in runs), max(r["exit_s"] for r in runs)],
        }
        for name, runs in samples.items()
    }
    refusal_s = statistics.median(r["total_s"] for r in refusals)
    print(f"short fit (20 steps), {rounds} alternating round(s), medians:")
    print(f"{'ended by':>16} {'launch to exit s':>17} {'exit after last line s':>23}")
    for name, row in rows.items():
        print(f"{name:>16} {row['total_s']:>17.2f} {row['exit_s']:>23.2f}")
    print(f"\nmissing --config refused after {refusal_s:.2f} s")
    write_json(
        args.out,
        {"rounds": rounds, "short_fit": rows, "missing_config_refused_s": refusal_s},
    )


if __name__ == "__main__":
    main()
