"""Committed benchmark results say where they come from: every file in benchmarks/results/
carries its date, machine, commit and command, as the docs render them."""

import json
import sys
from pathlib import Path

import pytest

from fgat.app.recipes.benchmark import write_json

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
HEADER = {"date", "machine", "commit", "command"}


@pytest.mark.parametrize("path", sorted(RESULTS.glob("*.json")), ids=lambda path: path.name)
def test_committed_results_carry_their_provenance(path):
    result = json.loads(path.read_text())
    assert HEADER <= set(result), f"{path.name} lacks {HEADER - set(result)}"
    assert result["command"].startswith("python benchmarks/")
    assert len(result["commit"]) == 40 and int(result["commit"], 16) >= 0


def test_results_written_without_a_header_get_one(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["benchmarks/example.py", "--quick"])
    write_json(tmp_path / "example.json", {"rows": [1, 2]})
    result = json.loads((tmp_path / "example.json").read_text())
    assert result["command"] == "python benchmarks/example.py --quick"
    assert result["rows"] == [1, 2] and HEADER <= set(result)
    write_json(tmp_path / "own.json", {"commit": "abc", "command": "mine"})
    assert json.loads((tmp_path / "own.json").read_text()) == {"commit": "abc", "command": "mine"}
