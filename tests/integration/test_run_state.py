"""The state a fit leaves in its folder: the folder's lock, a run killed by SIGKILL ended KILLED
when the folder is next used, ``--ckpt_path last`` without a checkpoint, and a checkpoint of
another configuration refused (an explicit file or ``last``, with or without its fingerprint)."""

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest
import torch

from fgat.app.cli import main
from fgat.app.fingerprint import LOCK, lock_folder, read_record, unlock_folder
from fgat.app.lightning_cli import FINGERPRINT_KEY
from tests.integration.test_static import config_file

REPOSITORY = Path(__file__).resolve().parents[2]
NOISE = (
    "Seed set to",
    "litlogger",
    "_pytree",
    "LeafSpec",
    "The dirpath has changed",
    "Couldn't infer the batch indices",
    "RuntimeWarning",
    "HINT",
)


def fit(folder: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fgat", "fit", "--config", "config.yaml", *extra],
        cwd=folder,
        env={**os.environ, "PYTHONPATH": str(REPOSITORY), "MLFLOW_TRACKING_URI": ""},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def dead_pid() -> int:
    """The PID of a process that has ended."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


@pytest.fixture(scope="module")
def story(tmp_path_factory):
    """A fit killed by SIGKILL before its first checkpoint, a second fit into its folder started
    while it ran, then ``--ckpt_path last`` in that folder: their outputs, the killed run's id."""
    folder = tmp_path_factory.mktemp("state")
    config_file(folder, steps=100_000, baseline_iterations=0)  # runs until it is killed
    client = mlflow.MlflowClient(f"sqlite:///{folder}/mlflow.db")
    killed = fit(folder, "--checkpoint_every=1000")
    record = None
    while killed.poll() is None and (record is None or record.get("status") != "running"):
        time.sleep(0.2)
        record = read_record(folder / "run")
    assert killed.poll() is None, killed.communicate()
    second = fit(folder)
    second_output = second.communicate(timeout=300)
    killed.send_signal(signal.SIGKILL)
    killed.wait(timeout=60)
    status_after_kill = client.get_run(record["run_id"]).info.status
    lock_after_kill = (folder / "run" / LOCK).is_file()
    resumed = fit(folder, "--ckpt_path", "last", "--trainer.max_steps=2")
    resumed_output = resumed.communicate(timeout=300)
    return {
        "folder": folder,
        "client": client,
        "pid": killed.pid,
        "run_id": record["run_id"],
        "second": (second.returncode, *second_output),
        "status_after_kill": status_after_kill,
        "lock_after_kill": lock_after_kill,
        "resumed": (resumed.returncode, *resumed_output),
    }


@pytest.mark.slow
def test_a_second_fit_into_a_held_folder_is_refused_naming_the_pid(story):
    code, out, err = story["second"]
    assert code == 2, err
    assert err.strip().splitlines() == [
        f"fgat fit: error: trainer.default_root_dir {story['folder'] / 'run'} is in use by "
        f"another fit (PID {story['pid']}, lock {story['folder'] / 'run' / LOCK}); wait for it "
        "to end, or choose another folder"
    ]
    assert not out


@pytest.mark.slow
def test_a_killed_fit_is_ended_killed_when_its_folder_is_used_again(story):
    assert story["status_after_kill"] == "RUNNING" and story["lock_after_kill"]
    code, out, err = story["resumed"]
    assert code == 0, err
    run, folder = story["run_id"], story["folder"] / "run"
    lines = err.splitlines()
    assert f"fgat: took over the lock {folder / LOCK} of PID {story['pid']}, which is no " in err
    assert (
        f"fgat: the fit of PID {story['pid']} in {folder} was killed before it ended; its MLflow "
        f"run {run} marked KILLED"
    ) in lines
    assert (
        f"fgat: --ckpt_path last: no checkpoint in {folder / 'checkpoints'}; starting from scratch"
        in lines
    )
    assert story["client"].get_run(run).info.status == "KILLED"
    assert not any(noise in err + out for noise in NOISE), err
    record = read_record(folder)
    assert record["status"] == "finished" and record["run_id"] != run
    assert story["client"].get_run(record["run_id"]).info.status == "FINISHED"
    assert not (folder / LOCK).exists()


@pytest.mark.slow
@pytest.mark.parametrize("stamped", [True, False])
def test_a_checkpoint_of_another_configuration_is_refused(story, tmp_path, capsys, stamped):
    last = story["folder"] / "run" / "checkpoints" / "last.ckpt"
    content = torch.load(last, weights_only=True)
    assert content[FINGERPRINT_KEY]["config"]["model"]["init_args"]["n_gaussians"] == 150
    if not stamped:  # e.g. saved by an older fgat: the module's arguments are compared
        del content[FINGERPRINT_KEY]
    other = tmp_path / "elsewhere" / "other.ckpt"
    other.parent.mkdir()
    torch.save(content, other)
    config_file(tmp_path, steps=4, baseline_iterations=0)
    words = ["fit", "--config", str(tmp_path / "config.yaml"), "--model.init_args.n_gaussians=200"]
    assert main([*words, "--ckpt_path", str(other)]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith(
        f"fgat fit: error: --ckpt_path {other}: it was saved by a run that had another "
        "configuration (model.init_args.n_gaussians 150 -> 200"
    )
    assert not (tmp_path / "run" / LOCK).exists()
    if not stamped:
        return
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    shutil.copy(other, tmp_path / "run" / "checkpoints" / "last.ckpt")
    assert main([*words, "--ckpt_path", "last"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith(
        f"fgat fit: error: --ckpt_path last ({tmp_path / 'run' / 'checkpoints' / 'last.ckpt'}): "
        "it was saved by a run that had another configuration (model.init_args.n_gaussians "
        "150 -> 200"
    )


def test_the_folder_lock_is_held_once_and_a_stale_one_is_taken_over(tmp_path):
    path, note = lock_folder(tmp_path / "run")
    assert note == "" and path.read_text().split() == [str(os.getpid()), socket.gethostname()]
    path.write_text(f"{os.getppid()} {socket.gethostname()}\n")  # a live process holds it
    with pytest.raises(ValueError, match=rf"is in use by another fit \(PID {os.getppid()}, lock"):
        lock_folder(tmp_path / "run")
    path.write_text("4242 elsewhere.example\n")  # another host: cannot tell, refused
    with pytest.raises(ValueError, match=r"\(PID 4242 on elsewhere.example, lock"):
        lock_folder(tmp_path / "run")
    gone = dead_pid()
    path.write_text(f"{gone} {socket.gethostname()}\n")
    again, note = lock_folder(tmp_path / "run")
    assert note == f"took over the lock {path} of PID {gone}, which is no longer running"
    unlock_folder(again)
    assert not again.exists()
    assert sorted(os.listdir(tmp_path / "run")) == []
