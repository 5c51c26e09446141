"""Bad input to ``fit`` and ``deconvolve`` found before anything is computed: a truth of another
size, inputs larger than the memory, too many ``predict --times``, Gaussians that all left the
grid, a full disk at the checkpoint; and the library noise a clean run must not print."""

import errno
import os
import shutil
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
import yaml

import fgat._core.resources
import fgat.app.fingerprint
from fgat._core.resources import DiskFullError
from fgat.app.cli import main
from fgat.app.lightning_cli import PREDICT_TIME_BYTES, check_times_disk, predict_times, times_count
from fgat.io.checkpoints import content_bytes, save_torch_file
from fgat.io.images import read_tiff, write_tiff
from fgat.recon.guards import descend
from fgat.recon.outcome import FitFailed

BEADS = {"kind": "beads", "n_beads": 4, "sigma": 1.0, "min_spacing": 6, "margin": [1, 5, 5]}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A simulated measurement of 5 x 40 x 40 voxels (``params.yaml`` says view_size 40), its
    truth, and the same truth cut to 32 x 32 px."""
    folder = tmp_path_factory.mktemp("sim")
    config = folder / "sim.yaml"
    config.write_text(
        yaml.safe_dump(
            {"system": "small", "depths_um": "-6:6:5", "view_size": 40, "photons": None}
            | {"phantom": BEADS}
        )
    )
    assert main(["simulate", "--config", str(config), "--out", str(folder / "sim")]) == 0
    sim = folder / "sim"
    truth = read_tiff(sim / "truth.ome.tif")
    write_tiff(folder / "truth32.ome.tif", truth[:, 4:36, 4:36], axes="ZYX")
    return sim, folder / "truth32.ome.tif"


def flfm_config(folder: Path, sim: Path, **data) -> Path:
    config = {
        "seed_everything": 0,
        "mlflow": {"experiment": "tests", "tracking_uri": f"sqlite:///{folder}/mlflow.db"},
        "trainer": {"max_steps": 2, "default_root_dir": str(folder / "run")},
        "model": {"class_path": "fgat.modules.StaticModule", "init_args": {"n_gaussians": 50}},
        "data": {
            "class_path": "fgat.datamodules.FLFMDataModule",
            "init_args": {
                "measurement": str(sim / "sensor.ome.tif"),
                "centers": str(sim / "centers.csv"),
                "psf": str(sim / "psf.ome.tif"),
            }
            | data,
        },
    }
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.mark.slow
def test_a_truth_of_another_lateral_size_is_refused_by_fit_and_deconvolve(
    simulated, tmp_path, capsys, monkeypatch
):
    sim, small = simulated
    shb = fgat.recon.static.StaticReconstruction  # nothing may be reconstructed
    monkeypatch.setattr(shb, "__init__", lambda *a, **k: pytest.fail("the fit started"))
    config = flfm_config(tmp_path, sim, truth=str(small))
    assert main(["fit", "--config", str(config)]) == 2
    fit_line = capsys.readouterr().err.strip()
    assert fit_line.count("\n") == 0
    assert (
        f"data.truth {small}: shape (5, 32, 32) does not match the reconstruction (5, 40, 40)"
        in fit_line
    )
    assert f"view size 40 px from the simulation's {sim / 'params.yaml'}" in fit_line
    out = tmp_path / "volume.ome.tif"
    words = ["deconvolve", "--measurement", str(sim / "sensor.ome.tif")]
    words += ["--psf", str(sim / "psf.ome.tif"), "--centers", str(sim / "centers.csv")]
    assert main([*words, "--truth", str(small), "--out", str(out)]) == 2
    line = capsys.readouterr()
    assert not line.out  # refused before the cost estimate and any iteration
    assert (
        f"--truth {small}: shape (5, 32, 32) does not match the reconstruction (5, 40, 40)"
        in line.err
    )
    assert not out.exists()
    # the truth of this measurement is accepted; a view size set to the truth's lets a cut one in
    for truth, size, shape in ((sim / "truth.ome.tif", [], 40), (small, ["--view-size", "32"], 32)):
        out = tmp_path / f"volume{shape}.ome.tif"
        assert (
            main([*words, "--truth", str(truth), *size, "--iterations", "1", "--out", str(out)])
            == 0
        )
        assert read_tiff(out).shape == (5, shape, shape)


def test_inputs_larger_than_the_memory_are_refused_before_they_are_hashed(
    simulated, tmp_path, capsys, monkeypatch
):
    sim, _ = simulated
    hashed = []
    monkeypatch.setattr(fgat.app.fingerprint, "file_digest", lambda path, *a: hashed.append(path))
    shape, dtype = (256, 256), np.dtype(np.float32)  # the sensor image as written
    needed = int(np.prod(shape)) * (dtype.itemsize + 4)
    monkeypatch.setattr(fgat._core.resources, "available_memory", lambda device=None: needed - 1)
    config = flfm_config(tmp_path, sim)
    assert main(["fit", "--config", str(config)]) == 2
    line = capsys.readouterr().err.strip()
    assert line.count("\n") == 0 and not hashed
    assert f"data.measurement {sim / 'sensor.ome.tif'} (256, 256) float32 need about" in line
    assert "a shorter sequence, or a crop of the sensor" in line
    assert not (tmp_path / "run" / "fit.lock").exists()  # released on the way out


def test_predict_times_are_counted_before_they_are_built(monkeypatch):
    assert times_count("0:1:101") == 101 and times_count("0, 0.5,1") == 3
    assert times_count("0:1:1e8") is None
    monkeypatch.setattr(fgat._core.resources, "available_memory", lambda device=None: 10**9)
    assert len(predict_times("0:1:1000")) == 1000
    count = 10**9 // PREDICT_TIME_BYTES + 1  # one point more than the memory holds
    with pytest.raises(ValueError, match=rf"--times '0:1:{count}': {count} time points need"):
        predict_times(f"0:1:{count}")
    with pytest.raises(ValueError, match="expected normalised times"):
        predict_times("0:1:1e8")


def test_a_series_larger_than_the_free_disk_is_refused(tmp_path, monkeypatch):
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=4 * 5 * 8 * 8 * 9))
    out = tmp_path / "new" / "volumes.ome.tif"
    check_times_disk("0:1:9", 9, (5, 8, 8), out)  # exactly fits
    with pytest.raises(ValueError, match=r"10 volumes \(5, 8, 8\) .* need about 12.8 kB in"):
        check_times_disk("0:1:10", 10, (5, 8, 8), out)


def test_a_loss_that_depends_on_no_parameter_fails_the_fit_with_one_line():
    means = torch.nn.Parameter(torch.zeros(3, 3))
    optimizer = torch.optim.Adam([means])
    empty = {"total": torch.zeros(())}  # no Gaussian inside the grid: a constant volume
    with pytest.raises(FitFailed, match="the fit failed at step 7: no Gaussian is left inside"):
        descend(empty, [("means", means)], optimizer, "step 7", 7)
    assert isinstance(FitFailed("x"), ValueError)  # the CLI's one line and exit code 2
    terms = {"total": (means**2).sum() + 1.0}
    assert descend(terms, [("means", means)], optimizer, "step 8", 8) == {"total": 1.0}


def test_a_full_disk_leaves_no_partial_checkpoint(tmp_path, monkeypatch):
    content = {"state_dict": {"w": torch.zeros(1000)}, "step": 3}
    assert content_bytes(content) == 4000
    real_save = torch.save

    def full(obj, path, *args, **kwargs):
        Path(path).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    target = tmp_path / "last.ckpt"
    with pytest.raises(
        DiskFullError,
        match=rf"checkpoint: cannot write {target}: the disk is full.*needs about 4.0 kB",
    ):
        save_torch_file(content, target)
    assert os.listdir(tmp_path) == []
    monkeypatch.setattr(torch, "save", real_save)
    assert torch.load(save_torch_file(content, target))["step"] == 3


@pytest.mark.slow
def test_a_fit_whose_checkpoint_finds_the_disk_full_ends_failed(tmp_path, capsys, monkeypatch):
    from tests.integration.test_static import config_file

    config_file(tmp_path, steps=2, baseline_iterations=0)

    def full(obj, path, *args, **kwargs):
        Path(path).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    assert main(["fit", "--config", str(tmp_path / "config.yaml")]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    checkpoint = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert line.startswith(
        f"fgat fit: error: checkpoint: cannot write {checkpoint}: the disk is full"
    )
    assert "needs about" in line and "free there" in line
    assert os.listdir(checkpoint.parent) == []  # not even a temporary
    assert not (tmp_path / "run" / "fit.lock").exists()
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    (run,) = client.search_runs([client.get_experiment_by_name("tests").experiment_id])
    assert run.info.status == "FAILED"
    assert fgat.app.fingerprint.read_record(tmp_path / "run")["status"] == "failed"


@pytest.mark.slow
def test_a_fit_whose_gaussians_all_leave_the_grid_ends_with_one_line(tmp_path, capsys):
    from tests.integration.test_static import config_file

    config_file(tmp_path, steps=20, baseline_iterations=0, lr_means=500.0)  # one step throws
    assert main(["fit", "--config", str(tmp_path / "config.yaml")]) == 2  # them all out
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("fgat fit: error: the fit failed at step 1: no Gaussian is left inside")
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    (run,) = client.search_runs([client.get_experiment_by_name("tests").experiment_id])
    assert run.info.status == "FAILED"
