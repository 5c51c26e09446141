"""The relative data residual and its reports (deconvolve, fit), and the labels of mips.png."""

import json
import logging
import math
from types import SimpleNamespace

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from scipy.signal import convolve

from fgat.app.callbacks import PlateauStopping, ReconstructionArtifacts, artifacts
from fgat.app.cli import main
from fgat.app.datamodules import PhantomDataModule
from fgat.app.modules import DynamicModule, StaticModule
from fgat.app.report import deconvolution_ending, report_path
from fgat.optics.acquisition import MeasuredOperator
from fgat.recon.metrics import relative_residual
from fgat.recon.outcome import VolumeRecord
from tests.integration.test_dynamic_stage import DYNAMIC, static_checkpoint  # noqa: F401 (fixture)
from tests.integration.test_dynamic_stage import SIMULATION as DYNAMIC_SIMULATION
from tests.integration.test_dynamic_stage import trainer as dynamic_trainer
from tests.integration.test_static import MODEL, SIMULATION
from tests.unit.sim.test_simulation import simulated, write_simulation  # noqa: F401 (fixture)


def brute_force_residual(psf, volume, data, gains, guard, mask):
    """||w (G C A x - y)|| / ||w y|| with A from scipy's direct convolution, float64."""
    views, ratios, misfit, norm = [], [], 0.0, 0.0
    n = data.shape[-1]
    for v in range(psf.shape[0]):
        full = sum(convolve(volume[z], psf[v, z], mode="same") for z in range(volume.shape[0]))
        view = gains[v] * full[guard : guard + n, guard : guard + n]
        m = ((mask[v] * (view - data[v])) ** 2).sum()
        d = ((mask[v] * data[v]) ** 2).sum()
        views.append(view)
        ratios.append(math.sqrt(m / d))
        misfit, norm = misfit + m, norm + d
    return math.sqrt(misfit / norm), ratios


def test_relative_residual_matches_a_float64_brute_force():
    rng = np.random.default_rng(3)
    n_views, depths, size, guard = 3, 4, 12, 2
    psf = rng.random((n_views, depths, 7, 7))
    volume = rng.random((depths, size + 2 * guard, size + 2 * guard))
    data = rng.random((n_views, size, size)) * 20
    gains = np.array([0.7, 1.0, 1.3])
    mask = (rng.random(data.shape) > 0.1).astype(np.float64)  # hot pixels at 0
    operator = MeasuredOperator(
        torch.tensor(psf, dtype=torch.float32), (size, size), guard_px=guard, gains=gains
    )
    found = relative_residual(
        operator, torch.tensor(volume, dtype=torch.float32), data, torch.tensor(mask)
    )
    overall, views = brute_force_residual(psf, volume, data, gains, guard, mask)
    assert found["overall"] == pytest.approx(overall, rel=1e-5)
    np.testing.assert_allclose(found["views"], views, rtol=1e-5)
    assert 0.05 < overall < 10 and len(set(np.round(views, 3))) == n_views  # not degenerate
    # a mask with a hot pixel that the prediction misses by far: left out, it changes nothing
    spoiled = data.copy()
    spoiled[mask == 0] = 1e6
    again = relative_residual(operator, torch.tensor(volume, dtype=torch.float32), spoiled, mask)
    assert again["overall"] == pytest.approx(overall, rel=1e-5)
    empty = relative_residual(operator, torch.zeros(operator.volume_shape), data, mask)
    assert empty["overall"] == pytest.approx(1.0) and empty["views"] == pytest.approx([1.0] * 3)


def test_relative_residual_refuses_a_measurement_of_another_shape():
    operator = MeasuredOperator(torch.ones(2, 1, 3, 3), (5, 5))
    with pytest.raises(ValueError, match=r"measurement has shape \(2, 4, 4\), the operator"):
        relative_residual(operator, torch.ones(1, 5, 5), np.ones((2, 4, 4)))


