"""The static stage end to end: LightningCLI + MLflow, resume, failures."""

import copy
import csv
import dataclasses
import math
import re
import warnings

import lightning.pytorch as pl
import mlflow
import numpy as np
import pytest
import torch
import yaml
from lightning.pytorch.callbacks import ModelCheckpoint

from fgat.app.callbacks import StepCheckpoint
from fgat.app.datamodules import FLFMDataModule, PhantomDataModule
from fgat.app.lightning_cli import run
from fgat.app.modules import StaticModule
from fgat.gaussians.densify import Densification
from fgat.gaussians.voxelize import voxelize_dense
from fgat.io.images import read_tiff
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system, parse_depths
from fgat.recon import StaticReconstruction, StaticSettings, phantom_scene
from fgat.recon.estimation import OpticsEstimation
from fgat.recon.metrics import compare_volumes
from fgat.sim.simulation import SimulationConfig, true_optics

SIMULATION = dict(
    system="small",
    depths_um="-12:12:13",
    view_size=32,
    photons=None,
    phantom={"kind": "beads", "n_beads": 6, "sigma": 1.0, "min_spacing": 6, "margin": [1, 5, 5]},
)
MODEL = dict(
    n_gaussians=150,
    init_iterations=10,
    baseline_iterations=10,
    lr_means=0.05,
    lr_intensities=0.05,
    densification={
        "start": 10,
        "interval": 10,
        "stop": 30,
        "grad_threshold": 0.0,
        "max_gaussians": 400,
    },
)
TOLERANCE = 2.0  # optics.stderr_tolerance of the tests: a fraction some terms exceed, some not


def config_file(tmp_path, steps=40, **model):
    config = {
        "seed_everything": 0,
        "mlflow": {"experiment": "tests", "tracking_uri": f"sqlite:///{tmp_path}/mlflow.db"},
        "checkpoint_every": 20,
        "trainer": {
            "max_steps": steps,
            "default_root_dir": str(tmp_path / "run"),
            "accelerator": "cpu",
            "log_every_n_steps": 5,
            "val_check_interval": 20,
            "check_val_every_n_epoch": None,
            "num_sanity_val_steps": 0,
            "enable_progress_bar": False,
            "enable_model_summary": False,
        },
        "model": {"class_path": "fgat.modules.StaticModule", "init_args": {**MODEL, **model}},
        "data": {
            "class_path": "fgat.datamodules.PhantomDataModule",
            "init_args": {"simulation": SIMULATION},
        },
    }
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def logged_run(tmp_path):
    """The MLflow client and the one run of experiment "tests", named as fgat names a fit."""
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    (experiment,) = [e for e in client.search_experiments() if e.name == "tests"]
    (run_info,) = client.search_runs([experiment.experiment_id])
    assert run_info.info.run_name.startswith("fit-static-")  # not MLflow's seeded random name
    return client, run_info


@pytest.mark.slow
def test_fit_logs_metrics_and_artifacts_to_mlflow(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MLflow keeps artifacts in ./mlruns
    run(["fit", "--config", str(config_file(tmp_path, steps=45))])
    client, run_info = logged_run(tmp_path)
    metrics = run_info.data.metrics
    for name in (
        "loss/pix",
        "gaussians/count",
        "time/voxelize_ms",
        "time/projection_ms",
        "time/step_ms",
        "val/psnr_volume",
        "val/ssim_volume",
        "val/ssim_mip_xy",
        "val/psnr_volume_shb",
        "val/ssim_volume_shb",
        "val/ssim_mip_xy_shb",
        "gaussians/cloned",
    ):
        assert name in metrics and math.isfinite(metrics[name]), name
    artifacts = {a.path for a in client.list_artifacts(run_info.info.run_id)}
    assert {"config.yaml", "volume.ome.tif", "gaussians.pt", "mips.png"} <= artifacts
    last = torch.load(
        tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False
    )
    assert last["global_step"] == 45  # saved at the end too, not only every 20 steps


class Record(pl.Callback):
    def on_train_start(self, trainer, pl_module):
        self.start = (trainer.global_step, pl_module.engine.cloud.count)
        self.initial = compare_volumes(pl_module().numpy(), pl_module.scene.truth)["psnr"]

    def on_train_end(self, trainer, pl_module):
        self.end = (trainer.global_step, pl_module.engine.cloud.count)
        self.final = compare_volumes(pl_module().numpy(), pl_module.scene.truth)["psnr"]


def fit(tmp_path, steps, ckpt_path=None):
    record = Record()
    trainer = pl.Trainer(
        max_steps=steps,
        default_root_dir=tmp_path,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        accelerator="cpu",
        callbacks=[
            record,
            ModelCheckpoint(
                dirpath=tmp_path / "ckpt", save_last=True, every_n_train_steps=15, save_top_k=0
            ),
        ],
    )
    pl.seed_everything(0)
    trainer.fit(StaticModule(**MODEL), PhantomDataModule(SIMULATION), ckpt_path=ckpt_path)
    return record


def test_short_fit_improves_and_resume_continues(tmp_path):
    first = fit(tmp_path, 30)
    assert first.final > first.initial + 1.0  # dB
    assert first.end[1] != MODEL["n_gaussians"]  # densification changed the count
    resumed = fit(tmp_path, 45, ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))
    assert resumed.start == first.end  # same step, same Gaussian count
    assert resumed.end[0] == 45


