"""The reproduction scripts' MLflow readers and figures, on small synthetic MLflow stores."""

import csv

import mlflow
import numpy as np
import pytest
from mlflow.entities import Metric

from fgat.app.callbacks.mlflow import FINGERPRINT, finished_fingerprints
from fgat.app.recipes import figS9_summary, figS10, optics
from fgat.optics.zernike import wavefront_map, zernike


@pytest.fixture
def sweep_store(tmp_path, monkeypatch):
    """A figS9-style experiment: 2 RMS levels x 3 seeds, a repeated trial, a failed run; metric
    values drawn at random and returned for an independent check."""
    monkeypatch.chdir(tmp_path)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    mlflow.set_tracking_uri(uri)
    mlflow.set_experiment("sweep")
    rng = np.random.default_rng(0)
    expected = {}
    for rms in (0.5, 1.0):
        for seed in (0, 1, 2):
            for attempt in range(2 if (rms, seed) == (1.0, 0) else 1):
                values = {
                    "zernike/residual_normalized": rng.uniform(0, 0.3),
                    "val/psnr_volume": rng.uniform(30, 40),
                    "val/ssim_volume": rng.uniform(0.8, 1),
                    "val/ssim_mip_xy": rng.uniform(0.8, 1),
                }
                with mlflow.start_run(run_name=f"rms{rms}-seed{seed}") as run:
                    mlflow.log_params(
                        {
                            "simulation/aberrations/rms": rms,
                            "simulation/aberrations/seed": seed,
                            "simulation/aberrations/terms": 17,
                        }
                    )
                    history = [
                        Metric(f"zernike_gt/c{j}", 0.1 * rms * (j % 3 - 1), 0, 0)
                        for j in range(5, 22)
                    ]
                    history += [
                        Metric(f"zernike/c{j}", 0.1 * rms * (j % 3 - 1) * step / 200, 0, step)
                        for j in range(5, 22)
                        for step in (100, 150, 200)
                    ]
                    history += [Metric(name, value, 0, 200) for name, value in values.items()]
                    mlflow.MlflowClient().log_batch(run.info.run_id, metrics=history)
                expected[(rms, seed)] = values  # the latest attempt counts
    with mlflow.start_run(run_name="rms2.0-seed0") as failed:
        mlflow.log_params({"simulation/aberrations/rms": 2.0, "simulation/aberrations/seed": 0})
    mlflow.MlflowClient().set_terminated(failed.info.run_id, status="FAILED")
    return uri, expected


@pytest.mark.slow
def test_figS9_summary_reads_the_sweep(sweep_store, tmp_path):
    uri, expected = sweep_store
    script = figS9_summary
    script.main(["--experiment", "sweep", "--out", str(tmp_path / "out")])
    with open(tmp_path / "out" / "summary.csv") as handle:
        summary = list(csv.DictReader(handle))
    assert [float(row["rms"]) for row in summary] == [
        0.5,
        1.0,
    ]  # the failed RMS 2.0 run is left out
    for row in summary:
        rms = float(row["rms"])
        assert int(row["trials"]) == 3
        for key, metric in script.METRICS.items():
            values = np.array([expected[(rms, seed)][metric] for seed in (0, 1, 2)])
            assert float(row[f"{key}_mean"]) == pytest.approx(values.mean(), rel=1e-6)
            assert float(row[f"{key}_sd"]) == pytest.approx(values.std(ddof=1), rel=1e-6)
    for name in ("runs.csv", "figS9_metrics.png", "figS9_wavefronts.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    records = script.sweep_runs("sweep", uri)
    assert len(records) == 6 and records[0]["indices"] == list(range(5, 22))
    assert records[0]["estimated"] == pytest.approx(
        records[0]["truth"]
    )  # final estimate = truth here
    client = mlflow.MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("sweep").experiment_id])
    for index, run in enumerate(runs):  # the failed run gets a fingerprint too: it does not count
        client.set_tag(run.info.run_id, FINGERPRINT, f"fp{index}")
    finished = {f"fp{index}" for index, run in enumerate(runs) if run.info.status == "FINISHED"}
    assert len(finished) == 7 and finished_fingerprints(uri, "sweep") == finished
    assert finished_fingerprints(uri, "no such experiment") == set()


