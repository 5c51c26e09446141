"""The Note S5 experiments (Tables S2-S5) of fgat.app.crossinfo_tables and ``fgat analyze
crossinfo``, on a tiny scene: the small system, 3 planes, 24 x 24 views, 10-px crops computed by
the matrix Fourier transform."""

import copy
import json
import math

import numpy as np
import pytest
import torch
import yaml

from fgat.app.cli import main
from fgat.app.crossinfo_tables import (
    PARAMETERS,
    REPORT_FILES,
    CrossInfoConfig,
    analysis_scene,
    leakage_table,
    leakage_test,
    modal_table,
    pixel_grid_fraction,
    predict,
    profile_table,
    refit,
    repeatability,
    run_scene,
    shift_cases,
)
from fgat.io.images import volume_entries, write_tiff
from fgat.optics.crossinfo import cross_information
from fgat.optics.systems import load_system
from fgat.recon.optics_report import optics_metrics

SCENE = {
    "system": "small",
    "depths_um": "-6:6:3",
    "view_size": 24,
    "phantom": {"kind": "beads", "n_beads": 6, "sigma": 1.0, "margin": [0, 2, 2]},
    "aberrations": {"amplitude": 0.05, "intercept_range": 0.5, "slope_range": 0.5},
    "seed": 0,
}
CONFIG = {"scene": SCENE, "crop_radius_px": 10, "method": "mft", "refits": 2, "max_iterations": 4}


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny tensors: one thread is as fast as two, and does not fight other work for the cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def point(one_thread):
    """The tiny scene's JPGM at its true optics, its volume and their cross-information."""
    config = CrossInfoConfig(**CONFIG)
    jpgm, volume = analysis_scene(
        config.simulation(), crop_radius_px=config.crop_radius_px, method=config.method
    )
    return jpgm, volume, cross_information(jpgm, volume)


def test_modal_tables_rank_unit_profiles(point):
    _, _, info = point
    for block, eta in (("b", info.eta_b), ("s", info.eta_s)):
        table = modal_table(info, block)
        values = [row[f"eta_{block}"] for row in table.rows]
        assert math.isclose(sum(v * v for v in values), 1.0, rel_tol=1e-12)  # Eq. S48
        assert values == sorted(values, reverse=True)
        assert [row["rank"] for row in table.rows] == list(range(1, 18))
        assert modal_table(info, block, top=5).rows == table.rows[:5]
        row = next(row for row in table.rows if row["noll"] == 11)
        assert (row["n"], row["m"], row["family"]) == (4, 0, "Spherical")
        assert table.summary[f"eta_{block}_11"] == row[f"eta_{block}"]
        assert table.summary["rank_11"] == row["rank"]
        assert np.allclose(values, np.sort(eta.numpy())[::-1])
    ratio = torch.linalg.matrix_norm(info.C_s) / torch.linalg.matrix_norm(info.C_b)
    assert table.summary["frobenius_ratio_s_over_b"] == pytest.approx(float(ratio))
    full = profile_table(info)
    assert [row["noll"] for row in full.rows] == list(range(5, 22))
    assert "| rank | noll | n | m | family | eta_b |" in modal_table(info, "b").markdown()


def test_shift_cases_follow_table_s4():
    cases = list(shift_cases(7, 0.3, 2.0, seed=0).values())
    intercepts, slopes = cases[0].reshape(2, 7, 2)
    assert torch.all(intercepts[:, 1] == 0.3) and not intercepts[:, 0].any() and not slopes.any()
    intercepts, slopes = cases[1].reshape(2, 7, 2)
    assert torch.all(slopes[:, 0] == 0.3) and not slopes[:, 1].any() and not intercepts.any()
    assert float(cases[0].norm()) == pytest.approx(0.7937, abs=1e-4)  # the paper's norm
    assert float(cases[2].norm()) == pytest.approx(1.5875, abs=1e-4)
    assert torch.equal(
        shift_cases(7, seed=3)["random dTheta_G"], shift_cases(7, seed=3)["random dTheta_G"]
    )


def test_small_shift_leakage_matches_the_leakage_map(point):
    """Eq. S51 is the first-order change of the refitted Zernike terms: for a small injected
    shift the refit moves them by -A^-1 C dTheta_G in size and direction."""
    jpgm, volume, info = point
    cases = leakage_test(jpgm, volume, info, shift_px=0.02, tolerance=1e-4)
    for case in cases:
        assert 0.9 < case.ratio < 1.1, case.label
        assert case.cosine > 0.95, case.label
        assert case.converged
    table = leakage_table(cases)
    assert [row["case"] for row in table.rows] == [case.label for case in cases]
    assert table.summary["cosine_min"] == min(case.cosine for case in cases)


def test_joint_refit_returns_to_the_optics_from_a_perturbed_start(point):
    jpgm, volume, info = point
    with torch.no_grad():
        clean = predict(jpgm, volume)
    start = {
        "zernike_coefficients": jpgm.zernike_coefficients + 0.005,
        "intercepts": jpgm.intercepts - 0.05,
    }
    fit = refit(jpgm, volume, clean, info.hessian, overrides=start, tolerance=1e-6)
    for name in PARAMETERS:
        torch.testing.assert_close(
            fit.parameters[name], getattr(jpgm, name).detach(), atol=1e-5, rtol=0
        )
    with pytest.raises(ValueError, match="curvature must be 17 x 17"):
        refit(jpgm, volume, clean, info.hessian, names=("zernike_coefficients",))