def test_non_finite_loss_names_step_and_term():
    engine = StaticReconstruction(
        phantom_scene(SimulationConfig(**SIMULATION)), StaticSettings(n_gaussians=20)
    )
    engine.measurement[0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="step 0: loss term 'total' is nan"):
        engine.step()


def test_a_static_step_is_one_adam_step_on_the_data_loss():
    """Without a Trainer: the step's loss and update against a float64 reference (dense
    voxelizer, L1 data loss, autograd) and Adam's first step, -lr * sign(gradient)."""
    settings = StaticSettings(
        n_gaussians=30,
        init="random",
        init_scale=1.5,
        baseline_iterations=0,
        lr_means=0.01,
        lr_scales=0.02,
        lr_quats=0.03,
        lr_intensities=0.04,
    )
    engine = StaticReconstruction(
        phantom_scene(SimulationConfig(**SIMULATION)),
        settings,
        Densification(enabled=False),
        total_steps=10,
    )
    reference = copy.deepcopy(engine.cloud).double()
    volume = voxelize_dense(
        reference.means,
        reference.scales,
        reference.quaternions,
        reference.intensities,
        reference.shape,
        reference.voxel_size.tolist(),
        reference.origin.tolist(),
    )
    operator = FLFMOperator(engine.psf.double(), reference.shape)
    loss = (operator.forward(volume) - engine.measurement.double()).abs().mean()
    loss.backward()
    loss = loss.detach()
    before = {
        name: parameter.detach().clone() for name, parameter in engine.cloud.named_parameters()
    }
    result = engine.step()
    assert result.losses["pix"] == pytest.approx(loss.item(), rel=1e-5)
    assert engine.steps_done == 1 and result.events == {} and result.count == 30
    # The rotation of the (isotropic) initial Gaussians has a zero gradient up to rounding: its sign
    # is noise.
    rates = {"means": 0.01, "raw_scales": 0.02, "raw_intensities": 0.04}
    for name, rate in rates.items():
        gradient = getattr(reference, name).grad
        clear = gradient.abs() > 1e-3 * gradient.abs().max()  # signs float32 agrees on
        step = (getattr(engine.cloud, name).detach() - before[name]).double()
        assert clear.sum() >= 10, name
        torch.testing.assert_close(step[clear], -rate * gradient[clear].sign(), rtol=0, atol=1e-5)


class Kill(pl.Callback):
    """Stop a run after ``step`` steps, as a kill after its last checkpoint would."""

    def __init__(self, step):
        self.step = step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        trainer.should_stop = trainer.should_stop or trainer.global_step == self.step


