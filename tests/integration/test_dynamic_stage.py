"""The dynamic stage end to end: sequences, DynamicModule, predict, pipeline over channels."""

import dataclasses
import logging
import math
import re

import lightning.pytorch as pl
import mlflow
import numpy as np
import pytest
import torch
import yaml

from fgat.app.callbacks import ReconstructionArtifacts
from fgat.app.callbacks.artifacts import seconds_per_unit_time, time_rows, times_interval_s
from fgat.app.datamodules import FLFMDataModule, PhantomDataModule
from fgat.app.datamodules.scene import SceneDataModule
from fgat.app.lightning_cli import run
from fgat.app.modules import DynamicModule, StaticModule
from fgat.app.pipeline import run_pipeline
from fgat.app.trials import Fanout
from fgat.dynamics import HexPlane
from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.dynamics.regularizers import plane_l1_to_one, plane_tv, temporal_smoothness
from fgat.io.images import (
    read_series,
    read_tiff,
    read_time_interval,
    read_voxel_size,
    volume_metadata,
    write_tiff,
)
from fgat.recon import DynamicReconstruction, DynamicSettings, load_static, phantom_scene
from fgat.recon.losses import dynamic_loss, pixel_loss
from fgat.recon.metrics import compare_volumes
from fgat.recon.names import PSNR, PSNR_REGISTERED, REGISTRATION_SHIFT, STILL
from fgat.sim.phantoms import moving_beads
from fgat.sim.simulation import SimulationConfig, frame_times, simulate, write_simulation

PHANTOM = {
    "kind": "moving_beads",
    "n_beads": 5,
    "sigma": 1.0,
    "velocity": [0.0, 6.0, 0.0],
    "rotation_deg": 0.0,
    "min_spacing": 5.0,
    "margin": [2, 9, 5],
}
SIMULATION = dict(
    system="small", depths_um="-9:9:7", view_size=32, photons=None, frames=5, phantom=PHANTOM
)
STATIC = dict(
    n_gaussians=200,
    init_iterations=10,
    baseline_iterations=0,
    lr_means=0.05,
    lr_intensities=0.05,
    densification={"enabled": False},
)
HEXPLANE = {"channels": 8, "spatial_resolution": [4, 8, 8]}
DYNAMIC = dict(hexplane=HEXPLANE, width=32, lr_planes=2e-2, lr_mlp=2e-3)
TRUE_GAINS = np.array([1.0, 0.9, 0.8, 0.7, 0.75, 0.85, 0.95])  # the 7 views, outer ones dimmer


def trainer(root, **options):
    return pl.Trainer(
        default_root_dir=root,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
        num_sanity_val_steps=0,
        enable_checkpointing=False,
        **options,
    )


@pytest.fixture(scope="module")
def static_checkpoint(tmp_path_factory):
    """A static stage fitted to the reference (middle) frame of a moving-bead sequence."""
    root = tmp_path_factory.mktemp("static")
    pl.seed_everything(0)
    fit = trainer(root, max_steps=150, limit_val_batches=0)
    fit.fit(StaticModule(**STATIC), PhantomDataModule(SIMULATION))
    path = root / "last.ckpt"
    fit.save_checkpoint(path)
    return path


class GivenScene(SceneDataModule):
    """A datamodule that serves a scene built beforehand."""

    def __init__(self, scene):
        super().__init__()
        self.given = scene

    def make_scene(self):
        return self.given


@pytest.fixture(scope="module")
def gained_static(tmp_path_factory):
    """The moving-bead sequence seen through views of gains ``TRUE_GAINS``, its scene calibrated
    with other gains (their square roots), and a short static fit with ``estimate_gains``: its
    checkpoint, results folder and final effective gains."""
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    frames = scene.frames * TRUE_GAINS[:, None, None]
    frames = (frames / frames[scene.reference].max()).astype(np.float32)
    scene = dataclasses.replace(
        scene, frames=frames, measurement=frames[scene.reference], gains=np.sqrt(TRUE_GAINS)
    )
    root = tmp_path_factory.mktemp("gained")
    pl.seed_everything(0)
    module = StaticModule(
        **{**STATIC, "n_gaussians": 30, "init": "random"}, estimate_gains=True, lr_gains=0.05
    )
    fit = trainer(root, max_steps=5, limit_val_batches=0, callbacks=[ReconstructionArtifacts()])
    fit.fit(module, GivenScene(scene))
    fit.save_checkpoint(root / "last.ckpt")
    with torch.no_grad():
        gains = module.engine.gains().clone()
    return root / "last.ckpt", root / "results" / "latest", gains, scene


