"""SIGINT (Ctrl-C) and SIGTERM stop the commands that run trials for good: ``fgat sweep``,
``fgat pipeline`` and the recipes exit with 128 + the signal's number within seconds, the
MLflow run under way KILLED, no trial run again or started after it."""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest
import yaml

from fgat.app.signals import Interrupted, StopSignals
from fgat.app.trials import Fanout, Trial, run_trials
from tests.integration.test_static import config_file

REPOSITORY = Path(__file__).resolve().parents[3]
STOPPED_WITHIN_S = 20.0  # the step under way, the checkpoint, MLflow and the exit: seconds


def start(command, cwd):
    return subprocess.Popen(
        command,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPOSITORY), "MLFLOW_TRACKING_URI": ""},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def runs_of(client, experiment):
    found = client.get_experiment_by_name(experiment)
    return [] if found is None else client.search_runs([found.experiment_id])


def stop_once_training(process, uri, experiment, number, timeout_s=600):
    """Send ``number`` once a run of ``experiment`` has logged a metric (its fit trains); the
    exit code, the seconds from the signal to the exit, the output and the runs."""
    client = mlflow.MlflowClient(uri)
    deadline = time.monotonic() + timeout_s
    while not any(run.data.metrics for run in runs_of(client, experiment)):
        assert process.poll() is None, process.communicate()[0]
        assert time.monotonic() < deadline, "no run started training"
        time.sleep(0.3)
    process.send_signal(number)
    sent = time.monotonic()
    try:
        output = process.communicate(timeout=120)[0]
    finally:
        process.kill()
    return process.returncode, time.monotonic() - sent, output, runs_of(client, experiment)


def assert_stopped_for_good(result, number):
    code, seconds, output, runs = result
    assert code == 128 + number, output
    assert seconds < STOPPED_WITHIN_S, (seconds, output)
    assert [run.info.status for run in runs] == ["KILLED"], output  # one trial, not retried
    assert "running it once more" not in output
    assert f"stopped by {signal.Signals(number).name}" in output


@pytest.mark.slow
def test_a_signal_stops_a_serial_sweep_for_good(tmp_path):
    config_file(tmp_path, steps=100_000)
    sweep = ["sweep", "--config", "config.yaml", "--grid", "seed=0:3", "--parallel", "1"]
    process = start([sys.executable, "-m", "fgat", *sweep], tmp_path)
    result = stop_once_training(process, f"sqlite:///{tmp_path}/mlflow.db", "tests", signal.SIGINT)
    assert_stopped_for_good(result, signal.SIGINT)
    assert "fgat sweep: stopped by SIGINT (trials stopped: seed0-" in result[2]


@pytest.mark.slow
def test_sigterm_stops_the_figS9_recipe_for_good(tmp_path):
    """``reproduce/figS9.sh`` (run from a copy of the recipes and configs) stopped by
    ``kill``: the signal reaches the recipe (the shell execs it), 143, its first trial KILLED,
    the second never started."""
    for folder in ("reproduce", "configs"):
        shutil.copytree(REPOSITORY / folder, tmp_path / folder)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    recipe = ["bash", "reproduce/figS9.sh", "--quick", "--seeds", "0", "1", "--levels", "0.05"]
    recipe += ["--tracking-uri", uri, "--trainer.max_steps=100000"]
    process = start(recipe, tmp_path)
    result = stop_once_training(process, uri, "figS9_quick", signal.SIGTERM)
    assert_stopped_for_good(result, signal.SIGTERM)
    assert "figS9: stopped by SIGTERM (trials stopped: rms0.05-seed0-" in result[2]


@pytest.mark.slow
def test_a_signal_stops_a_pipeline_for_good(tmp_path):
    config_file(tmp_path, steps=100_000)
    (tmp_path / "static.yaml").write_text(yaml.safe_dump({"checkpoint_every": 20}))
    pipeline = ["pipeline", "--config", "config.yaml", "--static", "static.yaml"]
    process = start([sys.executable, "-m", "fgat", *pipeline], tmp_path)
    result = stop_once_training(process, f"sqlite:///{tmp_path}/mlflow.db", "tests", signal.SIGINT)
    assert_stopped_for_good(result, signal.SIGINT)