@pytest.mark.slow
def test_a_resumed_run_is_the_run_it_continues(tmp_path):
    """Killed at step 13 and resumed, a fit with densification, JPGM events and an annealed
    Fourier term ends bit-identical to the same fit run straight through (CPU)."""
    model = {
        **MODEL,
        "lambda_fourier": 0.1,
        "optics": {"estimate": "joint", "start": 8, "every": 8, "steps": 2},
    }
    simulation = {**SIMULATION, "zernike": {5: 0.1}, "intercepts": {1: [0.0, 0.5]}}

    def fit(root, kill=None, ckpt_path=None):
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
            callbacks=[checkpoint] + ([Kill(kill)] if kill else []),
        )
        pl.seed_everything(0)
        module = StaticModule(**model)
        trainer.fit(module, PhantomDataModule(simulation, psf="ideal"), ckpt_path=ckpt_path)
        return module, trainer

    straight, _ = fit(tmp_path / "straight")
    _, killed = fit(tmp_path / "resumed", kill=13)
    assert killed.global_step == 13
    resumed, trainer = fit(
        tmp_path / "resumed", ckpt_path=tmp_path / "resumed" / "ckpt" / "last.ckpt"
    )
    assert trainer.global_step == 30 and resumed.engine.steps_done == 30
    assert (
        resumed.engine.cloud.count == straight.engine.cloud.count != MODEL["n_gaussians"]
    )  # densified
    for (name, expected), actual in zip(
        straight.engine.cloud.named_parameters(), resumed.engine.cloud.parameters()
    ):
        torch.testing.assert_close(actual, expected, rtol=0, atol=0, msg=name)
    for (name, expected), actual in zip(
        straight.engine.jpgm.named_parameters(), resumed.engine.jpgm.parameters()
    ):
        torch.testing.assert_close(actual, expected, rtol=0, atol=0, msg=name)
    torch.testing.assert_close(resumed.engine.psf, straight.engine.psf, rtol=0, atol=0)
    np.testing.assert_equal(resumed.engine.evaluate(), straight.engine.evaluate())


def test_bad_configs_fail_fast(tmp_path):
    with pytest.raises(
        ValueError,
        match="n_gausians: unknown option of fgat.modules.StaticModule; did you mean",
    ):
        run(["fit", "--config", str(config_file(tmp_path)), "--model.init_args.n_gausians=3"])
    with pytest.raises(ValueError, match="phantom.kind must be one of"):
        PhantomDataModule({**SIMULATION, "phantom": {"kind": "cubes"}})
    with pytest.raises(ValueError, match="data.psf must be"):
        PhantomDataModule(SIMULATION, psf="best")
    with pytest.raises(
        FileNotFoundError, match="data.measurement: file .*missing.tif does not exist"
    ):
        FLFMDataModule(str(tmp_path / "missing.tif"), centers=None, brightfield=None)
    image = tmp_path / "frame.tif"
    image.write_bytes(b"")
    with pytest.raises(ValueError, match="give a 'calibration' folder .*, lenslet 'centers'"):
        FLFMDataModule(str(image))
    with pytest.raises(ValueError, match="model.init must be"):
        StaticModule(init="dense")


def test_flfm_datamodule_reads_a_simulation_folder(tmp_path):
    import numpy as np

    from fgat.io.images import write_tiff
    from fgat.sim.simulation import SimulationConfig, simulate, write_simulation

    result = simulate(SimulationConfig(**{**SIMULATION, "photons": 500.0, "background": 20.0}))
    folder = write_simulation(result, tmp_path / "sim")
    sequence = np.stack([result.sensor * 0.5, result.sensor, result.sensor * 2.0])
    write_tiff(tmp_path / "sequence.tif", sequence, axes="TYX")
    data = FLFMDataModule(
        str(tmp_path / "sequence.tif"),
        centers=str(folder / "centers.csv"),
        psf=str(folder / "psf.ome.tif"),
        view_size=32,
        background=20.0,
        truth=str(folder / "truth.ome.tif"),
    )
    data.setup("fit")
    scene = data.scene
    expected = np.clip(result.views - 20.0, 0, None)
    np.testing.assert_allclose(
        scene.measurement * scene.scale, expected, rtol=1e-5, atol=1e-3
    )  # middle frame
    assert scene.volume_shape == (13, 32, 32) and scene.voxel_size_um == pytest.approx(
        (2.0, 0.975, 0.975)
    )
    with pytest.raises(ValueError, match="frame 5 is outside the 3 frames"):
        FLFMDataModule(
            str(tmp_path / "sequence.tif"),
            frame=5,
            centers=str(folder / "centers.csv"),
            psf=str(folder / "psf.ome.tif"),
        ).setup("fit")


