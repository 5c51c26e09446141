"""One tracking server, many writers: four fits logging at once lose no metric and leave no run
RUNNING."""

import os
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import mlflow
import pytest

from fgat.app.tracking_server import free_port, local_server, server_command, wait_until_healthy

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def test_server_command_checks_its_folders(tmp_path):
    command = server_command(f"sqlite:///{tmp_path}/m.db", str(tmp_path / "art"), port=5123)
    assert command[1:4] == ["-m", "mlflow", "server"]
    assert command[command.index("--host") + 1] == "127.0.0.1"
    assert command[command.index("--artifacts-destination") + 1] == str(tmp_path / "art")
    assert command[command.index("--workers") + 1] == "1"  # one writer for a SQLite file
    postgres = server_command("postgresql://db/runs", str(tmp_path / "art"))
    assert "--workers" not in postgres  # MLflow's default
    assert server_command("postgresql://db/runs", "art", workers=3)[-2:] == ["--workers", "3"]
    with pytest.raises(ValueError, match="--workers must be at least 1, got 0"):
        server_command(f"sqlite:///{tmp_path}/m.db", str(tmp_path / "art"), workers=0)
    with pytest.raises(
        FileNotFoundError, match="--backend-store-uri sqlite:.*: folder .* does not exist"
    ):
        server_command(f"sqlite:///{tmp_path}/missing/m.db", str(tmp_path / "art"))
    with pytest.raises(ValueError, match="--port must be a TCP port"):
        server_command(f"sqlite:///{tmp_path}/m.db", str(tmp_path / "art"), port=0)


@pytest.mark.slow
def test_local_server_serves_a_sqlite_store_for_the_block_only(tmp_path):
    uri = f"sqlite:///{tmp_path}/m.db"
    with local_server(uri) as server:
        client = mlflow.MlflowClient(server)
        created = client.create_experiment("served")
        with urllib.request.urlopen(f"{server}/health", timeout=5) as reply:
            assert reply.status == 200
    assert mlflow.MlflowClient(uri).get_experiment_by_name("served").experiment_id == created
    with pytest.raises(OSError):
        urllib.request.urlopen(f"{server}/health", timeout=5)  # stopped with the block
    with pytest.raises(
        FileNotFoundError, match="--backend-store-uri sqlite:.*: folder .* does not exist"
    ):
        with local_server(f"sqlite:///{tmp_path}/missing/m.db"):
            pass


@pytest.mark.slow
def test_four_concurrent_fits_log_everything_to_one_server(tmp_path):
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fgat",
            "tracking-server",
            "--port",
            str(port),
            "--backend-store-uri",
            f"sqlite:///{tmp_path}/runs.db",
            "--artifacts-destination",
            str(tmp_path / "artifacts"),
        ],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        wait_until_healthy(uri, server)
        fits = [
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "fgat",
                    "fit",
                    "--config",
                    str(CONFIGS / "base" / "common.yaml"),
                    "--config",
                    str(CONFIGS / "quickstart.yaml"),
                    "--trainer.max_steps=30",
                    "--trainer.val_check_interval=30",
                    "--trainer.log_every_n_steps=10",
                    "--trainer.enable_progress_bar=false",
                    "--trainer.callbacks=[]",
                    "--model.init_args.n_gaussians=100",
                    f"--seed_everything={seed}",
                    f"--trainer.default_root_dir=run{seed}",
                    f"--mlflow.tracking_uri={uri}",
                    "--mlflow.experiment=concurrent",
                ],
                cwd=tmp_path,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                env={**os.environ, "MLFLOW_TRACKING_URI": "", "OMP_NUM_THREADS": "1"},
            )  # one thread each, as README advises for runs sharing a machine's cores
            for seed in range(4)
        ]
        outputs = [fit.communicate(timeout=600)[0] for fit in fits]
        assert [fit.returncode for fit in fits] == [0] * 4, outputs
        client = mlflow.MlflowClient(uri)
        experiment = client.get_experiment_by_name("concurrent")
        runs = client.search_runs([experiment.experiment_id])
        assert len(runs) == 4 and {run.info.status for run in runs} == {"FINISHED"}
        for run in runs:
            steps = [m.step for m in client.get_metric_history(run.info.run_id, "loss")]
            assert steps == [9, 19, 29], steps  # every logging step of 30
            assert len(client.get_metric_history(run.info.run_id, "val/psnr_volume")) == 1
            artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
            assert {"config.yaml", "volume.ome.tif", "mips.png"} <= artifacts
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=60)