def test_dynamic_stage_uses_the_static_stages_estimated_gains(tmp_path, gained_static, caplog):
    """The static run's final effective gains, from its checkpoint or its results folder, are the
    dynamic forward model's (and its checkpoint's); a run without them keeps the scene's."""
    checkpoint, results, gains, scene = gained_static
    calibrated = torch.tensor(scene.gains, dtype=torch.float32)
    assert not torch.allclose(gains, calibrated, atol=1e-3)  # the static fit moved them
    for source in (checkpoint, results):
        module = DynamicModule(str(source), **DYNAMIC)
        caplog.clear()
        with caplog.at_level(logging.INFO):
            trainer(tmp_path, max_steps=1, limit_val_batches=0).fit(module, GivenScene(scene))
        torch.testing.assert_close(module.engine.operator.gains, gains)
        assert (
            "uses the static stage's estimated per-view gains "
            f"(min {float(gains.min()):.4g}, max {float(gains.max()):.4g})" in caplog.text
        )
    state = module.engine.state_dict()
    resumed = DynamicReconstruction.from_state_dict(scene, state, module.settings)
    torch.testing.assert_close(resumed.operator.gains, gains)  # the dynamic checkpoint's own
    del state["gains"]  # a dynamic checkpoint from before the gains were carried over
    old = DynamicReconstruction.from_state_dict(scene, state, module.settings)
    torch.testing.assert_close(old.operator.gains, calibrated)
    content = torch.load(checkpoint, map_location="cpu", weights_only=True)
    del content["reconstruction"]["gains"]  # a static checkpoint from before
    torch.save(content, tmp_path / "old.ckpt")
    static = load_static(tmp_path / "old.ckpt")
    assert static.gains is None
    engine = DynamicReconstruction.from_static(
        scene, *static, HexPlaneSettings(**HEXPLANE), DynamicSettings(width=32)
    )
    torch.testing.assert_close(engine.operator.gains, calibrated)
    with pytest.raises(ValueError, match=r"estimated gains of shape \(3,\), the data has 7 views"):
        DynamicReconstruction.from_static(scene, static.cloud, static.psf, gains[:3])


def test_sequence_phantom_matches_the_phantom_function():
    result = simulate(SimulationConfig(**SIMULATION))
    shape = (7, 32, 32)
    expected = moving_beads(
        shape, frame_times(5), **{k: v for k, v in PHANTOM.items() if k != "kind"}, seed=0
    )
    np.testing.assert_array_equal(result.truth, expected)
    assert result.views.shape == (5, 7, 32, 32) and result.sensor.shape[0] == 5
    np.testing.assert_allclose(result.times, [0, 0.25, 0.5, 0.75, 1])
    scene = PhantomDataModule(SIMULATION).make_scene()
    assert scene.reference == 2 and scene.n_frames == 5
    np.testing.assert_array_equal(scene.measurement, scene.frames[2])
    assert scene.measurement.max() == 1.0  # normalised by the reference frame
    np.testing.assert_array_equal(scene.truth, scene.truth_frames[2])
    between = scene.truth_at([0.5, 0.625])  # any times: normalised over the frames asked for
    np.testing.assert_allclose(
        between[0] / between[0].max(), expected[2] / expected[2].max(), atol=1e-6
    )
    with pytest.raises(ValueError, match="frames = 3 needs a dynamic phantom.kind"):
        SimulationConfig(
            **{**SIMULATION, "frames": 3, "phantom": {"kind": "beads", "n_beads": 3}}
        ).validate()
    with pytest.raises(ValueError, match="reference frame 9 is outside the 5 frames"):
        PhantomDataModule(SIMULATION, reference_frame=9)


def test_flfm_datamodule_reads_sequences_and_channels(tmp_path):
    result = simulate(SimulationConfig(**SIMULATION))
    write_simulation(result, tmp_path / "sim")
    sensor = read_tiff(tmp_path / "sim" / "sensor.ome.tif")
    assert sensor.shape[0] == 5
    options = dict(
        centers=str(tmp_path / "sim" / "centers.csv"),
        psf=str(tmp_path / "sim" / "psf.ome.tif"),
        view_size=32,
    )
    scene = FLFMDataModule(str(tmp_path / "sim" / "sensor.ome.tif"), **options).make_scene()
    assert scene.frames.shape == (5, 7, 32, 32) and scene.reference == 2
    np.testing.assert_allclose(scene.times, [0, 0.25, 0.5, 0.75, 1])
    np.testing.assert_allclose(scene.frames * scene.scale, result.views, rtol=1e-6, atol=1e-3)
    with_truth = FLFMDataModule(
        str(tmp_path / "sim" / "sensor.ome.tif"),
        truth=str(tmp_path / "sim" / "truth.ome.tif"),
        **options,
    ).make_scene()
    np.testing.assert_array_equal(with_truth.truth_frames, result.truth)
    np.testing.assert_array_equal(with_truth.truth, result.truth[2])
    two = np.stack([sensor, 2 * sensor], axis=1)  # (T, C, H, W)
    write_tiff(tmp_path / "two.ome.tif", two, axes="TCYX")
    with pytest.raises(ValueError, match="has 2 channels .* choose one with data.channel"):
        FLFMDataModule(str(tmp_path / "two.ome.tif"), **options).make_scene()
    second = FLFMDataModule(str(tmp_path / "two.ome.tif"), channel=1, **options).make_scene()
    np.testing.assert_allclose(
        second.frames, scene.frames, rtol=1e-6
    )  # same shape, twice the scale
    assert second.scale == pytest.approx(2 * scene.scale)