def test_pixel_grid_fraction_finds_crops_on_the_kinks(point):
    jpgm, _, _ = point
    assert pixel_grid_fraction(jpgm) < 0.1  # random true shifts
    aligned = copy.deepcopy(jpgm)
    with torch.no_grad():
        aligned.slopes.zero_()
        aligned.intercepts.copy_(aligned.centers.round() - aligned.centers)
    assert pixel_grid_fraction(aligned) == 1.0


def test_noisy_refits_spread_as_the_inverse_hessian_predicts(point):
    jpgm, volume, info = point
    result = repeatability(jpgm, volume, info, refits=12, noise_fraction=0.01, seed=0)
    assert result.pupil.shape == (12, 17) and result.geometry.shape == (12, 28)
    ratio = result.empirical_sd / result.predicted_sd
    assert 0.6 < np.median(ratio) < 1.6  # 12 draws: each s.d. within about +/- 25 %
    norms = result.norms()
    assert 0.6 < norms["pupil_norm_mean_waves"] / norms["pupil_norm_predicted_rms_waves"] < 1.6
    table = result.table(top=5)
    spreads = [row["empirical_sd_waves"] for row in table.rows]
    assert len(spreads) == 5 and spreads == sorted(spreads, reverse=True)
    predicted = info.standard_errors(result.sigma, "joint")["zernike"]
    for row in table.rows:
        assert row["predicted_sd_waves"] == pytest.approx(float(predicted[row["noll"] - 5]))
    assert table.summary["refits_converged"] == 12


def test_run_scene_rebuilds_a_fit_results_folder(point, tmp_path):
    jpgm, volume, _ = point
    depths = jpgm.depths_um.tolist()
    (tmp_path / "optics.yaml").write_text(yaml.safe_dump(optics_metrics(jpgm)))
    with torch.no_grad():
        write_tiff(tmp_path / "psf.ome.tif", jpgm().float().numpy(), axes="CZYX")
    write_tiff(
        tmp_path / "volume.ome.tif",
        volume.float().numpy(),
        axes="ZYX",
        metadata=volume_entries("up", depths),
    )
    rebuilt, read, operator = run_scene(tmp_path, load_system("small"), method="mft")
    assert operator is None and rebuilt.radius == 10
    torch.testing.assert_close(read, volume.float().double())
    for name in PARAMETERS:
        torch.testing.assert_close(getattr(rebuilt, name), getattr(jpgm, name), atol=1e-7, rtol=0)
    with torch.no_grad():
        write_tiff(tmp_path / "psf.ome.tif", jpgm().flip(-1).float().numpy(), axes="CZYX")
    with pytest.raises(ValueError, match="differs from psf.ome.tif"):
        run_scene(tmp_path, load_system("small"), method="mft")


def test_cli_writes_tables_s2_s5_and_refuses_a_full_folder(tmp_path, capsys):
    config = tmp_path / "crossinfo.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    out = tmp_path / "out"
    assert main(["analyze", "crossinfo", "--config", str(config), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(REPORT_FILES)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["repeatability"]["refits"] == 2
    assert 0 <= summary["crop_coordinates_on_pixel_grid"] < 0.1
    assert len(summary["leakage"]["cases"]) == 3
    assert "Table S4" in (out / "tableS4_leakage.md").read_text()
    assert (
        (out / "tableS2_intercept_profile.csv")
        .read_text()
        .startswith("rank,noll,n,m,family,eta_b\n")
    )
    printed = capsys.readouterr().out
    assert "||C_s||_F / ||C_b||_F = " in printed and "leakage dB_x = 0.3 px" in printed
    assert main(["analyze", "crossinfo", "--config", str(config), "--out", str(out)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert (
        line
        == f"fgat analyze: error: --out {out}: not empty; choose another folder or pass --overwrite"
    )


BAD = [
    ({"refits": 1}, "refits must be"),
    ({"typo": 1}, "unknown field(s) ['typo']"),
    ({"scene": {**SCENE, "photons": 10}}, "scene: unknown field(s) ['photons']"),
    (
        {"scene": {**SCENE, "phantom": {"kind": "beads", "n_bead": 3}}},
        "unknown option(s) ['n_bead']",
    ),
    ({"method": "fft"}, "method must be one of"),
    ({"noise_fraction": -0.1}, "noise_fraction must be"),
]


@pytest.mark.parametrize("change,message", BAD)
def test_cli_refuses_a_bad_config_with_one_line(change, message, tmp_path, capsys):
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump({**CONFIG, **change}))
    out = tmp_path / "out"
    assert main(["analyze", "crossinfo", "--config", str(config), "--out", str(out)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"fgat analyze: error: --config {config}: ") and message in line
    assert not out.exists()


def test_cli_refuses_missing_inputs_with_one_line(tmp_path, capsys):
    config = tmp_path / "crossinfo.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    out = str(tmp_path / "out")
    assert main(["analyze", "crossinfo", "--config", "nowhere.yaml", "--out", out]) == 2
    assert capsys.readouterr().err.strip() == (
        "fgat analyze: error: --config nowhere.yaml does not exist"
    )
    argv = ["analyze", "crossinfo", "--config", str(config), "--out", out]
    assert main([*argv, "--run", str(tmp_path)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"fgat analyze: error: --run {tmp_path}: no optics.yaml, psf.ome.tif")
    assert main([*argv, "--centers", "centers.csv"]) == 2
    assert capsys.readouterr().err.strip() == (
        "fgat analyze: error: --centers needs --run (the centres of a fit's lenslets)"
    )
    with pytest.raises(SystemExit) as exit_:
        main(["analyze", "crossinfo", "--out", out])
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "fgat analyze crossinfo: error: the following arguments are required: --config"
    )