def test_plateau_stopping():
    from types import SimpleNamespace

    from fgat.app.callbacks import PlateauStopping

    def drive(losses, **options):
        callback = PlateauStopping(**options)
        trainer = SimpleNamespace(should_stop=False, global_step=0)
        for step, loss in enumerate(losses):
            trainer.global_step = step + 1
            callback.on_train_batch_end(trainer, SimpleNamespace(last_loss=loss), None, None, step)
            if trainer.should_stop:
                return step + 1
        return None

    assert drive([1.0] * 100, tolerance=1e-3, window=10, min_steps=0) == 20
    assert (
        drive([1.0 / (k + 1) for k in range(100)], tolerance=1e-3, window=10, min_steps=0) is None
    )
    assert drive([1.0] * 100, tolerance=1e-3, window=10, min_steps=50) == 50


@pytest.mark.slow
def test_flfm_datamodule_computes_the_psf_from_optics(tmp_path):
    from fgat.optics.psf import JPGM
    from fgat.optics.systems import load_system
    from fgat.sim.simulation import SimulationConfig, simulate, write_simulation

    result = simulate(SimulationConfig(**SIMULATION))
    folder = write_simulation(result, tmp_path / "sim")
    data = FLFMDataModule(
        str(folder / "sensor.ome.tif"),
        centers=str(folder / "centers.csv"),
        system="small",
        depths_um="-12:12:13",
        zernike={5: 0.2},
        intercepts={2: [0.5, 0.0]},
        view_size=32,
    )
    data.setup("fit")
    expected = JPGM.with_parameters(
        load_system("small"),
        [float(z) for z in range(-12, 13, 2)],
        centers_px=result.centers,
        zernike={5: 0.2},
        intercepts={2: [0.5, 0.0]},
    )
    with torch.no_grad():
        torch.testing.assert_close(torch.from_numpy(data.scene.psf), expected())
    with pytest.raises(ValueError, match="slopes: view 9 does not exist"):
        FLFMDataModule(
            str(folder / "sensor.ome.tif"),
            centers=str(folder / "centers.csv"),
            system="small",
            depths_um="0",
            slopes={9: [0, 1]},
        ).setup("fit")


@pytest.mark.slow
def test_jpgm_events_in_a_fit(tmp_path, caplog):
    simulation = {**SIMULATION, "zernike": {5: 0.15}, "intercepts": {1: [0.0, 0.8]}}
    model = {
        **MODEL,
        "densification": {"enabled": False},
        "optics": {"estimate": "joint", "start": 10, "every": 10, "steps": 4},
    }
    trainer = pl.Trainer(
        max_steps=20,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        accelerator="cpu",
        enable_checkpointing=False,
    )
    module = StaticModule(**model)
    data = PhantomDataModule(simulation, psf="ideal")
    trainer.fit(module, data)
    engine = module.engine
    assert (
        engine.jpgm.zernike_coefficients.detach().abs().max() > 0
    )  # estimated from the ideal start
    ideal = torch.from_numpy(data.scene.psf)
    assert not torch.allclose(engine.psf, ideal)  # the operator follows the estimated optics
    with torch.no_grad():
        torch.testing.assert_close(engine.psf, engine.jpgm())
    fixed = StaticModule(**{**MODEL, "densification": {"enabled": False}})
    caplog.set_level("INFO")
    pl.Trainer(
        max_steps=5,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        accelerator="cpu",
        enable_checkpointing=False,
    ).fit(fixed, PhantomDataModule(simulation, psf="ideal"))
    assert fixed.engine.jpgm is None
    torch.testing.assert_close(fixed.engine.psf, ideal)  # estimate = none: PSF untouched
    assert "JPGM self-estimation skipped" in caplog.text
    with pytest.raises(ValueError, match="needs a PSF made from optics"):
        psf_file = tmp_path / "psf.tif"
        from fgat.io.images import write_tiff

        write_tiff(psf_file, data.scene.psf)
        pl.Trainer(max_steps=1, logger=False, enable_progress_bar=False, accelerator="cpu").fit(
            StaticModule(**model), PhantomDataModule(simulation, psf=str(psf_file))
        )


