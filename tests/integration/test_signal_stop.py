"""A fit stopped by SIGINT or SIGTERM: exit code, MLflow status, checkpoint, resumed history."""

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning.pytorch as pl
import mlflow
import numpy as np
import pytest
import torch

from fgat.app.callbacks import SignalStop, StepCheckpoint
from fgat.app.callbacks.interrupt import STOP_SIGNALS
from fgat.app.callbacks.mlflow import continue_history, stamp_ms
from fgat.app.datamodules import PhantomDataModule
from fgat.app.modules import StaticModule
from tests.integration.test_static import MODEL, SIMULATION, config_file

REPOSITORY = Path(__file__).resolve().parents[2]
OPTICS = {"estimate": "zernike", "start": 4, "every": 4, "steps": 2, "identifiability": False}


def fit_command(tmp_path, *extra):
    return subprocess.Popen(
        [sys.executable, "-m", "fgat", "fit", "--config", "config.yaml", "--checkpoint_every=3"]
        + list(extra),
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(REPOSITORY), "MLFLOW_TRACKING_URI": ""},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def experiment_ids(client):
    return [e.experiment_id for e in client.search_experiments() if e.name == "tests"]


def histories(client, run_id):
    """Metric name -> [(step, value)] of a run, in logging order (NaN as None)."""
    run = client.get_run(run_id)
    return {
        key: [
            (m.step, None if math.isnan(m.value) else m.value)
            for m in sorted(client.get_metric_history(run_id, key), key=lambda m: m.timestamp)
        ]
        for key in run.data.metrics
    }


@pytest.mark.slow
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_a_fit_killed_with_a_checkpoint_and_resume_continues(tmp_path, number):
    config_file(tmp_path, steps=200, optics=OPTICS)
    process = fit_command(tmp_path)
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    while process.poll() is None and not any(  # stopped after the first optics event
        "psf/error" in run.data.metrics for run in client.search_runs(experiment_ids(client))
    ):
        time.sleep(0.2)
    process.send_signal(number)
    output, _ = process.communicate(timeout=300)
    assert process.returncode == 128 + number, output
    checkpoint = tmp_path / "run" / "checkpoints" / "last.ckpt"
    step = torch.load(checkpoint, map_location="cpu", weights_only=False)["global_step"]
    assert OPTICS["start"] < step < 200
    assert f"stopped by {signal.Signals(number).name} at step {step}: checkpoint" in output
    experiment = client.get_experiment_by_name("tests")
    (killed,) = client.search_runs([experiment.experiment_id])
    assert killed.info.status == "KILLED"
    record = json.loads((tmp_path / "run" / "fingerprint.json").read_text())
    assert record["status"] == "killed" and record["checkpoint"] == str(checkpoint)
    if number == signal.SIGINT:
        return
    resumed = fit_command(tmp_path, "--ckpt_path", "last", f"--trainer.max_steps={step + 4}")
    output, _ = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, output
    runs = client.search_runs([experiment.experiment_id], order_by=["attributes.start_time ASC"])
    assert [run.info.status for run in runs] == ["KILLED", "FINISHED"]
    before, after = histories(client, killed.info.run_id), histories(client, runs[1].info.run_id)
    for key, points in after.items():  # one value per step
        if key == "epoch":  # Lightning's own: logged with training and validation metrics alike
            continue
        steps = [s for s, _ in points]
        assert len(steps) == len(set(steps)), (key, points)
    for key, points in before.items():  # everything the stopped run logged, its last event too
        assert set(points) <= set(after[key]), key
    assert max(s for s, _ in before["psf/error"]) <= step < max(s for s, _ in after["psf/error"])
    assert after["residual/relative"][-1][0] == step + 4  # the finished run's report
    assert "rather than converged" in runs[1].data.tags["fgat.stopped"]


