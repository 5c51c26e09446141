"""``benchmarks/gpu_checks.sh``: the GPU run's steps, each at a tiny size on the CPU (dry run)."""

import csv
import json
import math
import os
import subprocess
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "gpu_checks.sh"
STEPS = [
    "triton_tests",
    "static_step",
    "dynamic_step",
    "jpgm_update",
    "optics_trial",
    "engine_step",
    "dynamic_profile",
    "crossinfo",
]
"""The steps, the most important first."""


def run(*arguments: str, budget: str | None = None) -> subprocess.CompletedProcess:
    env = None if budget is None else {**os.environ, "GPU_CHECKS_BUDGET_S": budget}
    return subprocess.run(
        ["bash", str(SCRIPT), *arguments],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        env=env,
    )


def summary(out: Path) -> list[dict]:
    with (out / "gpu_checks_summary.tsv").open() as handle:
        return list(csv.DictReader(handle, delimiter="\t"))


def positive(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


@pytest.mark.slow
def test_dry_run_runs_every_step_and_writes_its_results(tmp_path):
    """Every step ok in the summary, in order, with its seconds; each result file holds finite
    positive timings; the trial's two JPGM events (after steps 2 and 3) a finite sigma each; the
    Triton tests' JUnit XML no failure or error (on a CPU all 15 skip: no CUDA); the tables'
    leakage cases finite ratios."""
    result = run("--dry-run", str(tmp_path))
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    rows = summary(tmp_path)
    assert [row["step"] for row in rows] == STEPS
    assert all(row["status"] == "ok" for row in rows), rows
    assert all(0 <= int(row["seconds"]) <= int(row["limit_s"]) for row in rows)

    static, dynamic, engine, jpgm = (
        json.loads((tmp_path / f"{name}.json").read_text())
        for name in ("static_step", "dynamic_step", "engine_step", "jpgm_update")
    )
    assert static["command"].startswith("python benchmarks/static_step.py --tiny")
    assert [row["case"] for row in static["steps"]] == ["tiny"]
    assert all(
        positive(static["steps"][0][key]) for key in ("voxelize_s", "projection_s", "step_s")
    )
    assert positive(static["dense"]["speedup"]) and static["dense"]["max_abs_difference"] < 1e-5
    row = dynamic["steps"][0]
    assert row["case"] == "tiny" and positive(row["step_s"]) and positive(row["deformation_s"])
    assert [row["engine"] for row in engine["steps"]] == ["static", "dynamic"]
    assert all(positive(row["step_s"]) and row["ops"] > 0 for row in engine["steps"])
    assert all(positive(row["update_s"]) and positive(row["psf_s"]) for row in jpgm["rows"])
    assert "Self CPU time total" in (tmp_path / "dynamic_step_profile.txt").read_text()

    trial = json.loads((tmp_path / "optics_trial.json").read_text())
    assert (trial["figure"], trial["seed"], trial["steps"]) == ("figS7", 3, 3)
    assert [event["step"] for event in trial["events"]] == [2, 3]
    assert all(math.isfinite(event["sigma"]) and event["sigma"] > 0 for event in trial["events"])
    assert positive(trial["total_s"])

    suite = ElementTree.parse(tmp_path / "triton_tests.xml").getroot().find("testsuite")
    assert int(suite.get("tests")) >= 15
    assert suite.get("failures") == suite.get("errors") == "0"
    if not torch.cuda.is_available():
        assert suite.get("skipped") == suite.get("tests")

    tables = json.loads((tmp_path / "tablesS2_S5" / "summary.json").read_text())
    assert tables["volume_shape"] == [7, 32, 32]
    assert all(positive(case["ratio"]) for case in tables["leakage"]["cases"])
    assert (tmp_path / "tablesS2_S5" / "comparison.md").is_file()
    assert {path.stem for path in (tmp_path / "gpu_checks_logs").iterdir()} == set(STEPS)


def test_a_spent_budget_skips_every_step_and_fails(tmp_path):
    """With no time left every step is skipped, listed in the summary, and the run fails."""
    result = run("--dry-run", str(tmp_path), budget="0")
    assert result.returncode == 1
    rows = summary(tmp_path)
    assert [row["step"] for row in rows] == STEPS
    assert all(row["status"] == "skipped" for row in rows)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU here runs the real checks")
def test_without_a_gpu_the_real_run_refuses_and_says_why(tmp_path):
    result = run(str(tmp_path))
    assert result.returncode == 2
    assert "no CUDA GPU" in result.stderr and "--dry-run" in result.stderr
    assert not (tmp_path / "gpu_checks_summary.tsv").exists()
