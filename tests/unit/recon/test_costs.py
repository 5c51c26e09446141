"""The cost estimate printed before a deconvolution or a fit: its counting, its calibration and
what the commands print."""

import time

import numpy as np
import pytest
import torch

import fgat.recon.costs as costs
from fgat._core.resources import Affine, format_seconds, process_memory
from fgat.recon.costs import (
    CostEstimate,
    deconvolution_cost,
    deconvolution_memory,
    optics_events,
    plane_seconds,
)
from fgat.recon.estimation import OpticsEstimation


@pytest.mark.parametrize(
    "start,every,first,last",
    [(200, 50, 0, 2000), (50, 25, 0, 800), (0, 1, 3, 10), (40, 40, 90, 95)],
)
def test_optics_events_count_the_schedules_events(start, every, first, last):
    schedule = OpticsEstimation(estimate="zernike", start=start, every=every)
    expected = sum(schedule.due(k) for k in range(first + 1, last + 1))
    assert optics_events(start, every, first, last) == expected


def test_plane_seconds_recovers_a_known_line(monkeypatch):
    """A fake clock advancing ``0.5 + 0.25 k`` seconds per call on ``k`` planes."""
    clock = [0.0]
    monkeypatch.setattr(time, "perf_counter", lambda: clock[0])

    def run(k):
        clock[0] += 0.5 + 0.25 * k

    line = plane_seconds(run, (1, 5))
    assert (line.fixed, line.per_unit) == pytest.approx((0.5, 0.25))
    assert line(101) == pytest.approx(25.75)
    flat = plane_seconds(
        lambda k: clock.__setitem__(0, clock[0] + (2.0 if k == 1 else 1.0)), (1, 3)
    )
    assert flat == Affine(2.0, 0.0)  # noise making the larger size faster: no negative slope


def test_estimate_lines_and_params():
    cost = CostEstimate(
        "static fit",
        {"setup": 12.0, "steps": 8000.0, "optics events": 0.0},
        {"setup": 2_000_000_000, "steps": 3_500_000_000},
        ["2000 steps x 4.0 s"],
        ["fewer steps (trainer.max_steps)"],
        "cpu",
    )
    lines = cost.lines()
    assert lines[0] == (
        "estimated static fit: about 2.2 h and 3.5 GB peak host memory (largest: steps) on cpu"
    )
    assert "  optics events: 0.0 s" not in lines and "  steps: 2.2 h" in lines
    assert lines[-1] == "  to reduce: fewer steps (trainer.max_steps)"
    params = cost.params()
    assert params["cost/seconds"] == 8012.0 and params["cost/peak_bytes"] == 3_500_000_000
    assert params["cost/seconds_optics_events"] == 0.0 and params["cost/bytes_setup"] == 2e9
    assert [format_seconds(t) for t in (0.031, 0.25, 4.2, 95, 8280)] == [
        "31 ms",
        "250 ms",
        "4.2 s",
        "1.6 min",
        "2.3 h",
    ]