@pytest.mark.parametrize("number", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.slow
def test_a_signal_outside_a_fits_own_handling_stops_the_trials(tmp_path, monkeypatch, number):
    """A signal while a trial sets up (before its fit's own handler takes over): Lightning
    makes the interrupt an exit with code 1 and ends the run FAILED; the trials stop all the
    same, that run is marked KILLED, an earlier trial's run is left as it was."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    client = mlflow.MlflowClient(uri)
    experiment = client.create_experiment("e")
    calls = []

    def main(words):
        calls.append(words[0])
        run = client.create_run(experiment).info.run_id
        if words[0] == "first":
            client.set_terminated(run, "FINISHED")
            return 0
        try:
            signal.raise_signal(number)
        except KeyboardInterrupt:
            client.set_terminated(run, "FAILED")
            raise SystemExit(1) from None
        return 0

    trials = [Trial(name, (name,), tmp_path / name, uri, "e") for name in ("first", "b", "c")]
    handlers = {n: signal.getsignal(n) for n in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(Interrupted) as stopped:
        run_trials(trials, Fanout(run_command=main))
    assert {n: signal.getsignal(n) for n in handlers} == handlers  # restored
    assert stopped.value.exit_code == 128 + number
    assert f"stopped by {signal.Signals(number).name} (trials stopped: b;" in str(stopped.value)
    assert calls == ["first", "b"]  # b neither run once more nor followed by c
    statuses = sorted(r.info.status for r in client.search_runs([experiment]))
    assert statuses == ["FINISHED", "KILLED"]


@pytest.mark.parametrize("code", [130, 143])
@pytest.mark.slow
def test_serial_trials_stop_when_a_fit_was_stopped_by_a_signal(tmp_path, monkeypatch, code):
    calls = []
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    trials = [Trial(name, ("fit",), tmp_path / name, uri, "e") for name in "ab"]
    with pytest.raises(Interrupted, match=r"\(trials stopped: a\)") as stopped:
        run_trials(trials, Fanout(run_command=lambda words: calls.append(words) or code))
    assert stopped.value.exit_code == code
    assert calls == [["fit"]]  # neither retried nor followed by the next trial


def test_stop_signals_turn_an_interrupt_into_interrupted_and_restore_the_handlers():
    before = {n: signal.getsignal(n) for n in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(Interrupted) as stopped, StopSignals() as stop:
        signal.raise_signal(signal.SIGTERM)
    assert stop.number == signal.SIGTERM and stopped.value.exit_code == 143
    assert {n: signal.getsignal(n) for n in before} == before
    with StopSignals() as stop:  # nothing received: nothing raised
        pass
    assert stop.number is None


def test_a_store_that_does_not_answer_leaves_the_stop_to_go_on(tmp_path, capsys):
    from fgat.app.tracking_server import free_port
    from fgat.app.trials import mark_killed

    trial = Trial("a", ("fit",), tmp_path, f"http://127.0.0.1:{free_port()}", "e")
    started = time.perf_counter()
    assert mark_killed(trial, 0, ("RUNNING",)) == []
    assert time.perf_counter() - started < 5  # no minutes of HTTP retries while stopping
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("a: its MLflow runs could not be marked KILLED (")


STEP = """import pathlib, signal, sys, time
folder = pathlib.Path(sys.argv[1])
def stop(number, frame):
    (folder / "stopped").write_text(signal.Signals(number).name)
    sys.exit(128 + number)
signal.signal(signal.SIGTERM, stop)
(folder / "started").write_text("1")
time.sleep(60)
"""


@pytest.mark.parametrize(("number", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_reaches_the_step_of_a_shell_recipe_under_way(tmp_path, number, code):
    """``reproduce/steps.sh``: the recipe ends with 128 + the signal, its step under way is
    stopped (SIGTERM, which a background step of a script does not ignore) and no next step
    starts."""
    (tmp_path / "step.py").write_text(STEP)
    script = tmp_path / "recipe.sh"
    script.write_text(
        "set -euo pipefail\n"
        f"source {REPOSITORY / 'reproduce' / 'steps.sh'}\n"
        f"step {sys.executable} {tmp_path / 'step.py'} {tmp_path}\n"
        f"step touch {tmp_path / 'next'}\n"
    )
    recipe = subprocess.Popen(["bash", str(script)])
    deadline = time.monotonic() + 30
    while not (tmp_path / "started").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    recipe.send_signal(number)
    assert recipe.wait(timeout=10) == code
    assert (tmp_path / "stopped").read_text() == "SIGTERM"
    assert not (tmp_path / "next").exists()