def test_deconvolution_ending_names_the_rule_or_the_budget():
    assert deconvolution_ending(12, 50, 1e-4, None) == (
        True,
        "converged: the Poisson cost changed by less than tol = 0.0001 after 12 of 50 iterations",
    )
    converged, text = deconvolution_ending(30, 50, None, 0.1)
    assert converged and "held-out pixels' rule" in text
    converged, text = deconvolution_ending(50, 50, 1e-4, None)
    assert not converged and "iteration budget (--iterations 50) rather than converged" in text
    converged, text = deconvolution_ending(50, 50, None, None)
    assert not converged and "convergence not tested" in text
    assert report_path("out/vol.ome.tif").name == "vol.residual.json"


@pytest.mark.slow
def test_deconvolve_prints_and_writes_the_residual(tmp_path, simulated, capsys):  # noqa: F811
    folder = write_simulation(simulated, tmp_path / "sim")
    command = ["deconvolve", "--measurement", str(folder / "sensor.ome.tif")]
    command += ["--psf", str(folder / "psf.ome.tif"), "--centers", str(folder / "centers.csv")]
    command += ["--background", "50"]
    reports = {}
    for name, extra in (("short", ["--iterations", "2"]), ("long", ["--iterations", "12"])):
        out = tmp_path / f"{name}.ome.tif"
        assert main([*command, *extra, "--tol", "1e-9", "--out", str(out)]) == 0
        printed = capsys.readouterr().out
        report = json.loads((tmp_path / f"{name}.residual.json").read_text())
        assert f"relative data residual ||Ax - y|| / ||y|| {report['relative_residual']:.4g}" in (
            printed
        )
        assert "rather than converged (--tol not met)" in printed and not report["converged"]
        assert len(report["relative_residual_views"]) == simulated.views.shape[0]
        assert report["iterations"] == report["max_iterations"]
        reports[name] = report["relative_residual"]
    assert 0 < reports["long"] < 0.8 * reports["short"] < 1  # iterating explains more of the data
    out = tmp_path / "loose.ome.tif"
    assert main([*command, "--iterations", "12", "--tol", "0.5", "--out", str(out)]) == 0
    assert "converged: the Poisson cost changed by less than tol = 0.5" in capsys.readouterr().out
    report = json.loads((tmp_path / "loose.residual.json").read_text())
    assert report["converged"] and report["iterations"] < 12
    (tmp_path / "taken.residual.json").write_text("a user's file")
    assert main([*command, "--out", str(tmp_path / "taken.ome.tif")]) == 2
    assert "taken.residual.json" in capsys.readouterr().err
    assert (tmp_path / "taken.residual.json").read_text() == "a user's file"


@pytest.mark.parametrize(
    ("jpgm", "label"),
    [
        (None, "3DGAT (Gaussians, optics fixed)"),
        (object(), "4DGAT static (Gaussians, optics estimated)"),
    ],
)
def test_mips_are_labelled_by_what_ran(tmp_path, monkeypatch, jpgm, label):
    shown = {}
    monkeypatch.setattr(artifacts, "plot_mips", lambda panels, *a, **k: shown.update(panels))
    monkeypatch.setattr(artifacts, "write_scene_volume", lambda *a, **k: None)
    monkeypatch.setattr(artifacts.ReconstructionArtifacts, "_optics_files", lambda *a: None)
    monkeypatch.setattr(artifacts, "identifiability_files", lambda *a: None)
    monkeypatch.setattr(artifacts, "relative_residual", lambda *a: {})
    scene = SimpleNamespace(scale=1.0, truth=None, name="s", voxel_size_um=(1.0, 1.0, 1.0))
    engine = SimpleNamespace(
        scene=scene,
        volume=lambda: torch.ones(2, 3, 3),
        cloud=SimpleNamespace(save=lambda path: None),
        jpgm=jpgm,
        optics_settling=lambda: None,
        log_gains=None,
        baseline=None,
        operator=None,
        grid_volume=lambda: None,
        measurement=None,
        mask=None,
    )
    artifacts.ReconstructionArtifacts._static_files(
        None, SimpleNamespace(engine=engine), tmp_path, VolumeRecord()
    )
    assert list(shown) == [label]