def test_process_memory_sees_a_new_allocation():
    before, _ = process_memory()
    block = np.ones(50_000_000 // 8)  # 50 MB, touched
    after, peak = process_memory()
    assert after - before > 40e6 and peak > after - 1e6  # ru_maxrss is sampled in pages
    del block


def test_deconvolution_cost_counts_iterations_and_the_memory_bound():
    from fgat.optics.acquisition import MeasuredOperator

    psf = torch.rand(3, 8, 9, 9)
    operator = MeasuredOperator(psf, (24, 24), 2)
    before, _ = process_memory()
    cost = deconvolution_cost(
        operator, 40, setup_seconds=1.5, options={"iterations": "--iterations"}
    )
    after, _ = process_memory()
    assert cost.seconds["setup"] == 1.5
    bound = deconvolution_memory(psf.shape, (8, 24, 24), guard_px=2)
    assert before <= cost.peak_bytes - bound <= after  # the process's size, then the bound
    assert "fewer iterations (--iterations)" in cost.levers
    # the calibrated projection against the same projection timed apart (the fastest of ten:
    # the estimate is that of the machine to itself)
    volume = torch.rand(operator.volume_shape)
    times = []
    for _ in range(10):
        start = time.perf_counter()
        operator.adjoint(operator.forward(volume))
        times.append(time.perf_counter() - start)
    assert 40 * min(times) / 3 < cost.seconds["iterations"] < 3 * 40 * min(times)


def test_deconvolve_prints_its_estimate_before_iterating(tmp_path, capsys, monkeypatch):
    """The estimate's lines come first, with the iterations counted from --iterations."""
    from fgat.app.cli import main
    from fgat.sim.simulation import SimulationConfig, simulate, write_simulation

    config = SimulationConfig(system="small", depths_um="-8:8:5", view_size=32, seed=1)
    folder = write_simulation(simulate(config), tmp_path / "sim")
    order = []
    real = costs.deconvolution_cost
    monkeypatch.setattr(
        costs,
        "deconvolution_cost",
        lambda *a, **k: order.append("estimate") or real(*a, **k),
    )
    command = ["deconvolve", "--measurement", str(folder / "sensor.ome.tif")]
    command += ["--psf", str(folder / "psf.ome.tif"), "--centers", str(folder / "centers.csv")]
    assert main([*command, "--iterations", "7", "--out", str(tmp_path / "v.ome.tif")]) == 0
    printed = capsys.readouterr().out
    assert order == ["estimate"]
    assert "estimated deconvolution: about" in printed and "peak host memory" in printed
    assert "7 iterations x" in printed and "--iterations, or --tol" in printed
    assert printed.index("estimated deconvolution") < printed.index("volume (5, ")


@pytest.mark.slow
def test_fit_prints_and_logs_its_estimate_with_the_optics_parts(tmp_path, monkeypatch, caplog):
    """A 4DGAT fit: the estimate (steps, JPGM events, standard errors) is printed before the
    first step and logged as MLflow params."""
    from fgat.app.lightning_cli import run
    from tests.integration.test_static import config_file, logged_run

    monkeypatch.chdir(tmp_path)
    seen = {}
    real = costs.static_fit_cost

    def spy(engine, total, setup):
        seen.update(steps_done=engine.steps_done, total=total)
        return real(engine, total, setup)

    monkeypatch.setattr(costs, "static_fit_cost", spy)
    optics = {"estimate": "zernike", "start": 10, "every": 10, "steps": 2}
    caplog.set_level("INFO")
    run(["fit", "--config", str(config_file(tmp_path, steps=20, optics=optics))])
    assert seen == {"steps_done": 0, "total": 20}
    assert "fgat: estimated static fit: about" in caplog.text
    assert "fgat:   1 JPGM events x 2 updates x" in caplog.text  # after step 20 only
    assert "optics fixed (model.optics.estimate = none)" in caplog.text
    _, run_info = logged_run(tmp_path)
    params = run_info.data.params
    for part in ("seconds", "peak_bytes", "seconds_steps", "seconds_optics_events"):
        assert float(params[f"cost/{part}"]) > 0
    assert float(params["cost/bytes_standard_errors"]) > float(params["cost/bytes_steps"]) > 0


@pytest.mark.slow
def test_dynamic_fit_prints_its_estimate(tmp_path, caplog):
    """The dynamic stage: the frame steps left counted from the epochs (no max_steps)."""
    import lightning.pytorch as pl

    from fgat.app.datamodules import PhantomDataModule
    from fgat.app.lightning_cli import FitCost
    from fgat.app.modules import DynamicModule, StaticModule
    from tests.integration.test_dynamic_stage import DYNAMIC, SIMULATION, STATIC, trainer

    pl.seed_everything(0)
    static = trainer(tmp_path / "static", max_steps=20, limit_val_batches=0)
    static.fit(StaticModule(**STATIC), PhantomDataModule(SIMULATION))
    static_checkpoint = tmp_path / "static.ckpt"
    static.save_checkpoint(static_checkpoint)
    caplog.set_level("INFO")
    module = DynamicModule(str(static_checkpoint), **DYNAMIC)
    trainer(tmp_path, max_epochs=2, limit_val_batches=0, callbacks=[FitCost()]).fit(
        module, PhantomDataModule(SIMULATION)
    )
    frames = module.scene.n_frames
    assert "fgat: estimated dynamic fit: about" in caplog.text
    assert f"fgat:   {2 * frames} frame steps x" in caplog.text