@pytest.mark.slow
def test_jpgm_events_log_truth_and_residual(tmp_path, monkeypatch):
    """The optics, their truth and errors, and at the end their standard errors."""
    monkeypatch.chdir(tmp_path)
    path = config_file(
        tmp_path,
        steps=20,
        densification={"enabled": False},
        optics={
            "estimate": "zernike",
            "start": 10,
            "every": 10,
            "steps": 3,
            "stderr_tolerance": TOLERANCE,
        },
    )
    config = yaml.safe_load(path.read_text())
    config["data"]["init_args"]["psf"] = "ideal"
    config["data"]["init_args"]["simulation"]["aberrations"] = {
        "terms": 3,
        "amplitude": 0.1,
        "seed": 1,
    }
    path.write_text(yaml.safe_dump(config))
    run(["fit", "--config", str(path)])
    client, run_info = logged_run(tmp_path)
    metrics = run_info.data.metrics
    for name in (
        "zernike/c5",
        "zernike_gt/c5",
        "shift_gt/b1_x",
        "zernike/residual_normalized",
        "time/jpgm_iter_ms",
    ):
        assert name in metrics, name
    assert (
        metrics["zernike_gt/c21"] == 0.0 and metrics["zernike_gt/c5"] != 0.0
    )  # three sampled terms
    params = run_info.data.params
    assert (
        params["simulation/aberrations/terms"] == "3" and params["psf"] == "ideal"
    )  # the datamodule's too
    # optics errors against an independent float64 evaluation of the ideal and true stacks
    simulation = SimulationConfig(**config["data"]["init_args"]["simulation"])
    system, depths = load_system(simulation.system), parse_depths(simulation.depths_um)
    optics = true_optics(simulation, system.n_lenslets)
    with torch.no_grad():
        ideal = JPGM(system, depths, dtype=torch.float64)().numpy()
        truth = JPGM.with_parameters(system, depths, dtype=torch.float64, **optics)().numpy()
    for v in range(system.n_lenslets):
        expected = np.linalg.norm(ideal[v] - truth[v]) / np.linalg.norm(truth[v])
        assert metrics[f"psf/error_initial_view{v}"] == pytest.approx(expected, rel=1e-4)
    coefficients = np.array([optics["zernike"].get(j, 0.0) for j in range(5, 22)])
    estimated = np.array([metrics[f"zernike/c{j}"] for j in range(5, 22)])
    assert metrics["zernike/residual_normalized"] == pytest.approx(
        np.linalg.norm(estimated - coefficients) / np.linalg.norm(coefficients), rel=1e-5
    )
    assert (
        metrics["psf/error"] < metrics["psf/error_initial"]
    )  # the events moved the PSF towards the truth
    for name in (
        "intercept_error_max_px",
        "slope_error_max_px",
        "intercept_error_gauge_free_max_px",
    ):
        assert metrics[f"shift/{name}"] == 0.0  # shifts neither aberrated nor estimated
    artifacts = {a.path for a in client.list_artifacts(run_info.info.run_id)}
    assert {
        "psf.ome.tif",
        "optics.yaml",
        "pupil_phase.png",
        "zernike.png",
        "psf_ideal.png",
        "psf_estimated.png",
        "psf_truth.png",
        "shb.ome.tif",
    } <= artifacts
    # the estimated stack reads back as fgat deconvolve reads a PSF
    local = mlflow.artifacts.download_artifacts(
        run_id=run_info.info.run_id,
        artifact_path="psf.ome.tif",
        dst_path=str(tmp_path / "fetched"),
        tracking_uri=client.tracking_uri,
    )
    estimated = read_tiff(local, ndim=4, axes="(V, Z, h, w) PSF stack", nonnegative=True)
    assert estimated.shape == ideal.shape
    expected = np.linalg.norm(estimated - truth) / np.linalg.norm(truth)
    assert metrics["psf/error"] == pytest.approx(expected, rel=1e-3)
    # the standard errors at the end: a metric and a row per coefficient, the flag by the rule
    assert {"identifiability.csv", "identifiability.png"} <= artifacts
    table = mlflow.artifacts.download_artifacts(
        run_id=run_info.info.run_id,
        artifact_path="identifiability.csv",
        dst_path=str(tmp_path / "fetched"),
        tracking_uri=client.tracking_uri,
    )
    with open(table, newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["parameter"] for row in rows] == [f"zernike/c{j}" for j in range(5, 22)]
    assert not any(name.startswith("shift/stderr") for name in metrics)  # shifts not estimated
    for row, c in zip(rows, coefficients):
        stderr, value = float(row["stderr"]), float(row["estimate"])
        assert math.isfinite(stderr) and stderr > 0
        assert metrics[row["parameter"].replace("/c", "/stderr_c")] == pytest.approx(stderr)
        assert value == pytest.approx(metrics[row["parameter"]])
        assert row["flagged"] == str(int(stderr > TOLERANCE * abs(value)))
        assert float(row["truth"]) == pytest.approx(c)
        assert row["within_2se"] == str(int(abs(value - c) <= 2 * stderr))
    flagged = sum(int(row["flagged"]) for row in rows)
    assert metrics["identifiability/flagged"] == flagged and 0 < flagged < len(rows)  # both kinds
    assert 0 < metrics["identifiability/noise_sigma"] < 1


