"""The quickstart as a user runs it: ``python -m fgat fit`` on ``configs/base/common.yaml`` and
``configs/quickstart.yaml``, in a fresh folder logging to a fresh SQLite store, from launch to
exit; its last validation scores (the Gaussians' and the SHB baseline's volume PSNR and x-y MIP
SSIM against the truth) read back from MLflow. The docs' quickstart page and the Python guide's
test quote these numbers.

    python benchmarks/quickstart.py [--out benchmarks/results/quickstart.json]
"""

from __future__ import annotations

import argparse
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fgat.app.recipes.benchmark import provenance, write_json

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SCORES = (
    "val/psnr_volume",
    "val/psnr_volume_shb",
    "val/psnr_volume_registered",
    "val/ssim_mip_xy",
    "val/ssim_mip_xy_shb",
)


def run_quickstart(folder: Path) -> tuple[float, dict[str, float]]:
    """Wall time (s) of the quickstart in ``folder`` and its last logged scores."""
    store = folder / "mlflow.db"
    words = [
        "fit",
        "--config",
        str(CONFIGS / "base" / "common.yaml"),
        "--config",
        str(CONFIGS / "quickstart.yaml"),
        f"--mlflow.tracking_uri=sqlite:///{store}",
        "--trainer.enable_progress_bar=false",
    ]
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "fgat", *words], cwd=folder, check=True)
    seconds = time.perf_counter() - start
    with sqlite3.connect(store) as database:
        rows = database.execute("SELECT key, value FROM latest_metrics").fetchall()
    logged = dict(rows)
    return seconds, {name: logged[name] for name in SCORES if name in logged}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="benchmarks/results/quickstart.json")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        seconds, scores = run_quickstart(Path(folder))
    result = {
        **provenance("python benchmarks/quickstart.py"),
        "configs": ["configs/base/common.yaml", "configs/quickstart.yaml"],
        "scores": [{"metric": name, "value": round(value, 4)} for name, value in scores.items()],
        "wall_s": round(seconds, 1),
    }
    write_json(args.out, result)


if __name__ == "__main__":
    main()
