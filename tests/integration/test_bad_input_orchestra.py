"""``fgat sweep``, ``pipeline`` and ``tracking-server`` refuse bad input with one line (exit
code 2) before anything long starts: fan-out options, grids too large to list, a tracking store
that cannot be used, an address or port the server cannot listen on."""

import socket
import time
from pathlib import Path

import pytest

import fgat.app.lightning_cli  # noqa: F401 - imported here, not in the timed refusals
from fgat.app.cli import main
from fgat.app.sweep import Progress, grid_points
from fgat.app.tracking_server import free_port
from fgat.app.trials import Outcome
from tests.integration.test_bad_input_pipeline import configs  # noqa: F401 - the pipeline's configs fixture

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
QUICKSTART = ["--config", str(CONFIGS / "base" / "common.yaml")]
QUICKSTART += ["--config", str(CONFIGS / "quickstart.yaml")]


def refused(words, capsys, within_s=2.0):
    """The one line ``python -m fgat <words>`` ends with (exit code 2, within ``within_s``)."""
    started = time.perf_counter()
    code = main(words)
    seconds = time.perf_counter() - started
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert seconds < within_s, (seconds, err)
    return err


@pytest.mark.parametrize(
    ("option", "value", "expected"),
    [
        ("--cpus-per-trial", "nan", "--cpus-per-trial must be a finite number > 0, got 'nan'"),
        ("--cpus-per-trial", "inf", "--cpus-per-trial must be a finite number > 0, got 'inf'"),
        ("--cpus-per-trial", "0", "--cpus-per-trial must be a finite number > 0, got '0'"),
        ("--cpus-per-trial", "-1", "--cpus-per-trial must be a finite number > 0, got '-1'"),
        ("--gpus-per-trial", "nan", "--gpus-per-trial must be a finite number >= 0, got 'nan'"),
        ("--parallel", "1.5", "--parallel '1.5': expected a whole number >= 1 or auto"),
    ],
)
@pytest.mark.parametrize("command", ["sweep", "pipeline"])
def test_bad_fanout_is_refused_at_once(command, option, value, expected, capsys):
    words = [command, *QUICKSTART, "--grid", "seed=0:2"]
    if command == "pipeline":
        words = [command, *QUICKSTART, "--static", "static.yaml"]
    assert expected in refused([*words, option, value], capsys)


def test_a_grid_is_counted_before_it_is_listed(capsys):
    started = time.perf_counter()
    with pytest.raises(ValueError) as error:
        grid_points(["seed=0:100000000"])
    assert time.perf_counter() - started < 0.1  # counted, not listed (a list took 45 s)
    assert str(error.value) == (
        "--grid: 100000000 trials (100000000) is more than --max-trials 1000; give "
        "--max-trials 100000000 to run them all"
    )
    with pytest.raises(ValueError, match=r"6 trials \(2 x 3\) is more than --max-trials 5"):
        grid_points(["a=1,2", "seed=0:3"], max_trials=5)
    points = grid_points(["a=1,2", "seed=10:13"], max_trials=6)
    assert points == [{"a": a, "seed": s} for a in "12" for s in ("10", "11", "12")]
    err = refused(["sweep", *QUICKSTART, "--grid", "seed=0:100000000"], capsys)
    assert "give --max-trials 100000000 to run them all" in err
    err = refused(["sweep", *QUICKSTART, "--grid", "seed=0:3", "--max-trials", "0"], capsys)
    assert "--max-trials must be an integer >= 1, got '0'" in err


def test_many_grid_points_are_announced_with_their_progress(capsys, monkeypatch):
    Progress(19).step()
    assert capsys.readouterr().out == ""  # a few points: nothing to say
    monkeypatch.setattr(Progress, "every_s", 0.0)
    progress = Progress(10_000)
    for _ in range(3):
        progress.step()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == (
        "fgat sweep: resolving and checking the configurations of 10000 grid points before any "
        "trial starts"
    )
    assert [line.split(" (")[0] for line in lines[1:]] == [
        "fgat sweep: resolved 1 of 10000 grid points",
        "fgat sweep: resolved 2 of 10000 grid points",
    ]
    assert lines[2].endswith(" s left)")


def test_an_unusable_tracking_store_is_refused_before_any_trial(tmp_path, capsys):
    """One check (:func:`fgat.app.callbacks.mlflow.check_tracking_uri`) for every command that
    logs: an unreachable server answers at once (it took 254 s and 113 lines when every grid
    point retried it), a database that is a folder too."""
    unreachable = f"http://127.0.0.1:{free_port()}"
    sweep = ["sweep", *QUICKSTART, "--grid", "seed=0:50", "--parallel", "1"]
    err = refused([*sweep, f"--mlflow.tracking_uri={unreachable}"], capsys, within_s=10)
    assert err.startswith(
        f"fgat sweep: error: --mlflow.tracking_uri {unreachable}: cannot open the tracking store"
    )
    folder = f"sqlite:///{tmp_path}"
    err = refused([*sweep, f"--mlflow.tracking_uri={folder}"], capsys, within_s=10)
    assert err.endswith(
        f"--mlflow.tracking_uri {folder}: {tmp_path} is a folder; expected a database file"
    )
    fit = ["fit", *QUICKSTART, f"--mlflow.tracking_uri={folder}", "--trainer.max_steps=1"]
    fit += [f"--trainer.default_root_dir={tmp_path / 'run'}"]
    err = refused(fit, capsys, within_s=30)  # the same check: the fit builds its model first
    assert err.endswith(f"{tmp_path} is a folder; expected a database file")