def test_dynamic_loss_terms_against_hand_computed_values():
    hexplane = HexPlane(channels=2, spatial_resolution=(3, 4, 5), temporal_resolution=4, levels=2)
    with torch.no_grad():
        for plane in hexplane.planes:
            plane.add_(
                torch.randn(plane.shape, generator=torch.Generator().manual_seed(plane.numel()))
            )
    prediction, target = torch.rand(3, 16, 16), torch.rand(3, 16, 16)
    terms = dynamic_loss(prediction, target, hexplane, lambda_tv=0.1, lambda_sm=0.2, lambda_l1=0.3)
    spatiotemporal = hexplane.spatiotemporal_planes()
    expected = (
        pixel_loss(prediction, target)
        + 0.1 * plane_tv(list(hexplane.planes))
        + 0.2 * temporal_smoothness(spatiotemporal)
        + 0.3 * plane_l1_to_one(spatiotemporal)
    )
    torch.testing.assert_close(terms["total"], expected)
    ssim_terms = dynamic_loss(
        prediction, target, hexplane, lambda_ssim=1.0, lambda_tv=0, lambda_sm=0, lambda_l1=0
    )
    torch.testing.assert_close(
        ssim_terms["total"], (ssim_terms["pix"] + ssim_terms["ssim"]) / 2
    )  # 1 / (1 + lambda_S)
    assert set(ssim_terms) == {"total", "pix", "ssim", "img"}


class Record(pl.Callback):
    def on_train_end(self, trainer, pl_module):
        engine, scene = pl_module.engine, pl_module.scene
        self.frames = [
            compare_volumes(volume, truth)["psnr"]
            for volume, truth in zip(engine.volumes(), scene.truth_frames)
        ]
        self.static = [s["psnr"] for s in engine.still_scores]
        with torch.no_grad():
            self.reference = engine.gaussians_at(float(scene.times[scene.reference]))


def test_short_dynamic_fit_beats_no_deformation(tmp_path, static_checkpoint):
    record = Record()
    pl.seed_everything(0)
    module = DynamicModule(str(static_checkpoint), **DYNAMIC)
    trainer(tmp_path, max_epochs=40, check_val_every_n_epoch=20, callbacks=[record]).fit(
        module, PhantomDataModule(SIMULATION)
    )
    for reference, key in zip(record.reference, ("means", "scales", "quats", "intensities")):
        torch.testing.assert_close(
            reference, module.engine.g0[key], rtol=0, atol=1e-6
        )  # G_{t_ref} = G_0
    assert record.frames[2] == pytest.approx(record.static[2], abs=1e-6)
    moved = [0, 1, 3, 4]
    gains = [record.frames[k] - record.static[k] for k in moved]
    assert min(gains) > 1.0 and np.mean(gains) > 3.0, (record.frames, record.static)  # dB
    assert not any(value.requires_grad for value in module.engine.g0.values())  # G_0 frozen
    assert math.isfinite(module.trainer.callback_metrics["val/psnr_volume"])


def test_single_frame_skips_the_dynamic_stage(tmp_path, static_checkpoint, caplog):
    single = {**SIMULATION, "frames": 1}
    module = DynamicModule(str(static_checkpoint), **DYNAMIC)
    with caplog.at_level(logging.INFO):
        fit = trainer(tmp_path, max_epochs=5, callbacks=[ReconstructionArtifacts()])
        fit.fit(module, PhantomDataModule(single))
    assert "single frame: dynamic stage skipped" in caplog.text
    assert fit.global_step == 0
    (result,) = (tmp_path / "results").glob("*/volumes.ome.tif")  # G0 is the result
    np.testing.assert_allclose(
        read_series(result)[0],
        module(0.0).detach().numpy() * module.scene.scale,
        rtol=1e-5,
        atol=1e-5,
    )