def test_gain_settings_reach_the_engine_settings():
    module = StaticModule(estimate_gains=True, lr_gains=0.02)
    assert module.settings.estimate_gains and module.settings.lr_gains == 0.02
    assert not StaticModule().settings.estimate_gains
    with pytest.raises(ValueError, match="model.lr_gains must be a positive number"):
        StaticModule(estimate_gains=True, lr_gains=0.0)


@pytest.mark.parametrize("logging", [True, False])
def test_log_step_logs_the_step_metrics_on_logging_steps(logging):
    from types import SimpleNamespace

    from fgat.app.modules.shell import log_step
    from fgat.recon import StepResult
    from fgat.recon.plateau import LossTrend

    logged = {}
    module = SimpleNamespace(
        loss_trend=LossTrend(),
        log_dict=logged.update,
        log=lambda name, value, **options: logged.__setitem__(name, value),
        loggers=[],
        global_step=0,
        trainer=SimpleNamespace(_logger_connector=SimpleNamespace(should_update_logs=logging)),
    )
    result = StepResult({"total": 1.5}, {"step_ms": 2.0}, count=3, metrics={"gain/view1": 0.9})
    log_step(module, result)
    assert module.last_loss == 1.5 and module.loss_trend.last == 1.5
    if logging:
        assert logged["gain/view1"] == 0.9 and logged["gaussians/count"] == 3.0
        assert logged["loss"] == 1.5 and logged["time/step_ms"] == 2.0
    else:
        assert logged == {}


def optics_engine(steps=8, **optics):
    """A tiny engine estimating the Zernike terms of a one-term phantom, a few pixels masked,
    after ``steps`` steps (8: one JPGM event)."""
    scene = phantom_scene(SimulationConfig(**{**SIMULATION, "zernike": {5: 0.1}}), psf="ideal")
    mask = np.ones_like(scene.measurement)
    mask[:, ::7, ::5] = 0.0
    scene = dataclasses.replace(scene, mask=mask)
    engine = StaticReconstruction(
        scene,
        StaticSettings(n_gaussians=40, init_iterations=5, baseline_iterations=0),
        Densification(enabled=False),
        OpticsEstimation(estimate="zernike", start=4, every=4, steps=3, **optics),
        total_steps=8,
    )
    for _ in range(steps):
        engine.step()
    return engine


@pytest.mark.slow
def test_converged_optics_skip_later_events_and_resume_so():
    with pytest.warns(RuntimeWarning, match="the optics converged after step 12"):
        engine = optics_engine(steps=12, tolerance=0.9, parameter_tolerance=0.99)
    assert engine.optics_converged_at == 12  # quiet events at steps 8 and 12
    assert not any("optics" in engine.step().events for _ in range(8))  # due at 16 and 20
    resumed = optics_engine(steps=0, tolerance=0.9, parameter_tolerance=0.99)
    resumed.load_state_dict(engine.state_dict())
    assert resumed.optics_converged_at == 12
    assert optics_engine(steps=12).optics_converged_at is None  # tolerance 0: never