def test_fit_ending_names_the_rule_or_the_budget():
    plateau = PlateauStopping()
    trainer = SimpleNamespace(global_step=30, max_steps=30, callbacks=[plateau])
    module = SimpleNamespace(stop_reason=None)
    assert artifacts.fit_ending(trainer, module) == (
        False,
        "stopped by its step budget (trainer.max_steps = 30) rather than converged "
        "(PlateauStopping not met)",
    )
    trainer.callbacks = []
    assert (
        "no stopping rule: fgat.callbacks.PlateauStopping"
        in artifacts.fit_ending(trainer, module)[1]
    )
    trainer.callbacks, trainer.global_step, plateau.reason = [plateau], 12, "flat"
    assert artifacts.fit_ending(trainer, module) == (
        True,
        "converged: stopped at step 12 by its stopping rule (flat)",
    )
    trainer.callbacks, module.stop_reason = [], "frames converged"
    assert artifacts.fit_ending(trainer, module)[0]


@pytest.mark.slow
@pytest.mark.parametrize("plateau", [False, True])
def test_a_fit_reports_its_residual_and_how_it_stopped(tmp_path, caplog, plateau):
    callbacks = [ReconstructionArtifacts()]
    if plateau:  # any window that improves the loss by less than all of it is a plateau
        callbacks.append(PlateauStopping(tolerance=1.0, window=4, min_steps=4))
    trainer = pl.Trainer(
        max_steps=30,
        default_root_dir=tmp_path,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        accelerator="cpu",
        enable_checkpointing=False,
        callbacks=callbacks,
    )
    module = StaticModule(**{**MODEL, "baseline_iterations": 0})
    with caplog.at_level(logging.INFO):
        trainer.fit(module, PhantomDataModule(SIMULATION))
    report = json.loads((tmp_path / "results" / "latest" / "residual.json").read_text())
    engine = module.engine
    views = engine.operator.forward(engine.grid_volume()).double().numpy()
    data = engine.measurement.double().numpy()
    misfit, norm = ((views - data) ** 2).sum(axis=(1, 2)), (data**2).sum(axis=(1, 2))
    assert report["relative_residual"] == pytest.approx(math.sqrt(misfit.sum() / norm.sum()))
    np.testing.assert_allclose(report["relative_residual_views"], np.sqrt(misfit / norm))
    assert report["relative_residual"] > 0
    assert report["steps"] == trainer.global_step and report["stage"] == "static"
    assert report["loss"] == pytest.approx(module.last_loss)
    assert report["converged"] == plateau
    if plateau:
        assert trainer.global_step < 30
        assert report["stopped"].startswith(f"converged: stopped at step {trainer.global_step}")
    else:
        assert report["relative_residual"] < 0.5  # 30 steps explain most of the data
        assert report["stopped"].startswith(
            "stopped by its step budget (trainer.max_steps = 30) rather than converged"
        )
    assert f"data: relative data residual ||Ax - y|| / ||y|| {report['relative_residual']:.4g}" in (
        caplog.text
    )


@pytest.mark.slow
def test_a_dynamic_fit_reports_the_residual_of_every_frame(tmp_path, static_checkpoint):  # noqa: F811
    pl.seed_everything(0)
    module = DynamicModule(str(static_checkpoint), **DYNAMIC, frame_tolerance=0.05)
    fit = dynamic_trainer(
        tmp_path, max_epochs=200, limit_val_batches=0, callbacks=[ReconstructionArtifacts()]
    )
    fit.fit(module, PhantomDataModule(DYNAMIC_SIMULATION))
    report = json.loads((tmp_path / "results" / "latest" / "residual.json").read_text())
    engine, misfit, norm = module.engine, 0.0, 0.0
    with torch.no_grad():
        for index, t in enumerate(engine.times):
            views = engine.operator.forward(engine.grid_volume_at(float(t))).double().numpy()
            data = np.asarray(engine.frames[index], dtype=np.float64)
            misfit = misfit + ((views - data) ** 2).sum(axis=(1, 2))
            norm = norm + (data**2).sum(axis=(1, 2))
    assert report["relative_residual"] == pytest.approx(math.sqrt(misfit.sum() / norm.sum()))
    np.testing.assert_allclose(report["relative_residual_views"], np.sqrt(misfit / norm))
    assert report["stage"] == "dynamic" and report["converged"]
    assert "frame_tolerance = 0.05" in report["stopped"]