@pytest.mark.parametrize("tiff_bytes", [1 << 30, pytest.param(1, marks=pytest.mark.slow)])
def test_dynamic_results_streamed_as_tiff_or_zarr_hold_every_frame(
    tmp_path, static_checkpoint, monkeypatch, tiff_bytes
):
    """A small series is one OME-TIFF, a larger one (here: any) an OME-Zarr written frame by
    frame; both hold the volumes at the frames' times, and the per-frame scores are those of
    the whole series against the truth."""
    monkeypatch.setattr("fgat.app.callbacks.artifacts.SERIES_TIFF_BYTES", tiff_bytes)
    module = DynamicModule(str(static_checkpoint), **DYNAMIC)
    trainer(tmp_path, max_epochs=2, callbacks=[ReconstructionArtifacts()]).fit(
        module, PhantomDataModule(SIMULATION, frame_interval_s=0.25)
    )
    (folder,) = (tmp_path / "results").iterdir()
    name = "volumes.ome.tif" if tiff_bytes > 1 else "volumes.ome.zarr"
    assert sorted(p.name for p in folder.glob("volumes.*")) == [name]
    engine, scene = module.engine, module.scene
    expected = engine.volumes() * scene.scale
    written = read_series(folder / name)
    assert written.shape == expected.shape == (5, 7, 32, 32)
    np.testing.assert_allclose(written, expected, rtol=1e-5, atol=1e-4)
    assert volume_metadata(folder / name)["depths_um"] == list(scene.optics.depths_um)
    assert read_voxel_size(folder / name)["Z"] == pytest.approx(scene.voxel_size_um[0])
    assert read_time_interval(folder / name) == 0.25  # data.frame_interval_s
    rows = np.loadtxt(folder / "frames.csv", delimiter=",", skiprows=1)
    psnr = [compare_volumes(v, t)["psnr"] for v, t in zip(expected, scene.truth_frames)]
    np.testing.assert_allclose(rows[:, 2], psnr, rtol=1e-4)
    assert (folder / "mips_time.png").stat().st_size > 10_000


def test_frame_interval_gives_rendered_series_their_seconds():
    scene = phantom_scene(SimulationConfig(**SIMULATION))  # five frames
    assert seconds_per_unit_time(scene) is None and times_interval_s([0, 0.5, 1], scene) is None
    scene.frame_interval_s = 0.5  # four intervals: 2 s from the first frame to the last
    assert seconds_per_unit_time(scene) == 2.0
    assert times_interval_s(np.linspace(0, 1, 9), scene) == pytest.approx(0.25)
    assert times_interval_s([0.0, 0.1, 0.5], scene) is None  # uneven: no single step
    assert times_interval_s([0.3], scene) is None
    scene.truth_at = None  # no scores against the truth: only the times
    rows = time_rows([{"index": 0, "time": 0.0}, {"index": 1, "time": 0.75}], scene)
    assert rows == [[0, 0.0, 0.0], [1, 0.75, 1.5]]  # index, time, time_s
    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="data.frame_interval_s"):
            PhantomDataModule(SIMULATION, frame_interval_s=bad)


def test_static_checkpoint_must_match_the_data(tmp_path, static_checkpoint):
    other = {**SIMULATION, "depths_um": "-9:9:9"}
    with pytest.raises(
        ValueError,
        match=r"Gaussians are on a \(7, 32, 32\) grid, but the data's volume is "
        r"\(9, 32, 32\)",
    ):
        trainer(tmp_path, max_epochs=1).fit(
            DynamicModule(str(static_checkpoint), **DYNAMIC), PhantomDataModule(other)
        )
    with pytest.raises(FileNotFoundError, match="model.static: .*nowhere.ckpt does not exist"):
        trainer(tmp_path, max_epochs=1).fit(
            DynamicModule(str(tmp_path / "nowhere.ckpt")), PhantomDataModule(other)
        )
    with pytest.raises(ValueError, match="unknown field"):
        DynamicModule("x.ckpt", hexplane={"chanels": 4})


def cli_config(tmp_path, static, **data):
    config = {
        "seed_everything": 0,
        "mlflow": {"experiment": "dynamic", "tracking_uri": f"sqlite:///{tmp_path}/mlflow.db"},
        "trainer": {
            "max_epochs": 3,
            "default_root_dir": str(tmp_path / "run"),
            "accelerator": "cpu",
            "log_every_n_steps": 5,
            "check_val_every_n_epoch": 3,
            "num_sanity_val_steps": 0,
            "enable_progress_bar": False,
            "enable_model_summary": False,
        },
        "model": {
            "class_path": "fgat.modules.DynamicModule",
            "init_args": {"static": str(static), **DYNAMIC},
        },
        "data": {
            "class_path": "fgat.datamodules.PhantomDataModule",
            "init_args": {"simulation": SIMULATION, **data},
        },
    }
    path = tmp_path / "dynamic.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.mark.slow
