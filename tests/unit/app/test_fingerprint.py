"""Re-runs you can trust: fingerprints of resolved configs and inputs, stage folders, recipe
trials, MLflow store creation and resumed runs."""

import hashlib
import json
import multiprocessing
import re
from pathlib import Path

import mlflow
import numpy as np
import pytest
import yaml

from fgat.app.callbacks.mlflow import FINGERPRINT, RESUMED_BY, RESUMED_FROM, check_tracking_uri
from fgat.app.fingerprint import (
    differing_fields,
    file_digest,
    fingerprint,
    read_record,
    resume_checkpoint,
    run_folder,
    write_record,
)
from fgat.app.lightning_cli import resolved_config, run
from fgat.app.pipeline import run_pipeline
from fgat.app.trials import Trial
from fgat.io.images import read_tiff, write_tiff
from fgat.sim.simulation import SimulationConfig, simulate, write_simulation

CONFIG = {
    "seed_everything": 0,
    "mlflow": {"experiment": "a", "run_name": "x"},
    "checkpoint_every": 100,
    "trainer": {"max_steps": 10, "default_root_dir": "runs/a", "enable_progress_bar": True},
    "model": {"init_args": {"lr_means": 0.02, "densification": {"enabled": True}}},
}


def test_fingerprint_is_the_sha256_of_the_canonical_config():
    fp = fingerprint(CONFIG)
    canonical = {
        "model": {"init_args": {"densification": {"enabled": True}, "lr_means": 0.02}},
        "seed_everything": 0,
        "trainer": {"max_steps": 10},
    }  # names, logging and folders dropped
    expected = hashlib.sha256(
        json.dumps(canonical, sort_keys=True, separators=(",", ":")).encode()
    ).hexdigest()
    assert fp.digest == expected and fp.config == canonical and fp.short == expected[:8]


def test_fingerprint_follows_what_changes_the_result(tmp_path):
    base = fingerprint(CONFIG)
    cosmetic = {
        **CONFIG,
        "mlflow": {"experiment": "b"},
        "checkpoint_every": 5,
        "trainer": {
            **CONFIG["trainer"],
            "default_root_dir": "elsewhere",
            "enable_progress_bar": False,
        },
    }
    assert fingerprint(cosmetic) == base
    seeded = fingerprint({**CONFIG, "seed_everything": 1})
    nested = fingerprint(
        {**CONFIG, "model": {"init_args": {"lr_means": 0.02, "densification": {"enabled": False}}}}
    )
    assert len({base.digest, seeded.digest, nested.digest}) == 3
    assert differing_fields(base.config, seeded.config) == "seed_everything 0 -> 1"
    assert (
        differing_fields(base.config, nested.config)
        == "model.init_args.densification.enabled True -> False"
    )


def test_fingerprint_reads_input_files_by_content(tmp_path):
    first, moved = tmp_path / "a.tif", tmp_path / "b.tif"
    first.write_bytes(b"\x00" * 1000)
    moved.write_bytes(b"\x00" * 1000)
    with_file = lambda path: fingerprint({**CONFIG, "data": {"measurement": str(path)}})  # noqa: E731
    original = with_file(first)
    assert (
        original.config["data"]["measurement"]
        == "file:" + hashlib.blake2b(b"\x00" * 1000, digest_size=16).hexdigest()
    )
    assert with_file(moved) == original  # same bytes elsewhere: same experiment
    moved.write_bytes(b"\x00" * 999 + b"\x01")
    changed = with_file(moved)
    assert changed != original
    assert (
        differing_fields(original.config, changed.config)
        == "data.measurement (input contents differ)"
    )
    assert file_digest(moved, chunk=7) == file_digest(moved)  # chunking does not matter


