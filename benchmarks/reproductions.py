"""The CPU-scale reproductions the docs quote: each recipe run as its page says, into a fresh
MLflow store and results folder, its wall time and its result table kept.

* ``figS5_quick`` and ``figS6_quick``: ``python reproduce/optics.py figS5 --quick --seeds 0 1 2
  3`` and ``python reproduce/optics.py figS6 --quick`` (seeds 0-3 each: 4DGAT and 3DGAT, SHB
  logged beside them): ``summary.csv``'s row per seed;
* ``figS12``: ``python reproduce/figS12.py`` (the quick beating shell, both stages): each
  time point's volume PSNR of the nearest frame, cubic interpolation and 4DGAT, and their means
  over the interpolated time points.

    python benchmarks/reproductions.py [--out benchmarks/results/reproductions_quick.json]

Run it from the repository root (the recipes read ``configs/``), with no earlier fits of these
recipes under ``runs/`` (a fit finds its folder's last checkpoint and resumes from it, which
would time the resumption).
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fgat.app.recipes.benchmark import write_json

FIGS12_SCORES = ("psnr_volume_frames", "psnr_volume_cubic", "psnr_volume_4DGAT")
OPTICS_FIGURES = ("figS5", "figS6")
RUN_FOLDERS = ("runs/figS5_quick", "runs/figS6_quick", "runs/dynamic_quick")
"""Where the recipes fit (their configs' ``trainer.default_root_dir``): earlier fits there are
resumed or skipped, so their time would not be a fit's."""
OPTICS_SEEDS = ("--seeds", "0", "1", "2", "3")


def timed(command: list[str], store: Path) -> float:
    """Wall time (s) of ``command`` run from the repository root, logging to ``store``."""
    start = time.perf_counter()
    environment = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{store}"}
    subprocess.run(command, check=True, env=environment)
    return time.perf_counter() - start


def table(path: Path) -> list[dict]:
    """A CSV's rows, numbers as floats rounded to 4 decimals."""
    with open(path, newline="") as file:
        rows = list(csv.DictReader(file))
    return [{key: _number(value) for key, value in row.items()} for row in rows]


def _number(text: str):
    try:
        return round(float(text), 4)
    except ValueError:
        return text


def figS12_means(rows: list[dict]) -> list[dict]:
    """Each method's mean volume PSNR over the interpolated time points (not acquired)."""
    between = [row for row in rows if row["acquired_frame"] == "False"]
    return [
        {"method": name.removeprefix("psnr_volume_"), "mean_psnr_db": round(mean, 4)}
        for name in FIGS12_SCORES
        for mean in [statistics.fmean(row[name] for row in between)]
    ]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="benchmarks/results/reproductions_quick.json")
    args = parser.parse_args()
    earlier = [folder for folder in RUN_FOLDERS if Path(folder).exists()]
    if earlier:
        parser.error(
            f"{', '.join(earlier)}: earlier fits of these recipes, which they would resume or "
            "skip instead of timing a fit; move them away first"
        )
    result = {}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        python = sys.executable
        for figure in OPTICS_FIGURES:
            seconds = timed(
                [python, "reproduce/optics.py", figure, "--quick", *OPTICS_SEEDS]
                + ["--out", str(folder)],
                folder / f"{figure}.db",
            )
            rows = table(folder / f"{figure}_quick" / "summary.csv")
            result[f"{figure}_quick"] = {"wall_s": round(seconds, 1), "rows": rows}
        seconds = timed(
            [python, "reproduce/figS12.py", "--out", str(folder / "figS12")], folder / "figS12.db"
        )
        rows = table(folder / "figS12" / "figS12.csv")
        result["figS12"] = {"wall_s": round(seconds, 1), "means": figS12_means(rows), "rows": rows}
    write_json(args.out, result)


if __name__ == "__main__":
    main()