@pytest.mark.slow
def test_identifiability_noise_is_the_residual_variance_of_the_used_pixels():
    engine = optics_engine(stderr_tolerance=0.3)
    result = engine.identifiability()
    with torch.no_grad():  # independently: the engine's float32 forward model
        residual = (engine.operator.forward(engine.cloud()) - engine.measurement).double()
    used = torch.from_numpy(engine.scene.mask).bool()
    n_parameters = 11 * engine.cloud.count + len(engine.jpgm.zernike_indices)
    expected = residual[used].square().sum() / (int(used.sum()) - n_parameters)
    assert result.n_pixels == int(used.sum()) < used.numel()
    assert result.n_parameters == n_parameters
    assert result.noise_sigma == pytest.approx(float(expected.sqrt()), rel=1e-4)
    rows = result.rows()
    assert len(rows) == len(engine.jpgm.zernike_indices) and "truth" in rows[0]
    for row in rows:
        assert math.isfinite(row["stderr"]) and row["stderr"] > 0
        assert row["flagged"] == int(row["stderr"] > 0.3 * abs(row["estimate"]))


def test_identifiability_memory_counts_the_estimated_groups_columns():
    """Three Jacobian copies of ``N = V Y X`` rows per estimated column (``K`` Zernike terms,
    ``4V`` shifts): the groups' bounds differ by exactly those columns."""
    from fgat.recon.optics_report import identifiability_memory

    jpgm = JPGM(load_system("small"), [-5.0, 0.0, 5.0], crop_radius_px=16, dtype=torch.float64)
    shape = (3, 24, 24)
    bytes_of = {e: identifiability_memory(jpgm, shape, estimate=e) for e in ("zernike", "shifts")}
    bytes_of["joint"] = identifiability_memory(jpgm, shape)
    column = 3 * 7 * 24 * 24 * 8
    assert bytes_of["joint"] - bytes_of["zernike"] == 4 * 7 * column
    assert bytes_of["joint"] - bytes_of["shifts"] == 17 * column
    with pytest.raises(ValueError, match="estimate must be"):
        identifiability_memory(jpgm, shape, estimate="both")


def test_identifiability_skipped_writes_nothing(tmp_path, caplog, monkeypatch):
    from types import SimpleNamespace

    from fgat.app.callbacks.artifacts import identifiability_files

    trainer = SimpleNamespace(loggers=[], global_step=8)
    engine = optics_engine(steps=0, identifiability=False)
    caplog.set_level("INFO")
    identifiability_files(trainer, engine, tmp_path)
    assert "identifiability skipped (model.optics.identifiability = false)" in caplog.text
    engine.estimation = OpticsEstimation(estimate="zernike")  # switched on, but no memory
    monkeypatch.setattr("fgat._core.resources.available_memory", lambda device=None: 1000)
    identifiability_files(trainer, engine, tmp_path)
    assert "identifiability skipped: the standard errors of the estimated optics" in caplog.text
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="model.optics.stderr_tolerance must be a positive"):
        StaticModule(optics={"estimate": "zernike", "stderr_tolerance": 0})


@pytest.mark.slow
def test_a_fit_started_afresh_in_a_run_folder_replaces_its_last_checkpoint(tmp_path, monkeypatch):
    """A recipe's --refit runs again in the same folder: the folder's last.ckpt must then be the
    new run's, not the previous one's beside a last-v1.ckpt."""
    monkeypatch.chdir(tmp_path)
    for steps in (10, 6):
        run(["fit", "--config", str(config_file(tmp_path, steps=steps))])
    checkpoints = tmp_path / "run" / "checkpoints"
    assert [path.name for path in checkpoints.iterdir()] == ["last.ckpt"]
    saved = torch.load(checkpoints / "last.ckpt", map_location="cpu", weights_only=False)
    assert saved["global_step"] == 6


@pytest.mark.slow
def test_identifiability_without_gaussians_names_the_singular_block():
    """Every Gaussian pruned: the image says nothing about the optics, and the report says so
    (identifiability_files then logs it as skipped) instead of writing NaN standard errors."""
    engine = optics_engine(steps=0)
    engine.cloud.set_gaussians(torch.zeros(0, 3), torch.ones(0, 3), torch.ones(0))
    with pytest.raises(ValueError, match=r"the block A \(Zernike\) is singular"):
        engine.identifiability()