def test_an_ome_tiff_written_again_keeps_its_fingerprint(tmp_path):
    """fgat's OME-TIFFs carry a UUID drawn from their contents: the same volume written twice is
    the same file (a stage reading it is not redone), a changed value is another file."""
    from fgat.io.images import read_tiff, write_tiff

    path = tmp_path / "sensor.ome.tif"
    volume = np.random.default_rng(0).random((2, 3, 8, 8)).astype(np.float32)
    with_file = lambda: fingerprint({**CONFIG, "data": {"measurement": str(path)}})  # noqa: E731
    write_tiff(path, volume, axes="TCYX", voxel_size_um=(1.0, 1.0))
    original = with_file()
    write_tiff(path, volume.copy(), axes="TCYX", voxel_size_um=(1.0, 1.0))
    assert with_file() == original
    write_tiff(path, volume, axes="TCYX", voxel_size_um=(1.0, 2.0))  # other metadata
    assert with_file() != original
    volume[1, 2, 3, 4] += 1e-3
    write_tiff(path, volume, axes="TCYX", voxel_size_um=(1.0, 1.0))
    assert with_file() != original
    np.testing.assert_array_equal(read_tiff(path), volume)


def test_run_folder_belongs_to_one_fingerprint(tmp_path):
    fp, other = fingerprint(CONFIG), fingerprint({**CONFIG, "seed_everything": 3})
    base = tmp_path / "static"
    assert run_folder(base, fp) == (base, None)  # free
    write_record(base, fp, status="finished")
    assert read_record(base)["status"] == "finished"
    assert run_folder(base, fp) == (base, None)  # its own
    folder, message = run_folder(base, other)
    assert folder == tmp_path / f"static-{other.short}"
    assert message == f"{base} holds a run of another configuration (seed_everything 0 -> 3)"
    legacy = tmp_path / "legacy"
    (legacy / "checkpoints").mkdir(parents=True)
    assert (
        run_folder(legacy, fp)[0] == tmp_path / f"legacy-{fp.short}"
    )  # files without a record are kept


@pytest.mark.parametrize(
    ("status", "trial_resumes"), [("killed", True), ("failed", True), ("finished", False)]
)
def test_a_trial_resumes_an_unfinished_run_and_fits_a_finished_one_afresh(
    tmp_path, status, trial_resumes
):
    """A trial that runs although its folder's run finished (``--refit``, or a tracking store
    without that run) starts afresh: resuming would run no step and log a run with no history.
    A pipeline stage still resumes a finished run (its results written again)."""
    fp = fingerprint(CONFIG)
    folder = tmp_path / "trial"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "last.ckpt").write_bytes(b"")
    write_record(folder, fp, status=status)
    checkpoint = folder / "checkpoints" / "last.ckpt"
    assert resume_checkpoint(folder, fp) == checkpoint
    trial = Trial("t", ("fit", "--config", "c.yaml"), folder, "sqlite:///m.db", "a", fp)
    resumed = ["--ckpt_path", str(checkpoint)]
    assert trial.command() == ["fit", "--config", "c.yaml", *(resumed if trial_resumes else [])]
    other = fingerprint({**CONFIG, "seed_everything": 3})
    assert resume_checkpoint(folder, other) is None  # another configuration's checkpoint


def test_resolved_config_is_what_the_cli_runs_with():
    config = resolved_config(
        [
            "fit",
            "--config",
            "configs/base/common.yaml",
            "--config",
            "configs/quickstart.yaml",
            "--model.init_args.lr_means=0.5",
        ]
    )
    assert config["model"]["init_args"]["lr_means"] == 0.5
    assert config["data"]["init_args"]["simulation"]["phantom"]["n_beads"] == 40
    quickstart = yaml.safe_load(Path("configs/quickstart.yaml").read_text())
    assert config["trainer"]["max_steps"] == quickstart["trainer.max_steps"]


def _create_store(uri, experiment, barrier, errors):
    barrier.wait()
    try:
        check_tracking_uri(uri, experiment)
    except Exception as error:  # noqa: BLE001 - reported to the parent
        errors.put(repr(error))


