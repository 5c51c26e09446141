"""Hostile inputs over every command (the table of ``benchmarks/hostile.py``): corrupt, empty,
huge, NaN, wrong-unit and wrong-type inputs, faults of the tracking server and of the tracking
URI. Each case must end as its table says:

* ``refuse``: a non-zero exit code, no traceback, one error line (the last) naming the case's
  option, file or field, within :data:`BOUND_S` (in-process) or :data:`ISOLATED_BOUND_S` (a
  subprocess, start-up included), and nothing left in the case's folder;
* ``warn``: exit 0 with a warning naming the option (or such a refusal);
* ``result``: exit 0 and the right number printed (a width in um, a view count).

Cases run in-process through :func:`fgat.app.cli.main` where they can; those that start servers,
could hang or allocate without bound before the checks exist run as ``python -m fgat``
subprocesses with a timeout (``Case.isolate``). ``python benchmarks/hostile.py`` runs the whole
table as subprocesses and records exit code, time and line per case.
"""

import time
from pathlib import Path

import pytest

from fgat.app.cli import main
from fgat.app.recipes import hostile

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

BOUND_S = 10.0  # generous for a slow, shared machine: the benchmark records the real times
ISOLATED_BOUND_S = 25.0  # a subprocess: Python, torch and Lightning imports included
ISOLATED_TIMEOUT_S = 40.0

CASES = [case for case in hostile.CASES if case.section != hostile.REFERENCE]

SLOW_IN_PROCESS = {"fit_ckpt_other_configuration"}
"""Cases that take more than a few seconds in-process (a fit to a checkpoint first)."""


def case_param(case):
    """The case as a parameter, marked slow when it runs as a ``python -m fgat`` subprocess or
    is one of :data:`SLOW_IN_PROCESS`."""
    slow = case.isolate or case.id in SLOW_IN_PROCESS
    return pytest.param(case, id=case.id, marks=pytest.mark.slow if slow else ())


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """The inputs the cases share (a simulation, a real checkpoint, ...), made once; the
    modules the commands import loaded first, so that a case's time is its own."""
    import mlflow  # noqa: F401

    import fgat.app.lightning_cli  # noqa: F401  (Lightning, jsonargparse)

    return tmp_path_factory.mktemp("hostile_shared")


def run_in_process(case, folder, shared, tracking, capsys, monkeypatch):
    """``fgat.app.cli.main`` on the case in ``folder``: its :class:`hostile.Outcome` and values."""
    values, made = hostile.prepare(case, folder, shared, CONFIGS)
    monkeypatch.chdir(folder)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tracking / 'mlflow.db'}")
    monkeypatch.delenv("FGAT_TRACEBACK", raising=False)
    for name, value in case.env:
        monkeypatch.setenv(name, hostile.fill(value, values))
    capsys.readouterr()
    start = time.perf_counter()
    try:
        code = main(hostile.argv_of(case, values))
    except SystemExit as stop:  # argparse's refusals
        code = stop.code if isinstance(stop.code, int) else 1
    wall = time.perf_counter() - start
    keep = values.pop("_keep", None)
    if keep is not None:
        keep.close()
    captured = capsys.readouterr()
    litter = hostile.left_behind(folder, made)
    return hostile.Outcome(code, wall, captured.out, captured.err, litter), values


@pytest.mark.parametrize("case", [case_param(case) for case in CASES])
def test_hostile_case(case, shared, tmp_path, capsys, monkeypatch):
    folder, tracking = tmp_path / "case", tmp_path / "tracking"
    tracking.mkdir()
    if case.isolate:
        outcome, values = hostile.run_subprocess(
            case, folder, shared, CONFIGS, tracking, ISOLATED_TIMEOUT_S
        )
        bound = ISOLATED_BOUND_S
    else:
        outcome, values = run_in_process(case, folder, shared, tracking, capsys, monkeypatch)
        bound = BOUND_S
    failures = hostile.judge(case, outcome, values, None, bound)
    assert not failures, (
        f"fgat {' '.join(hostile.argv_of(case, values))}: {'; '.join(failures)}\n"
        f"exit {outcome.exit}, {outcome.wall_s:.1f} s\nstderr tail:\n{outcome.stderr[-2000:]}"
    )


def test_the_judge_refuses_what_the_suite_must_not_pass():
    """The expectations fail on a silent exit 0, a traceback, two error lines, a line without
    the option, a slow refusal, litter and a wrong number; they pass a clean refusal."""
    refuse = hostile.Case("x", ("deconvolve",), "refuse", ("--iterations",))
    line = "fgat deconvolve: error: --iterations 1e9: more than 1e6; pass --max-iterations"
    clean = hostile.Outcome(2, 0.5, "", f"usage: fgat deconvolve\n{line}\n", [])
    assert hostile.judge(refuse, clean, {}, None, 10) == []
    assert hostile.judge(refuse, clean, {}, 2.5, 10) == ["2.5 s before refusing (bound 2 s)"]
    bad = {
        "exit 0": hostile.Outcome(0, 0.5, "done", "", []),
        "traceback": hostile.Outcome(2, 0.5, "", f"Traceback (most recent call last):\n{line}", []),
        "2 error lines": hostile.Outcome(2, 0.5, "", f"ValueError: x\n{line}", []),
        "does not name": hostile.Outcome(2, 0.5, "", "fgat deconvolve: error: too many", []),
        "before refusing": hostile.Outcome(2, 11.0, "", line, []),
        "left": hostile.Outcome(2, 0.5, "", line, ["out"]),
        "timeout": hostile.Outcome(None, 60.0, "", "", []),
    }
    for reason, outcome in bad.items():
        failures = hostile.judge(refuse, outcome, {}, None, 10)
        assert any(reason in failure for failure in failures), (reason, failures)
    result = hostile.Case("y", ("analyze",), "result", result=(r"width ([0-9.]+) um", 0.47, 0.05))
    assert hostile.judge(result, hostile.Outcome(0, 1, "width 0.48 um", "", []), {}, None, 10) == []
    assert hostile.judge(result, hostile.Outcome(0, 1, "width 480 um", "", []), {}, None, 10)
    warn = hostile.Case("z", ("calibrate",), "warn", ("--dark",))
    assert hostile.judge(warn, hostile.Outcome(0, 1, "", "", []), {}, None, 10)
    warned = hostile.Outcome(0, 1, "", "warning: --dark d.tif is brighter than the image", [])
    assert hostile.judge(warn, warned, {}, None, 10) == []


def test_every_command_has_cases():
    commands = {case.argv[0] if case.argv[0] != "analyze" else case.argv[1] for case in CASES}
    expected = {"design", "psf", "simulate", "calibrate", "calibrate-depth", "deconvolve"}
    expected |= {"crossinfo", "fwhm", "cytometry", "track", "pipeline", "sweep"}
    expected |= {"tracking-server", "fit", "validate", "test", "predict"}
    assert expected <= commands, expected - commands