def test_cli_fit_logs_and_predict_renders_any_time(tmp_path, static_checkpoint, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = cli_config(tmp_path, static_checkpoint)
    run(["fit", "--config", str(config)])
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    (experiment,) = [e for e in client.search_experiments() if e.name == "dynamic"]
    (info,) = client.search_runs([experiment.experiment_id])
    assert info.info.run_name.startswith("fit-dynamic-")
    for name in (
        "loss/img",
        "loss/tv",
        "loss/sm",
        "loss/l1",
        "time/frame_step_ms",
        "val/loss_pix",
        "val/psnr_volume",
        "val/ssim_mip_xy",
        "val/psnr_volume_no_deformation",
        "frame/psnr_volume",
    ):  # 7 planes: no 3D SSIM
        assert math.isfinite(info.data.metrics[name]), name
    assert (
        len(client.get_metric_history(info.info.run_id, "frame/psnr_volume")) == 5
    )  # one per frame
    artifacts = {a.path for a in client.list_artifacts(info.info.run_id)}
    assert {
        "volumes.ome.tif",
        "mips_time.png",
        "frames.csv",
        "psnr_frames.png",
        "config.yaml",
    } <= artifacts
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    out = tmp_path / "dense.ome.tif"
    run(
        [
            "predict",
            "--config",
            str(config),
            "--ckpt_path",
            str(ckpt),
            "--times",
            "0:1:9",
            "--out",
            str(out),
        ]
    )
    dense = read_tiff(out, ndim=4)
    assert dense.shape == (9, 7, 32, 32)
    module = DynamicModule.load_from_checkpoint(ckpt, weights_only=False)
    fit = trainer(tmp_path)
    fit.predict(
        module, PhantomDataModule(SIMULATION), return_predictions=False
    )  # setup for a direct query
    for index, t in ((0, 0.0), (3, 0.375), (8, 1.0)):
        with torch.no_grad():
            expected = module(t).numpy() * module.scene.scale
        np.testing.assert_allclose(dense[index], expected, rtol=1e-5, atol=1e-4 * expected.max())
    times = np.loadtxt(tmp_path / "dense_times.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(times[:, 1], np.linspace(0, 1, 9))
    truth = module.scene.truth_at(np.linspace(0, 1, 9))  # the phantom between frames
    assert times[4, 2] == pytest.approx(compare_volumes(dense[4], truth[4])["psnr"], abs=1e-3)
    store = tmp_path / "dense.ome.zarr"  # streamed volume by volume
    arguments = ["--config", str(config), "--ckpt_path", str(ckpt), "--times", "0:1:9"]
    run(["predict", *arguments, "--out", str(store)])
    np.testing.assert_array_equal(read_series(store), dense)
    assert read_voxel_size(store) == read_voxel_size(out)
    assert volume_metadata(store) == volume_metadata(out)
    np.testing.assert_allclose(
        np.loadtxt(tmp_path / "dense_times.csv", delimiter=",", skiprows=1), times, rtol=1e-6
    )  # scores against the truth at each time alone, not at all nine at once
    with pytest.raises(ValueError, match="dense.ome.zarr: the store exists; choose another name"):
        run(["predict", *arguments, "--out", str(store)])
    with pytest.raises(ValueError, match="expected normalised times in"):
        run(["predict", "--config", str(config), "--ckpt_path", str(ckpt), "--times", "0:2:5"])
    with pytest.raises(ValueError, match="belong to 'predict'"):
        run(["fit", "--config", str(config), "--times", "0:1:5"])


def two_channel_configs(tmp_path) -> tuple[str, str]:
    """The dynamic and static configs of a pipeline over a (T, C, H, W) sequence of two
    channels (the second the first's frames in reverse order), tiny stages."""
    result = simulate(SimulationConfig(**{**SIMULATION, "frames": 3}))
    write_simulation(result, tmp_path / "sim")
    sensor = read_tiff(tmp_path / "sim" / "sensor.ome.tif")
    write_tiff(tmp_path / "two.ome.tif", np.stack([sensor, sensor[::-1]], axis=1), axes="TCYX")
    config = yaml.safe_load(cli_config(tmp_path, "set-by-the-pipeline").read_text())
    config["trainer"]["max_epochs"] = 2
    config["data"] = {
        "class_path": "fgat.datamodules.FLFMDataModule",
        "init_args": {
            "measurement": str(tmp_path / "two.ome.tif"),
            "centers": str(tmp_path / "sim" / "centers.csv"),
            "psf": str(tmp_path / "sim" / "psf.ome.tif"),
            "view_size": 32,
        },
    }
    (tmp_path / "dynamic.yaml").write_text(yaml.safe_dump(config))
    static = {
        "trainer": {
            "max_epochs": None,
            "max_steps": 10,
            "val_check_interval": 10,
            "check_val_every_n_epoch": None,
        },
        "model": {"class_path": "fgat.modules.StaticModule", "init_args": STATIC},
    }
    (tmp_path / "static.yaml").write_text(yaml.safe_dump(static))
    return str(tmp_path / "dynamic.yaml"), str(tmp_path / "static.yaml")


@pytest.mark.slow
def test_pipeline_runs_both_stages_per_channel_and_merges(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    two_channel_configs(tmp_path)
    with pytest.raises(ValueError, match="the data has 2 channels: pass --channels all"):
        run_pipeline(str(tmp_path / "dynamic.yaml"), str(tmp_path / "static.yaml"))
    result = run_pipeline(str(tmp_path / "dynamic.yaml"), str(tmp_path / "static.yaml"), "all")
    assert result.volumes == tmp_path / "run" / "volumes.ome.zarr"
    volumes = read_series(result.volumes, ndim=5)
    assert result.stages == [
        (tmp_path / "run" / f"ch{c}" / "static", tmp_path / "run" / f"ch{c}" / "dynamic")
        for c in (0, 1)
    ]
    assert volumes.shape == (3, 2, 7, 32, 32)  # (T, C, Z, Y, X)
    for channel in (0, 1):
        single = next(
            (tmp_path / "run" / f"ch{channel}" / "dynamic" / "results").glob("*/volumes.ome.tif")
        )
        np.testing.assert_array_equal(volumes[:, channel], read_tiff(single))
    recorded = volume_metadata(result.volumes)  # the channels' depth axis and planes
    assert recorded == volume_metadata(single) and recorded["depth_axis"] == "up"
    assert len(recorded["depths_um"]) == 7
    assert not np.allclose(
        volumes[:, 0], volumes[:, 1]
    )  # the channels differ (time-reversed frames)
    stamp = (tmp_path / "run" / "ch0" / "static" / "fingerprint.json").stat().st_mtime
    run_pipeline(
        str(tmp_path / "dynamic.yaml"), str(tmp_path / "static.yaml"), "0,1"
    )  # finished stages skipped
    assert (tmp_path / "run" / "ch0" / "static" / "fingerprint.json").stat().st_mtime == stamp
    assert "static stage (channel 0) finished before" in capsys.readouterr().out
    record = tmp_path / "run" / "ch1" / "dynamic" / "fingerprint.json"
    record.write_text(
        record.read_text().replace('"finished"', '"running"')
    )  # as if killed after its last checkpoint
    run_pipeline(str(tmp_path / "dynamic.yaml"), str(tmp_path / "static.yaml"), "1")
    resumed = (
        r"dynamic stage \(channel 1\) -> \S+/ch1/dynamic "
        r"\(resuming from \S+/ch1/dynamic/checkpoints/last.ckpt\)"
    )
    assert re.search(resumed, capsys.readouterr().out)


@pytest.mark.slow
def test_pipeline_channels_run_at_once_on_ray(tmp_path, monkeypatch, capsys):
    """``--parallel 2``: each channel's stages run as one Ray trial (its own process and log),
    then the merge finds every stage finished and writes each channel's series."""
    pytest.importorskip("ray")
    monkeypatch.chdir(tmp_path)
    dynamic, static = two_channel_configs(tmp_path)
    result = run_pipeline(dynamic, static, "all", fanout=Fanout(parallel=2))
    out = capsys.readouterr().out
    assert "fgat pipeline: 2 of 2 trials finished" in out
    assert out.count("finished before with this configuration") == 4  # the merge's pass
    volumes = read_series(result.volumes, ndim=5)
    assert volumes.shape == (3, 2, 7, 32, 32)
    for channel, (static_folder, dynamic_folder) in enumerate(result.stages):
        log = (tmp_path / "run" / f"ch{channel}" / "trial.log").read_text()
        assert f"--channels {channel}" in log and f"dynamic stage (channel {channel}) ->" in log
        assert static_folder == tmp_path / "run" / f"ch{channel}" / "static"
        single = next((dynamic_folder / "results").glob("*/volumes.ome.tif"))
        np.testing.assert_array_equal(volumes[:, channel], read_tiff(single))
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    runs = client.search_runs([client.get_experiment_by_name("dynamic").experiment_id])
    assert sorted(run.info.run_name for run in runs) == [
        "dynamic-ch0",
        "dynamic-ch1",
        "static-ch0",
        "static-ch1",
    ]
    assert {run.info.status for run in runs} == {"FINISHED"}


def test_non_finite_frame_names_step_frame_and_term(static_checkpoint):
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    engine = DynamicReconstruction.from_static(
        scene,
        *load_static(static_checkpoint),
        HexPlaneSettings(**HEXPLANE),
        DynamicSettings(width=32),
    )
    engine.frames = np.full_like(engine.frames, np.nan)
    with pytest.raises(FloatingPointError, match=r"step 0 \(frame \d\): loss term 'total' is nan"):
        engine.step()


def test_dynamic_scores_register_the_scene_once_for_every_frame(static_checkpoint):
    """With every truth frame displaced by whole voxels, G_0 registered to the reference frame
    gives the displacement, and the frames' registered PSNR (and G_0 left still's) is what the
    same reconstruction scores against the undisplaced truth, up to the voxels moved out."""
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    displacement = (0, -2, 1)
    moved = np.zeros_like(scene.truth_frames)
    moved[:, :, :-2, 1:] = scene.truth_frames[:, :, 2:, :-1]  # moved[i] = truth[i - d]
    engines = [
        DynamicReconstruction.from_static(
            given, *load_static(static_checkpoint), HexPlaneSettings(**HEXPLANE), DynamicSettings()
        )
        for given in (scene, dataclasses.replace(scene, truth_frames=moved))
    ]
    for engine in engines:
        torch.manual_seed(0)
        for _ in range(5):
            engine.step()
    plain, displaced = (engine.evaluate() for engine in engines)
    assert engines[1].scene_shift == pytest.approx(displacement, abs=0.1)
    assert [displaced[name] for name in REGISTRATION_SHIFT] == list(engines[1].scene_shift)
    for suffix in ("", STILL):
        assert displaced[PSNR + suffix] < plain[PSNR + suffix] - 3
        assert displaced[PSNR_REGISTERED + suffix] == pytest.approx(plain[PSNR + suffix], abs=0.05)
    assert engines[0].scene_shift == pytest.approx((0, 0, 0), abs=0.1)


def test_frame_order_is_a_shuffled_dataloaders(static_checkpoint):
    """Every pass visits every frame once, in the order a shuffled DataLoader over the frames
    draws from the same global random stream."""
    from torch.utils.data import RandomSampler

    scene = phantom_scene(SimulationConfig(**SIMULATION))
    engine = DynamicReconstruction.from_static(
        scene,
        *load_static(static_checkpoint),
        HexPlaneSettings(**HEXPLANE),
        DynamicSettings(width=32),
    )
    visited, take = [], engine.next_frame

    def recorded():
        visited.append(take())
        return visited[-1]

    engine.next_frame = recorded
    torch.manual_seed(5)
    for _ in range(15):
        engine.step()
    torch.manual_seed(5)
    expected = [index for _ in range(3) for index in RandomSampler(range(5))]
    assert visited == expected
    assert all(sorted(visited[k : k + 5]) == [0, 1, 2, 3, 4] for k in (0, 5, 10))


def test_dynamic_state_dict_resumes_exactly(static_checkpoint):
    """Killed mid-pass and resumed from its state (and the same global random stream), the
    field ends bit-identical to an uninterrupted run."""
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    static = load_static(static_checkpoint)

    def engine():
        torch.manual_seed(0)  # the MLP's initialisation and the frame orders
        return DynamicReconstruction.from_static(
            scene, *static, HexPlaneSettings(**HEXPLANE), DynamicSettings(width=32)
        )

    straight = engine()
    for _ in range(8):
        straight.step()
    first = engine()
    for _ in range(3):
        first.step()
    state, stream = first.state_dict(), torch.get_rng_state()
    torch.manual_seed(123)  # a fresh process: another MLP initialisation, overwritten by the state
    resumed = DynamicReconstruction.from_state_dict(scene, state, DynamicSettings(width=32))
    torch.set_rng_state(stream)
    for _ in range(5):
        resumed.step()
    for (name, expected), actual in zip(
        straight.field.state_dict().items(), resumed.field.state_dict().values()
    ):
        torch.testing.assert_close(actual, expected, rtol=0, atol=0, msg=name)
    np.testing.assert_equal(
        resumed.evaluate(), straight.evaluate()
    )  # bit-identical (NaN: no 3D SSIM on 7 planes)


def test_static_run_loads_from_its_checkpoint_or_its_files(tmp_path, static_checkpoint):
    state = torch.load(static_checkpoint, map_location="cpu", weights_only=False)["reconstruction"]
    cloud, psf, gains = load_static(static_checkpoint)
    torch.testing.assert_close(cloud.means, state["cloud"]["means"], rtol=0, atol=0)
    torch.testing.assert_close(psf, state["psf"], rtol=0, atol=0)
    assert gains is None  # fitted without estimate_gains: the datamodule's gains are used
    cloud.save(tmp_path / "gaussians.pt")
    assert load_static(tmp_path).psf is None  # no psf.ome.tif: the datamodule's PSF is used
    assert load_static(tmp_path).gains is None  # no gains.yaml: the datamodule's gains
    write_tiff(tmp_path / "psf.ome.tif", 2 * state["psf"].numpy(), axes="CZYX")
    from_files, stack, _ = load_static(tmp_path / "gaussians.pt")
    for name in ("means", "scales", "quaternions", "intensities"):
        torch.testing.assert_close(getattr(from_files, name), getattr(cloud, name), rtol=0, atol=0)
    torch.testing.assert_close(stack, 2 * state["psf"])
    (tmp_path / "gains.yaml").write_text("gains: [1.0, -0.5]")
    with pytest.raises(ValueError, match="gains.yaml must hold 'gains: \\[...\\]', one finite"):
        load_static(tmp_path)
    with pytest.raises(ValueError, match="is not a static-stage checkpoint"):
        torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
        load_static(tmp_path / "other.ckpt")


def test_sequence_camera_has_one_photon_scale_for_all_frames():
    clean = simulate(SimulationConfig(**SIMULATION)).sensor  # photons None: noise-free counts
    noisy = simulate(SimulationConfig(**{**SIMULATION, "photons": 1e6})).sensor
    expected = clean.sum(axis=(1, 2), dtype=np.float64) * 1e6 / clean.max()
    np.testing.assert_allclose(noisy.sum(axis=(1, 2), dtype=np.float64), expected, rtol=2e-3)
    peak = np.unravel_index(
        np.argmax(clean), clean.shape
    )  # the sequence's brightest pixel: ~1e6 counts
    assert noisy[peak] == pytest.approx(1e6, abs=5 * 1e3)  # five Poisson sigmas


def test_converged_frames_are_skipped_until_a_revisit(static_checkpoint):
    """With frame_tolerance, a pass visits the frames whose last visit changed their image loss
    by at least the tolerance times what they lost since their first visit (every frame on
    every revisit-th pass), recomputed here from the losses the steps report; the stage
    converges at the first step after which every frame's ratio is below it (the reference
    frame, anchored to G_0, has a constant loss), and the state carries it across a resume."""
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    tolerance, revisit = 0.05, 3
    settings = DynamicSettings(width=32, frame_tolerance=tolerance, revisit=revisit)
    torch.manual_seed(0)
    engine = DynamicReconstruction.from_static(
        scene, *load_static(static_checkpoint), HexPlaneSettings(**HEXPLANE), settings
    )
    visits, passes = [], []
    take = engine.next_frame

    def recorded():
        index = take()
        visits.append(index)
        passes.append(engine.passes)
        return index

    engine.next_frame = recorded
    first, losses, changes, expected_passes, converged_at = {}, {}, {}, {}, None
    for step in range(1, 151):
        result = engine.step()
        frame, current_pass = visits[-1], passes[-1]
        if current_pass not in expected_passes:  # this step began a pass
            skipped = {k for k, c in changes.items() if c < tolerance}
            everyone = set(range(5))
            expected_passes[current_pass] = (
                everyone if current_pass % revisit == 0 else (everyone - skipped or everyone)
            )
        loss = result.losses["img"]
        if frame in losses:
            change, gained = abs(loss - losses[frame]), first[frame] - loss
            changes[frame] = 0.0 if change == 0 else change / gained if gained > 0 else math.inf
        first.setdefault(frame, loss)
        losses[frame] = loss
        all_settled = len(changes) == 5 and all(c < tolerance for c in changes.values())
        if converged_at is None and all_settled:
            converged_at = step
            assert result.events["frames"]["frames/converged_at_step"] == step
        else:
            assert "frames" not in result.events
        assert result.metrics["frames/converged"] == sum(c < tolerance for c in changes.values())
    for number, frames in expected_passes.items():
        assert sorted(v for v, p in zip(visits, passes) if p == number) == sorted(frames) or (
            number == passes[-1]  # the pass in progress
        )
    assert any(len(frames) < 5 for frames in expected_passes.values())  # something was skipped
    assert converged_at is not None and engine.converged_at == converged_at
    resumed = DynamicReconstruction.from_state_dict(scene, engine.state_dict(), settings)
    assert (resumed.passes, resumed.converged_at) == (engine.passes, engine.converged_at)
    assert resumed.frame_changes == engine.frame_changes and resumed._order == engine._order


def test_dynamic_fit_stops_once_every_frame_has_converged(tmp_path, static_checkpoint, caplog):
    pl.seed_everything(0)
    module = DynamicModule(str(static_checkpoint), **DYNAMIC, frame_tolerance=0.05)
    with caplog.at_level(logging.INFO):
        fit = trainer(tmp_path, max_epochs=200, limit_val_batches=0)
        fit.fit(module, PhantomDataModule(SIMULATION))
    assert "the dynamic stage has converged and stops" in caplog.text
    assert fit.global_step == module.engine.converged_at < 200 * 5
