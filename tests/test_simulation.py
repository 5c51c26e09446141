import subprocess
import sys

import numpy as np
import pytest
import yaml

from fgat.cli import main
from fgat.io import read_tiff
from fgat.simulation import SimulationConfig, read_centers, simulate, write_simulation

CONFIG = dict(
    system="small",
    depths_um="-12:12:9",
    view_size=48,
    phantom={"kind": "beads", "n_beads": 10, "sigma": 1.0, "min_spacing": 6, "margin": [1, 6, 6]},
    zernike={5: 0.1, 23: 0.05},
    intercepts={1: [0.5, -0.25]},
    slopes={3: [0.0, 0.5]},
    photons=800.0,
    background=50.0,
    read_noise=1.5,
    seed=3,
)


@pytest.fixture(scope="module")
def simulated():
    return simulate(SimulationConfig(**CONFIG))


def test_simulation_round_trip(simulated, tmp_path):
    folder = write_simulation(simulated, tmp_path / "sim")
    for name in ("truth", "psf", "sensor", "views"):
        np.testing.assert_array_equal(
            read_tiff(folder / f"{name}.ome.tif"), getattr(simulated, name)
        )
    np.testing.assert_allclose(read_centers(folder / "centers.csv"), simulated.centers, atol=1e-6)
    params = yaml.safe_load((folder / "params.yaml").read_text())
    assert params["config"]["seed"] == 3 and params["zernike"][5] == pytest.approx(0.1)
    assert params["zernike"][23] == pytest.approx(0.05) and params["intercepts_px"][1] == [
        0.5,
        -0.25,
    ]
    assert params["system"]["name"] == "small" and params["voxel_size_um"] == pytest.approx(
        [3.0, 0.975, 0.975]
    )
    with pytest.raises(ValueError, match="not empty"):
        write_simulation(simulated, folder)
    write_simulation(simulated, folder, overwrite=True)


def test_simulation_is_seeded_and_consistent(simulated):
    again = simulate(SimulationConfig(**CONFIG))
    np.testing.assert_array_equal(again.sensor, simulated.sensor)
    assert simulated.views.shape == (7, 48, 48) and simulated.psf.shape == (7, 9, 65, 65)
    assert (
        simulated.sensor.min() > 0 and abs(np.median(simulated.sensor) - 50) < 5
    )  # offset + read noise


def test_config_errors_name_file_and_field(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text("system: small\nphotonz: 10\n")
    with pytest.raises(ValueError, match="sim.yaml: unknown field\\(s\\) \\['photonz'\\]"):
        SimulationConfig.from_yaml(path)
    path.write_text("phantom: {kind: cubes}\n")
    with pytest.raises(ValueError, match="sim.yaml: phantom.kind must be one of"):
        SimulationConfig.from_yaml(path)
    path.write_text("photons: -5\n")
    with pytest.raises(ValueError, match="photons must be positive"):
        SimulationConfig.from_yaml(path)


def test_cli_simulate_then_deconvolve(tmp_path, capsys):
    config = tmp_path / "sim.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    out = tmp_path / "out"
    assert main(["simulate", "--config", str(config), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [
            "truth.ome.tif",
            "psf.ome.tif",
            "sensor.ome.tif",
            "views.ome.tif",
            "centers.csv",
            "params.yaml",
        ]
    )
    volume = tmp_path / "volume.ome.tif"
    assert (
        main(
            [
                "deconvolve",
                "--measurement",
                str(out / "sensor.ome.tif"),
                "--psf",
                str(out / "psf.ome.tif"),
                "--centers",
                str(out / "centers.csv"),
                "--background",
                "50",
                "--iterations",
                "20",
                "--truth",
                str(out / "truth.ome.tif"),
                "--out",
                str(volume),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    psnr = float(printed.split("PSNR ")[1].split(" dB")[0])
    assert volume.exists() and psnr > 25
    refused = subprocess.run(
        [sys.executable, "-m", "fgat", "simulate", "--config", str(config), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert refused.returncode == 2 and "not empty" in refused.stderr


def test_cli_deconvolve_errors(tmp_path, simulated):
    folder = write_simulation(simulated, tmp_path / "sim")
    (tmp_path / "c.csv").write_text("row,col\n1,2\n")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "fgat",
            "deconvolve",
            "--measurement",
            str(folder / "sensor.ome.tif"),
            "--psf",
            str(folder / "psf.ome.tif"),
            "--centers",
            str(tmp_path / "c.csv"),
            "--out",
            str(tmp_path / "v.tif"),
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2 and "1 centres but" in out.stderr and "7 views" in out.stderr


def test_sampled_aberrations():
    from fgat.simulation import sample_aberrations, true_optics

    optics = sample_aberrations(7, rms=1.5, intercept_range=1.0, slope_range=2.0, seed=4)
    coefficients = np.array(list(optics["zernike"].values()))
    assert list(optics["zernike"]) == list(range(5, 22))
    assert np.linalg.norm(coefficients) == pytest.approx(1.5)  # RMS in waves = 2-norm (Noll)
    assert all(abs(v) <= 1.0 for b in optics["intercepts"].values() for v in b)
    assert (
        all(abs(v) <= 2.0 for s in optics["slopes"].values() for v in s)
        and len(optics["slopes"]) == 7
    )
    raw = sample_aberrations(7, seed=4)["zernike"]
    assert (
        all(-1 <= c <= 1 for c in raw.values()) and raw == sample_aberrations(7, seed=4)["zernike"]
    )
    assert list(sample_aberrations(7, terms=7)["zernike"]) == list(
        range(5, 12)
    )  # Fig. S8's subspace
    config = SimulationConfig(
        **{**CONFIG, "aberrations": {"terms": 7, "amplitude": 0.2}, "zernike": {5: 0.5}}
    )
    assert true_optics(config, 7)["zernike"][5] == 0.5  # explicit entries take precedence
    with pytest.raises(ValueError, match="aberrations: unknown field"):
        SimulationConfig(**{**CONFIG, "aberrations": {"rsm": 1.0}}).validate()