def pipeline_words(*extra):
    return ["pipeline", "--config", "dynamic.yaml", "--static", "static.yaml", *extra]


def test_pipeline_refuses_bad_channels_and_stores(configs, capsys, monkeypatch):  # noqa: F811
    ran = []
    monkeypatch.setattr("fgat.app.lightning_cli.run", ran.append)  # no stage may start
    err = refused(pipeline_words("--channels", "0,a"), capsys)
    assert err.endswith("--channels '0,a': expected all or channel numbers in 0..0, e.g. 0,2")
    unreachable = f"http://127.0.0.1:{free_port()}"
    err = refused(pipeline_words(f"--mlflow.tracking_uri={unreachable}"), capsys, within_s=10)
    assert f"--mlflow.tracking_uri {unreachable}: cannot open the tracking store" in err
    assert ran == []


def test_pipeline_runs_on_the_ray_cluster_it_is_given(configs, monkeypatch):  # noqa: F811
    """``--address`` is honoured: the pipeline runs as a trial there (then this process finds
    its stages finished), as ``sweep --address`` runs its trials (which log over HTTP)."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://head:5000")
    monkeypatch.setattr("fgat.app.pipeline.checked_store", lambda uri, experiment: None)
    given = []

    def run_trials(trials, fanout, label):
        given.append((trials, fanout))
        return [Outcome(trial, 0, 1, 0.0) for trial in trials]

    monkeypatch.setattr("fgat.app.pipeline.run_trials", run_trials)
    monkeypatch.setattr("fgat.app.pipeline._run_stages", lambda *args: "merged")
    assert main(pipeline_words("--address", "ray://head:10001")) == 0
    ((trials, fanout),) = given
    assert fanout.address == "ray://head:10001"
    (trial,) = trials
    assert trial.words[:5] == ("pipeline", "--config", "dynamic.yaml", "--static", "static.yaml")
    assert "--address" not in trial.words  # the trial itself runs where Ray put it


@pytest.fixture
def no_exec(monkeypatch):
    """A server that would start fails the test instead of replacing the test process."""

    def execv(*args):
        raise AssertionError(f"the server started: {args}")

    monkeypatch.setattr("os.execv", execv)


def test_tracking_server_refuses_what_it_cannot_serve(tmp_path, capsys, no_exec):
    database = f"sqlite:///{tmp_path}/m.db"
    server = ["tracking-server", "--backend-store-uri", database]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        err = refused([*server, "--port", str(port)], capsys)
    assert err.endswith(
        f"--host 127.0.0.1 --port {port}: cannot listen there (Address already in use)"
    )
    err = refused([*server, "--host", "192.0.2.1"], capsys)  # TEST-NET-1: not this machine's
    assert "--host 192.0.2.1 --port 5000: cannot listen there" in err
    err = refused([*server, "--host", "no.such.host.invalid"], capsys)
    assert "--host no.such.host.invalid: not an address to listen on" in err
    (tmp_path / "file").write_text("")
    err = refused([*server, "--artifacts-destination", str(tmp_path / "file")], capsys)
    file = tmp_path / "file"
    assert err.endswith(
        f"--artifacts-destination {file}: a file; expected a folder (created if missing)"
    )
    err = refused(["tracking-server", "--backend-store-uri", f"sqlite:///{tmp_path}"], capsys)
    assert err.endswith(f"sqlite:///{tmp_path}: {tmp_path} is a folder; expected a database file")


@pytest.mark.slow
def test_a_recipe_refuses_an_unusable_tracking_store_with_one_line(tmp_path):
    """The same check before a recipe's first trial: one line, exit code 2, no trial run."""
    import os
    import subprocess
    import sys

    repository = CONFIGS.parent
    unreachable = f"http://127.0.0.1:{free_port()}"
    recipe = [sys.executable, str(repository / "reproduce" / "figS9.py"), "--quick"]
    recipe += ["--seeds", "0", "--levels", "0.05", "--tracking-uri", unreachable]
    done = subprocess.run(
        recipe,
        cwd=repository,
        env={**os.environ, "PYTHONPATH": str(repository), "MLFLOW_TRACKING_URI": ""},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 2, done.stderr
    (line,) = [line for line in done.stderr.splitlines() if line.startswith("figS9:")]
    assert line.startswith(
        f"figS9: error: --mlflow.tracking_uri {unreachable}: cannot open the tracking store ("
    )
    assert "Traceback" not in done.stderr and "figS9_quick [1/1]" not in done.stdout