def test_identifiability_summary_warns_for_joint_estimates():
    from types import SimpleNamespace

    from fgat.app.callbacks.artifacts import identifiability_summary

    result = SimpleNamespace(
        noise_sigma=0.003,
        flagged=np.array([True, False, False, False]),
        names=["zernike/c5", "zernike/c6", "shift/b0_y", "shift/b0_x"],
        tolerance=0.5,
        truth=np.zeros(4),
        within_2se=np.array([1.0, 1.0, 0.0, 1.0]),
    )
    line = identifiability_summary(result, "zernike")
    assert "1 of 4 estimated terms flagged (s.e. > 0.5 |estimate|)" in line
    assert "within 2 s.e. for 75% of them" in line and "joint" not in line
    assert "one optical model" in identifiability_summary(result, "joint")
    assert "within 2 s.e." not in identifiability_summary(
        SimpleNamespace(**{**vars(result), "truth": None}), "shifts"
    )


@pytest.mark.slow
def test_measured_data_skips_the_shb_baseline(monkeypatch):
    """Without a truth the SHB pre-pass runs only the initialisation's iterations and no
    baseline is kept; with one it runs to the baseline's and keeps it."""
    import fgat.recon.static as static

    runs = []
    deconvolve = static.deconvolve

    def counted(*args, **kwargs):
        runs.append(args[2])
        return deconvolve(*args, **kwargs)

    monkeypatch.setattr(static, "deconvolve", counted)
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    settings = StaticSettings(n_gaussians=20, init_iterations=5, baseline_iterations=12)
    measured = StaticReconstruction(
        dataclasses.replace(scene, truth=None), settings, Densification(enabled=False)
    )
    phantom = StaticReconstruction(scene, settings, Densification(enabled=False))
    assert runs == [5, 12]
    assert measured.baseline is None and measured.evaluate() == {}
    assert phantom.baseline.shape == scene.volume_shape
    assert "val/psnr_volume_shb" in phantom.evaluate()


def test_identifiability_plan_splits_planes_then_columns_to_fit():
    """A budget below the whole stack's passes: fewer planes per pass first, then fewer columns,
    and the planned bytes within the budget; no limit keeps everything in one pass."""
    from fgat.recon.optics_report import identifiability_memory, identifiability_plan

    jpgm = JPGM(load_system("small"), [-6.0, -3.0, 0.0, 3.0, 6.0], crop_radius_px=16)
    shape = (5, 24, 24)
    whole = identifiability_plan(jpgm, shape)
    assert (whole.chunk_size, whole.depth_chunk) == (8, 5)
    assert whole.nbytes == identifiability_memory(jpgm, shape)
    one_plane = identifiability_memory(jpgm, shape, chunk_size=8, depth_chunk=1)
    assert one_plane < whole.nbytes
    plan = identifiability_plan(jpgm, shape, available=one_plane / 0.8)
    assert (plan.chunk_size, plan.depth_chunk, plan.nbytes) == (8, 1, one_plane)
    tight = identifiability_plan(jpgm, shape, available=0.6 * one_plane / 0.8)
    assert tight.depth_chunk == 1 and tight.chunk_size < 8 and tight.nbytes <= 0.6 * one_plane


@pytest.mark.slow
def test_only_a_last_event_still_moving_is_reported():
    """Zernike steps of 1e-4 waves cannot reach a 0.1-wave term: both events stop at full speed.
    The events log it without a warning (an alternation's early events move by design); the fit's
    end reports the last one, also after a resume."""
    assert optics_engine(steps=0).optics_settling() is None  # no event yet
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        engine = optics_engine(steps=8, lr_zernike=1e-4)
    line = engine.optics_settling()
    assert line.startswith("the last JPGM event (after step 8) ended with entries still moving")
    assert re.search(r"\(\d+ of \d+ zernike coefficients\)", line)
    assert "raise optics.lr_zernike or optics.steps" in line
    resumed = optics_engine(steps=0, lr_zernike=1e-4)
    resumed.load_state_dict(engine.state_dict())
    assert resumed.optics_settling() == line