@pytest.mark.slow
def test_figS10_trajectories(sweep_store, tmp_path):
    script = figS10
    script.main(["--experiment", "sweep", "--run", "rms1.0-seed0", "--out", str(tmp_path / "out")])
    with open(tmp_path / "out" / "trajectories.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 17 * 3
    first = [row for row in rows if row["j"] == "5"]
    assert [int(row["step"]) for row in first] == [100, 150, 200]
    assert float(first[-1]["estimate"]) == pytest.approx(
        float(first[-1]["truth"])
    )  # 0.1 * (5 % 3 - 1)
    assert float(first[0]["estimate"]) == pytest.approx(0.1 * 0.5)
    assert (tmp_path / "out" / "figS10.png").stat().st_size > 0
    with pytest.raises(SystemExit, match="no finished run"):
        script.main(["--experiment", "sweep", "--run", "rms2.0-seed0"])


def test_wavefront_map_is_the_weighted_zernike_sum():
    import torch

    size = 32
    waves = wavefront_map([5, 8], [0.3, -0.2], size).numpy()
    axis = (np.arange(size) + 0.5) / size * 2 - 1
    y, x = np.meshgrid(axis, axis, indexing="ij")
    rho, theta = np.hypot(y, x), np.arctan2(y, x)
    inside = rho <= 1
    expected = (
        0.3 * zernike(5, torch.from_numpy(rho), torch.from_numpy(theta)).numpy()
        - 0.2 * zernike(8, torch.from_numpy(rho), torch.from_numpy(theta)).numpy()
    )
    np.testing.assert_allclose(waves[inside], expected[inside], atol=1e-12)
    assert np.isnan(waves[~inside]).all()
    # RMS over the pupil of orthonormal terms = the coefficient norm (the "RMS" of Fig. S9)
    assert np.sqrt(
        np.nanmean(wavefront_map([5, 8], [0.3, -0.2], 512).numpy() ** 2)
    ) == pytest.approx(np.hypot(0.3, 0.2), rel=2e-2)
    with pytest.raises(ValueError, match="2 coefficients for 1 Zernike indices"):
        wavefront_map([5], [0.1, 0.2])


@pytest.mark.slow
def test_optics_recipe_summary_pairs_4dgat_with_3dgat(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    mlflow.set_tracking_uri(uri)
    mlflow.set_experiment("figS7_quick")
    script = optics
    logged = {}
    for method, offset in (("4DGAT", 5.0), ("3DGAT", 0.0)):
        metrics = {metric: 30.0 + offset + k for k, metric in enumerate(script.SCORES.values())}
        metrics.update(
            {f"{metric}_shb": 28.0 + k for k, metric in enumerate(script.SCORES.values())}
        )
        if method == "4DGAT":
            metrics.update(
                {metric: 0.01 * (k + 1) for k, metric in enumerate(script.OPTICS.values())}
            )
            metrics.update({f"psf/error_view{v}": 0.1 * v for v in range(7)})
            metrics.update({f"psf/error_initial_view{v}": 1.0 + v for v in range(7)})
        with mlflow.start_run(run_name=f"{method}-seed3"):
            mlflow.log_metrics(metrics)
        logged[method] = metrics
    rows, views = script.summary_rows(script.latest_runs("figS7_quick", uri), [3])
    (row,) = rows
    assert row["psnr_4dgat"] == 35.0 and row["psnr_3dgat"] == 30.0 and row["psnr_shb"] == 28.0
    assert (row["psnr_registered_4dgat"], row["psnr_registered_3dgat"]) == (36.0, 31.0)
    assert row["psnr_registered_shb"] == 29.0
    assert row["ssim_xy_4dgat"] == logged["4DGAT"]["val/ssim_mip_xy"]
    assert row["sigma"] == 0.01 and row["psf_error_ideal"] == pytest.approx(0.07)
    assert [v["view"] for v in views] == list(range(7)) and views[2]["psf_error_ideal"] == 3.0
    with pytest.raises(SystemExit, match="no finished MLflow run named 4DGAT-seed4, 3DGAT-seed4"):
        script.summary_rows(script.latest_runs("figS7_quick", uri), [4])
    assert script.latest_runs("not run yet", uri) == {}  # nothing to skip: every trial is fitted