class FakeClient:
    """The part of MlflowClient that continue_history uses, in memory."""

    def __init__(self, points):
        self.points = points  # run -> [Metric]
        self.status, self.tags = {}, {}

    def get_run(self, run_id):
        metrics = {m.key: m.value for m in self.points[run_id]}
        info = type("Info", (), {"status": self.status.get(run_id, "RUNNING")})
        data = type("Data", (), {"metrics": metrics})
        return type("Run", (), {"info": info, "data": data})

    def set_terminated(self, run_id, status):
        self.status[run_id] = status

    def set_tag(self, run_id, key, value):
        self.tags[(run_id, key)] = value

    def get_metric_history(self, run_id, key):
        return [m for m in self.points[run_id] if m.key == key]

    def log_batch(self, run_id, metrics):
        self.points.setdefault(run_id, []).extend(metrics)


def test_continue_history_copies_what_was_logged_before_the_checkpoint():
    from mlflow.entities import Metric

    saved = 1_000
    logged = [
        Metric("zernike/c4", 0.0, 10, 0),
        Metric("loss/pix", 1.0, 500, 7),
        Metric("psf/error", 0.3, saved, 8),  # the event of the checkpoint's own step
        Metric("loss/pix", 0.9, saved + 1, 8),  # after the checkpoint: computed again
    ]
    client = FakeClient({"old": logged})
    assert continue_history(client, "old", "new", 8, saved_ms=saved) == 3
    assert client.points["new"] == logged[:3]
    assert client.status == {"old": "KILLED"}
    client = FakeClient({"old": logged})  # a checkpoint without its save time: by step
    assert continue_history(client, "old", "new", 8) == 2


def test_stamp_ms_separates_before_from_after():
    before = int(time.time() * 1000)
    stamp = stamp_ms()
    assert before <= stamp < int(time.time() * 1000)


class Signal(pl.Callback):
    """Send this process ``number`` during step ``step`` (before its optimizer step)."""

    def __init__(self, number, step):
        self.number, self.step = number, step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            signal.raise_signal(self.number)


@pytest.mark.slow
@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT])
def test_a_fit_stopped_by_a_signal_resumes_into_the_run_it_would_have_been(tmp_path, number):
    """Stopped by a signal during step 13 (with densification, JPGM events and an annealed
    Fourier term), a fit writes the checkpoint of step 14 and, resumed, ends bit-identical to
    the same fit run straight through (CPU)."""
    model = {
        **MODEL,
        "lambda_fourier": 0.1,
        "optics": {"estimate": "joint", "start": 8, "every": 8, "steps": 2},
    }
    simulation = {**SIMULATION, "zernike": {5: 0.1}, "intercepts": {1: [0.0, 0.5]}}

    def fit(root, *callbacks, ckpt_path=None):
        checkpoint = StepCheckpoint(
            dirpath=root / "ckpt", every_n_train_steps=1000, save_last=True, save_top_k=0
        )
        trainer = pl.Trainer(
            max_steps=30,
            default_root_dir=root,
            logger=False,
            enable_progress_bar=False,
            enable_model_summary=False,
            accelerator="cpu",
            val_check_interval=10,
            check_val_every_n_epoch=None,
            num_sanity_val_steps=0,
            callbacks=[checkpoint, SignalStop(), *callbacks],
        )
        pl.seed_everything(0)
        module = StaticModule(**model)
        trainer.fit(module, PhantomDataModule(simulation, psf="ideal"), ckpt_path=ckpt_path)
        return module, trainer

    handlers = {n: signal.getsignal(n) for n in STOP_SIGNALS}
    try:
        straight, _ = fit(tmp_path / "straight")
        with pytest.raises(SystemExit):  # Lightning ends a fit interrupted so
            fit(tmp_path / "resumed", Signal(number, 13))
    finally:
        for n, handler in handlers.items():
            signal.signal(n, handler)
    last = tmp_path / "resumed" / "ckpt" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == 14
    resumed, trainer = fit(tmp_path / "resumed", ckpt_path=last)
    assert trainer.global_step == 30 and resumed.engine.steps_done == 30
    for (name, expected), actual in zip(
        straight.engine.cloud.named_parameters(), resumed.engine.cloud.parameters()
    ):
        torch.testing.assert_close(actual, expected, rtol=0, atol=0, msg=name)
    for (name, expected), actual in zip(
        straight.engine.jpgm.named_parameters(), resumed.engine.jpgm.parameters()
    ):
        torch.testing.assert_close(actual, expected, rtol=0, atol=0, msg=name)
    np.testing.assert_equal(resumed.engine.evaluate(), straight.engine.evaluate())