def test_store_created_once_when_runs_start_together(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    context = multiprocessing.get_context("fork")
    barrier, errors = context.Barrier(3), context.Queue()
    workers = [
        context.Process(target=_create_store, args=(uri, "race", barrier, errors)) for _ in range(3)
    ]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(120)
    assert [worker.exitcode for worker in workers] == [0, 0, 0]
    assert errors.empty()
    names = [e.name for e in mlflow.MlflowClient(uri).search_experiments()]
    assert names.count("race") == 1


def test_experiment_created_by_another_run_between_lookup_and_creation(tmp_path, monkeypatch):
    """A tracking server has no file lock: another run may create the experiment after this one
    looked it up. Its RESOURCE_ALREADY_EXISTS answer means the experiment is there."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    real = mlflow.MlflowClient(uri)
    existing = real.create_experiment("race")

    class LateClient(mlflow.MlflowClient):
        looked_up = 0

        def get_experiment_by_name(self, name):
            LateClient.looked_up += 1
            return None if LateClient.looked_up == 1 else super().get_experiment_by_name(name)

    monkeypatch.setattr(mlflow, "MlflowClient", LateClient)
    check_tracking_uri(uri, "race")
    assert LateClient.looked_up == 2
    assert [e.experiment_id for e in real.search_experiments() if e.name == "race"] == [existing]


@pytest.mark.parametrize(
    ("uri", "message"),
    [
        ("bogus://nowhere", "cannot open the tracking store"),
        ("sqlite:////no/such/folder/mlflow.db", "folder /no/such/folder does not exist"),
    ],
)
def test_unusable_tracking_store_fails_at_once(uri, message):
    with pytest.raises((ValueError, FileNotFoundError), match=re.escape(message)):
        check_tracking_uri(uri, "x")


# ---------------------------------------------------------------------------------------- real runs
PHANTOM = {
    "kind": "moving_beads",
    "n_beads": 4,
    "sigma": 1.0,
    "velocity": [0.0, 6.0, 0.0],
    "rotation_deg": 0.0,
    "min_spacing": 5.0,
    "margin": [2, 8, 5],
}
SIMULATION = dict(
    system="small", depths_um="-9:9:7", view_size=24, photons=None, frames=3, phantom=PHANTOM
)


@pytest.fixture
def measured(tmp_path, monkeypatch):
    """A simulated 3-frame acquisition on disk and the pipeline's two configs."""
    monkeypatch.chdir(tmp_path)
    write_simulation(simulate(SimulationConfig(**SIMULATION)), tmp_path / "sim")
    trainer = {
        "accelerator": "cpu",
        "default_root_dir": str(tmp_path / "run"),
        "enable_progress_bar": False,
        "enable_model_summary": False,
        "num_sanity_val_steps": 0,
        "log_every_n_steps": 1,
    }
    dynamic = {
        "seed_everything": 0,
        "mlflow": {"experiment": "p", "tracking_uri": f"sqlite:///{tmp_path}/mlflow.db"},
        "trainer": {**trainer, "max_epochs": 1, "check_val_every_n_epoch": 1},
        "model": {
            "class_path": "fgat.modules.DynamicModule",
            "init_args": {
                "static": "set-by-the-pipeline",
                "width": 16,
                "hexplane": {"channels": 4, "spatial_resolution": [4, 6, 6]},
            },
        },
        "data": {
            "class_path": "fgat.datamodules.FLFMDataModule",
            "init_args": {
                "measurement": str(tmp_path / "sim" / "sensor.ome.tif"),
                "centers": str(tmp_path / "sim" / "centers.csv"),
                "psf": str(tmp_path / "sim" / "psf.ome.tif"),
                "view_size": 24,
            },
        },
    }
    static = {
        "trainer": {
            "max_epochs": None,
            "max_steps": 4,
            "val_check_interval": 4,
            "check_val_every_n_epoch": None,
        },
        "model": {
            "class_path": "fgat.modules.StaticModule",
            "init_args": {
                "n_gaussians": 60,
                "init_iterations": 3,
                "baseline_iterations": 0,
                "densification": {"enabled": False},
            },
        },
    }
    (tmp_path / "dynamic.yaml").write_text(yaml.safe_dump(dynamic))
    (tmp_path / "static.yaml").write_text(yaml.safe_dump(static))
    return tmp_path


def _pipeline(root, *extra):
    return run_pipeline(
        str(root / "dynamic.yaml"), str(root / "static.yaml"), None, list(extra)
    ).volumes


@pytest.mark.slow
def test_pipeline_reruns_exactly_when_the_configuration_or_data_change(measured, capsys):
    first = read_tiff(_pipeline(measured), ndim=4)
    record = read_record(measured / "run" / "static")
    assert record["status"] == "finished"
    client = mlflow.MlflowClient(f"sqlite:///{measured}/mlflow.db")
    run_id = record["run_id"]
    assert client.get_run(run_id).data.tags[FINGERPRINT] == record["fingerprint"]
    capsys.readouterr()

    _pipeline(measured)  # identical: both stages skipped
    out = capsys.readouterr().out
    assert "static stage finished before" in out and "dynamic stage finished before" in out

    _pipeline(measured, "--seed_everything=1")  # a seed: both stages run again, beside the first
    out = capsys.readouterr().out
    assert "run/static holds a run of another configuration (seed_everything 0 -> 1)" in out
    assert "finished before" not in out
    assert (
        len(list((measured / "run").glob("static-*"))) == 1
        and len(list((measured / "run").glob("dynamic-*"))) == 1
    )

    _pipeline(measured, "--data.init_args.frame=0")  # an override: another reference frame
    assert "data.init_args.frame None -> 0" in capsys.readouterr().out

    sensor = read_tiff(measured / "sim" / "sensor.ome.tif")
    write_tiff(
        measured / "sim" / "sensor.ome.tif", sensor[::-1].copy(), axes="TYX"
    )  # the data changed
    changed = read_tiff(_pipeline(measured), ndim=4)
    out = capsys.readouterr().out
    assert (
        "data.init_args.measurement (input contents differ)" in out and "finished before" not in out
    )
    assert not np.allclose(changed, first)
    assert len(list((measured / "run").glob("static-*"))) == 3

    other = measured / "elsewhere"  # a root on the command line is honoured
    _pipeline(measured, f"--trainer.default_root_dir={other}")
    assert (
        read_record(other / "static")["status"] == "finished"
        and (other / "dynamic" / "fingerprint.json").is_file()
    )


@pytest.mark.slow
def test_resume_marks_the_killed_run_and_continues_its_history(measured, capsys):
    args = [
        "fit",
        "--config",
        str(measured / "dynamic.yaml"),
        "--config",
        str(measured / "static.yaml"),
        "--trainer.max_steps=6",
        "--checkpoint_every=3",
        "--trainer.val_check_interval=3",
        f"--trainer.default_root_dir={measured / 'fit'}",
    ]
    run(args)
    uri = f"sqlite:///{measured}/mlflow.db"
    client = mlflow.MlflowClient(uri)
    killed = read_record(measured / "fit")["run_id"]
    client.update_run(killed, status="RUNNING")  # as a killed process leaves it
    with pytest.raises(ValueError, match=r"had another configuration \(seed_everything 0 -> 2\)"):
        run([*args, "--seed_everything=2", "--ckpt_path=last"])
    run([*args, "--trainer.max_steps=12", "--ckpt_path=last"])
    resumed = read_record(measured / "fit")["run_id"]
    old, new = client.get_run(killed), client.get_run(resumed)
    assert old.info.status == "KILLED" and new.info.status == "FINISHED"
    assert new.data.tags[RESUMED_FROM] == killed and old.data.tags[RESUMED_BY] == resumed
    history = client.get_metric_history(resumed, "loss")
    steps = sorted(m.step for m in history)
    assert steps == sorted(set(steps))  # one point per step: no overlap
    before = {m.step: m.value for m in client.get_metric_history(killed, "loss") if m.step < 6}
    assert before and all(
        {m.step: m.value for m in history}[step] == value for step, value in before.items()
    )
    assert max(steps) > 6  # and the resumed steps after them
