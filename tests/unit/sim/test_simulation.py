import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

from fgat._core.conventions import DEPTH_AXES, VIEW_ORDER, orient_volume
from fgat.app.cli import main
from fgat.instrument.centres import read_centers
from fgat.io.images import read_tiff, volume_metadata
from fgat.sim.simulation import OUTPUT_FILES, SimulationConfig, simulate, write_simulation

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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_cli_deconvolve_holdout_stops_before_the_noise_is_fitted(tmp_path, simulated, capsys):
    folder = write_simulation(simulated, tmp_path / "sim")
    command = ["deconvolve", "--measurement", str(folder / "sensor.ome.tif")]
    command += ["--psf", str(folder / "psf.ome.tif"), "--centers", str(folder / "centers.csv")]
    command += [
        "--background",
        "50",
        "--iterations",
        "200",
        "--truth",
        str(folder / "truth.ome.tif"),
    ]
    scores = {}
    for name, extra in (("all", []), ("holdout", ["--holdout", "0.1"])):
        assert main([*command, *extra, "--out", str(tmp_path / f"{name}.ome.tif")]) == 0
        scores[name] = float(capsys.readouterr().out.split("PSNR ")[1].split(" dB")[0])
    assert scores["holdout"] > scores["all"] + 1, scores
    with pytest.raises(SystemExit):
        main([*command, "--holdout", "0.8", "--out", str(tmp_path / "bad.ome.tif")])
    assert "--holdout: must be a finite number > 0 <= 0.5, got '0.8'" in capsys.readouterr().err


@pytest.mark.slow
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
    assert out.returncode == 2 and "1 lenslet centres but" in out.stderr and "7 views" in out.stderr


@pytest.mark.slow
def test_deconvolved_volume_records_depth_axis_depths_and_view_order(tmp_path, simulated):
    folder = write_simulation(simulated, tmp_path / "sim")
    depths = [-12.0, -9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0, 12.0]  # CONFIG's -12:12:9
    for name in ("truth", "psf"):  # simulate records the depths of its planes, and what it is
        assert volume_metadata(folder / f"{name}.ome.tif")["depths_um"] == depths
        assert volume_metadata(folder / f"{name}.ome.tif")["content"] == name.replace(
            "truth", "volume"
        )
    volumes, recorded = {}, {}
    for axis in ("up", "down"):
        out = tmp_path / f"{axis}.ome.tif"
        command = ["deconvolve", "--measurement", str(folder / "sensor.ome.tif")]
        command += ["--psf", str(folder / "psf.ome.tif"), "--centers", str(folder / "centers.csv")]
        command += ["--background", "50", "--iterations", "5", "--view-size", "48"]
        command += ["--depth-axis", axis]
        done = subprocess.run(
            [sys.executable, "-m", "fgat", *command, "--out", str(out)],
            capture_output=True,
            text=True,
        )
        assert done.returncode == 0, done.stderr
        volumes[axis], recorded[axis] = read_tiff(out), volume_metadata(out)
    assert recorded["up"] == {
        "content": "volume",
        "depth_axis": "up",
        "depth_axis_convention": DEPTH_AXES["up"],
        "depths_um": depths,
        "view_order": VIEW_ORDER,
    }
    assert recorded["down"] == {
        "content": "volume",
        "depth_axis": "down",
        "depth_axis_convention": DEPTH_AXES["down"],
        "depths_um": depths[::-1],
        "view_order": VIEW_ORDER,
    }
    assert volumes["up"].shape == (9, 48, 48)
    scale = volumes["up"].max()
    np.testing.assert_allclose(
        volumes["down"] / scale, orient_volume(volumes["up"], "down") / scale, atol=1e-5
    )
    assert not np.allclose(volumes["down"], volumes["up"], atol=1e-3 * scale)  # not Z-symmetric


@pytest.mark.slow
def test_lightning_volume_series_records_the_scene_depth_axis(tmp_path, simulated):
    from types import SimpleNamespace

    from fgat.app.callbacks.artifacts import VolumeSeriesWriter
    from fgat.app.datamodules.flfm import FLFMDataModule
    from fgat.instrument.measurement import measurement_model
    from fgat.optics.systems import load_system

    folder = write_simulation(simulated, tmp_path / "sim")
    scene = FLFMDataModule(
        str(folder / "sensor.ome.tif"),
        centers=str(folder / "centers.csv"),
        psf=str(folder / "psf.ome.tif"),
        depth_axis="down",
    ).make_scene()
    depths = (12.0, 9.0, 6.0, 3.0, 0.0, -3.0, -6.0, -9.0, -12.0)
    assert scene.depth_axis == "down" and scene.depths_um == depths
    np.testing.assert_array_equal(scene.psf, orient_volume(simulated.psf, "down"))
    out = tmp_path / "volumes.ome.tif"
    series = np.arange(2 * 9, dtype=np.float32).reshape(2, 9, 1, 1) * np.ones((1, 1, 4, 4))
    items = [{"index": k, "time": float(k), "volume": series[k]} for k in range(2)]
    writer = VolumeSeriesWriter(out)
    trainer = SimpleNamespace(is_global_zero=True)
    module = SimpleNamespace(scene=scene, print=lambda *args: None)
    for index, item in enumerate(items):  # volume by volume, as the predict loop hands them
        writer.write_on_batch_end(trainer, module, item, None, None, index)
    writer.write_on_epoch_end(trainer, module, [items], None)
    assert volume_metadata(out)["depth_axis"] == "down"
    assert volume_metadata(out)["depths_um"] == list(depths)
    np.testing.assert_array_equal(read_tiff(out), series)
    model = measurement_model(  # a system's PSF: the depths as given, turned with the volume
        centers=str(folder / "centers.csv"),
        system=load_system("small"),
        depths_um=[-3.0, 0.0, 3.0],
        depth_axis="down",
    )
    assert model.depths_um == (3.0, 0.0, -3.0) and model.psf.shape[1] == 3


def test_sampled_aberrations():
    from fgat.sim.simulation import sample_aberrations, true_optics

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


# ---------------------------------------------------------------- realistic measurements
SMALL = dict(
    system="small",
    depths_um="-12:12:5",
    view_size=32,
    phantom={"kind": "beads", "n_beads": 6, "sigma": 1.0, "margin": [1, 4, 4]},
    photons=None,
    seed=5,
)


@pytest.mark.slow
def test_no_imperfections_is_the_ideal_simulation(simulated, tmp_path):
    """``imperfections: null`` (or no key) is today's simulation bit for bit: the same as the
    chain of public pieces it has always been."""
    from fgat.optics.operator import FLFMOperator
    from fgat.optics.systems import load_system
    from fgat.sim.phantoms import noisy_measurement
    from fgat.sim.simulation import make_phantom, true_psf_model

    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump({**CONFIG, "imperfections": None}))
    config = SimulationConfig.from_yaml(path)
    assert config.imperfections is None and config == SimulationConfig(**CONFIG)
    path.write_text(yaml.safe_dump({**SMALL, "imperfections": None}))
    explicit, implicit = (
        simulate(SimulationConfig.from_yaml(path)),
        simulate(SimulationConfig(**SMALL)),
    )
    for name in ("truth", "psf", "sensor", "views", "centers"):
        np.testing.assert_array_equal(getattr(explicit, name), getattr(implicit, name))
    system = load_system("small")
    depths = list(np.linspace(-12, 12, 9))
    shape = (9, 48, 48)
    with torch.no_grad():
        psf = true_psf_model(config, system, depths)()
    truth = make_phantom(config, shape)
    clean = FLFMOperator.sensor(
        FLFMOperator(psf, shape).forward(torch.from_numpy(truth).double()).clamp(min=0),
        system.lenslet_centers_px(),
        system.sensor_shape,
    ).numpy()
    sensor = noisy_measurement(clean, photons=800.0, background=50.0, read_noise=1.5, seed=3)
    np.testing.assert_array_equal(simulated.truth, truth)
    np.testing.assert_array_equal(simulated.psf, psf.float().numpy())
    np.testing.assert_array_equal(simulated.sensor, sensor)
    np.testing.assert_array_equal(simulated.centers, system.lenslet_centers_px())
    for result in (simulated, explicit):
        assert result.imperfections is None and result.dark is None and result.flat is None
    folder = write_simulation(explicit, tmp_path / "out")
    assert sorted(p.name for p in folder.iterdir()) == sorted(OUTPUT_FILES)


def test_rotated_and_jittered_centres(tmp_path):
    from fgat.instrument.lattice import HexLattice
    from fgat.optics.operator import FLFMOperator
    from fgat.optics.spec import OpticsSpec
    from fgat.optics.systems import load_system

    system = load_system("small37")
    nominal = system.lenslet_centers_px()
    config = SimulationConfig(
        **{
            **SMALL,
            "system": "small37",
            "depths_um": "-2:2:3",
            "imperfections": {"mla_rotation_deg": 0.4, "center_jitter_px": 2.0},
        }
    )
    result = simulate(config)
    folder = write_simulation(result, tmp_path / "sim")
    centers = read_centers(folder / "centers.csv")
    np.testing.assert_allclose(centers, result.centers, atol=1e-6)
    rotated = HexLattice(tuple(nominal[0]), system.pitch_px, 0.4).centers(37)
    np.testing.assert_allclose(rotated, nominal, atol=1.1)  # 0.4 degrees at 3 pitches: 1.05 px
    jitter = centers - rotated
    assert np.abs(jitter).max() <= 2.0 + 1e-6 and jitter.std() > 0.8  # uniform in [-2, 2]
    params = yaml.safe_load((folder / "params.yaml").read_text())
    np.testing.assert_allclose(params["imperfections"]["nominal_centers_px"], nominal)
    np.testing.assert_allclose(params["centers_px"], centers, atol=1e-9)
    # the PSF is the JPGM's on the true centres, and the views are cut around them
    psf = OpticsSpec(system, (-2.0, 0.0, 2.0), result.centers).psf(dtype=torch.float64)
    np.testing.assert_allclose(result.psf, psf, atol=1e-7)
    np.testing.assert_array_equal(
        result.views,
        FLFMOperator.views_from_sensor(torch.from_numpy(result.sensor), centers, 32).numpy(),
    )
    drawn = config.imperfections.draw(system, 5)  # seeded
    np.testing.assert_array_equal(drawn.centers, result.centers)
    assert not np.allclose(config.imperfections.draw(system, 6).centers, centers)


def test_gains_multiply_each_view():
    gains = SimulationConfig(**{**SMALL, "imperfections": {"gains": [0.7, 1.0]}})
    ones = SimulationConfig(**{**SMALL, "imperfections": {"gains": [1.0] * 7}})
    with_gains, without = simulate(gains), simulate(ones)
    drawn = with_gains.imperfections.gains
    assert drawn[0] == 1.0 and ((drawn >= 0.7) & (drawn <= 1.0)).all() and drawn.std() > 0.03
    flux = with_gains.views.sum(axis=(1, 2), dtype=np.float64)
    reference = without.views.sum(axis=(1, 2), dtype=np.float64)
    assert (reference > 0).all()
    np.testing.assert_allclose(flux / reference, drawn, rtol=1e-6)
    explicit = SimulationConfig(**{**SMALL, "imperfections": {"gains": drawn.tolist()}})
    np.testing.assert_array_equal(simulate(explicit).sensor, with_gains.sensor)
    with pytest.raises(ValueError, match="imperfections.gains has 3 values for the 7 views"):
        simulate(SimulationConfig(**{**SMALL, "imperfections": {"gains": [1.0, 0.9, 0.8]}}))


def test_field_margin_brings_light_from_beyond_the_views(tmp_path):
    from fgat.io.images import write_tiff

    margin, size = 6, 32
    outside = np.zeros((5, size + 2 * margin, size + 2 * margin), np.float32)
    outside[0, margin - 3, margin + size // 2] = 1.0  # 3 px above the field, at -12 um
    write_tiff(tmp_path / "outside.tif", outside)
    config = SimulationConfig(
        **{
            **SMALL,
            "phantom": {"kind": "reticular", "path": str(tmp_path / "outside.tif")},
            "imperfections": {"field_margin_px": margin},
        }
    )
    result = simulate(config)
    assert result.truth.shape == (5, size, size) and not result.truth.any()
    np.testing.assert_array_equal(result.truth_padded, outside)
    assert result.views.sum() > 0.05 * result.sensor.sum() and result.views.max() > 0
    folder = write_simulation(result, tmp_path / "sim")
    assert read_tiff(folder / "truth_padded.ome.tif").shape == (5, 44, 44)
    assert not read_tiff(folder / "truth.ome.tif").any()
    # inside the field, the padded projection is the plain one: same views, same alignment
    inside = np.zeros_like(outside)
    inside[2, margin + 5, margin + 20] = inside[4, margin + 30, margin + 1] = 1.0
    write_tiff(tmp_path / "inside.tif", inside)
    write_tiff(tmp_path / "crop.tif", inside[:, margin:-margin, margin:-margin])
    padded = simulate(
        dataclasses.replace(
            config, phantom={"kind": "reticular", "path": str(tmp_path / "inside.tif")}
        )
    )
    plain = simulate(
        SimulationConfig(
            **{**SMALL, "phantom": {"kind": "reticular", "path": str(tmp_path / "crop.tif")}}
        )
    )
    np.testing.assert_array_equal(padded.truth, plain.truth)
    np.testing.assert_allclose(padded.views, plain.views, atol=1e-6 * plain.views.max())


def test_field_margin_on_a_sequence():
    from fgat.sim.simulation import make_phantom

    config = SimulationConfig(
        **{
            **SMALL,
            "phantom": {"kind": "moving_beads", "n_beads": 4},
            "frames": 2,
            "imperfections": {"field_margin_px": 4, "hot_pixels": 3},
        }
    )
    result = simulate(config)
    assert result.truth.shape == (2, 5, 32, 32) and result.truth_padded.shape == (2, 5, 40, 40)
    np.testing.assert_array_equal(result.truth, result.truth_padded[..., 4:-4, 4:-4])
    np.testing.assert_array_equal(make_phantom(config, (5, 32, 32), [0.0, 1.0]), result.truth)
    rows, cols = result.imperfections.hot_pixels.T
    assert (result.sensor[:, rows, cols] >= 500).all()


@pytest.mark.slow
def test_hot_pixels_dark_frames_and_flat(tmp_path):
    config = SimulationConfig(
        **{
            **SMALL,
            "photons": 1000.0,
            "background": 100.0,
            "read_noise": 2.0,
            "imperfections": {
                "gains": [0.6, 1.0],
                "hot_pixels": 20,
                "hot_pixel_counts": 500.0,
                "dark_frames": 8,
                "flat": True,
            },
        }
    )
    result = simulate(config)
    folder = write_simulation(result, tmp_path / "sim")
    hot = np.loadtxt(folder / "hot_pixels.csv", delimiter=",", skiprows=1, ndmin=2)
    np.testing.assert_array_equal(hot[:, :2], result.imperfections.hot_pixels)
    assert (hot[:, 2] == 500).all() and len(np.unique(hot[:, :2], axis=0)) == 20
    params = yaml.safe_load((folder / "params.yaml").read_text())
    assert params["imperfections"]["hot_pixels_px"] == hot[:, :2].astype(int).tolist()
    rows, cols = hot[:, :2].astype(int).T
    dark = read_tiff(folder / "dark.ome.tif")
    assert dark.shape == (8, 256, 256) and not np.array_equal(dark[0], dark[1])
    # hot pixels: in the image and in every dark frame, at the listed positions
    assert (result.sensor[rows, cols] > 100 + 500 - 5 * np.sqrt(500)).all()
    assert dark[:, rows, cols].mean() == pytest.approx(600, abs=4 * np.sqrt(500 / 160))
    normal = np.ones((256, 256), bool)
    normal[rows, cols] = False
    assert (dark[:, normal] < 100 + 10 * 2).all()
    # elsewhere: offset and read noise only
    assert dark[:, normal].mean() == pytest.approx(100.0, abs=0.01)
    assert np.sqrt(dark[:, normal].var(axis=0, ddof=1).mean()) == pytest.approx(2.0, rel=0.01)
    # the flat: a lit disk per lenslet at photons counts, scaled by its gain
    flat = read_tiff(folder / "flat.ome.tif")
    np.testing.assert_array_equal(flat, result.flat)
    assert flat[normal].max() == pytest.approx(1100, abs=150)
    grid = np.mgrid[:256, :256]
    pitch = 500 / 6.5
    means = []
    for center in result.centers:
        disk = (np.hypot(*(grid - center[:, None, None])) < 0.3 * pitch) & normal
        means.append(flat[disk].mean() - 100.0)
    gains = result.imperfections.gains
    np.testing.assert_allclose(np.array(means) / means[0], gains / gains[0], rtol=0.01)
    # overwriting with an ideal simulation leaves none of these files behind
    ideal = simulate(dataclasses.replace(config, imperfections=None))
    write_simulation(ideal, folder, overwrite=True)
    assert sorted(p.name for p in folder.iterdir()) == sorted(OUTPUT_FILES)


@pytest.mark.parametrize(
    "entry, message",
    [
        ("{hot_pixel: 3}", "imperfections: unknown field\\(s\\) \\['hot_pixel'\\]"),
        ("5", "imperfections must be a mapping of"),
        ("{mla_rotation_deg: 45}", "imperfections.mla_rotation_deg must be in \\(-30, 30\\)"),
        ("{center_jitter_px: -1}", "imperfections.center_jitter_px must be a finite number >= 0"),
        ("{gains: [1.0, 0.5]}", "imperfections.gains range \\[lo, hi\\] needs lo <= hi"),
        ("{gains: [0.0, 1.0]}", "imperfections.gains must be a finite number > 0"),
        ("{gains: 0.8}", "imperfections.gains must be a range \\[lo, hi\\]"),
        ("{hot_pixels: 2.5}", "imperfections.hot_pixels must be an integer"),
        ("{hot_pixel_counts: -1}", "imperfections.hot_pixel_counts must be"),
        ("{field_margin_px: -2}", "imperfections.field_margin_px must be an integer >= 0"),
        ("{dark_frames: many}", "imperfections.dark_frames must be an integer"),
        ("{flat: 3}", "imperfections.flat must be true or false"),
        ("{flat_radius_pitch: 0.7}", "imperfections.flat_radius_pitch must be"),
        ("{seed: -1}", "imperfections.seed must be an integer >= 0"),
    ],
)
def test_imperfections_are_validated(tmp_path, entry, message):
    path = tmp_path / "sim.yaml"
    path.write_text(f"system: small\nimperfections: {entry}\n")
    with pytest.raises(ValueError, match=f"sim.yaml: {message}"):
        SimulationConfig.from_yaml(path)


def test_imperfections_the_system_cannot_take():
    def run(**imperfections):
        simulate(SimulationConfig(**{**SMALL, "imperfections": imperfections}))

    with pytest.raises(ValueError, match="center_jitter_px = 20 must be below a quarter"):
        run(center_jitter_px=20)
    with pytest.raises(ValueError, match="field_margin_px = 40: the padded views do not fit"):
        run(field_margin_px=40)
    with pytest.raises(ValueError, match="hot_pixels = 70000 is more than"):
        run(hot_pixels=70000)


@pytest.mark.slow
def test_realistic37_measurement(tmp_path):
    from fgat.instrument.lattice import fit_hexagonal_lattice
    from fgat.recon.scene import phantom_scene

    config_path = "configs/simulate/realistic37.yaml"
    out = tmp_path / "sim37"
    assert main(["simulate", "--config", config_path, "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [*OUTPUT_FILES, "truth_padded.ome.tif", "dark.ome.tif", "flat.ome.tif", "hot_pixels.csv"]
    )
    centers = read_centers(out / "centers.csv")
    sensor, views = read_tiff(out / "sensor.ome.tif"), read_tiff(out / "views.ome.tif")
    truth, padded = read_tiff(out / "truth.ome.tif"), read_tiff(out / "truth_padded.ome.tif")
    assert sensor.shape == (360, 400) and views.shape == (37, 40, 40)
    assert truth.shape == (25, 40, 40) and padded.shape == (25, 60, 60)
    assert read_tiff(out / "dark.ome.tif").shape == (5, 360, 400)
    # beads straddle the view borders: light on the truth's border and in the margin
    assert truth[:, [0, -1], :].max() > 0.05 or truth[:, :, [0, -1]].max() > 0.05
    band = padded.copy()
    band[:, 10:-10, 10:-10] = 0
    assert band.max() > 0.5
    # a calibration of the flat finds the true centres
    fit = fit_hexagonal_lattice(read_tiff(out / "flat.ome.tif") - 100.0, 37)
    assert np.abs(fit.centers - centers).max() < 0.25
    assert fit.lattice.rotation_deg == pytest.approx(0.4, abs=0.3)
    params = yaml.safe_load((out / "params.yaml").read_text())
    assert params["config"]["imperfections"]["gains"] == [0.7, 1.0]
    assert len(params["imperfections"]["hot_pixels_px"]) == 30
    # the reconstruction's phantom scene takes it: true centres in its true optics
    scene = phantom_scene(SimulationConfig.from_yaml(config_path))
    assert scene.measurement.shape == (37, 40, 40) and scene.truth.shape == (25, 40, 40)
    np.testing.assert_allclose(scene.truth_optics.centers_px, centers, atol=1e-6)


def test_shell_beads_phantom_is_drawn_on_the_grid_in_um():
    from pathlib import Path

    from fgat.recon.metrics import axial_lateral_aspect
    from fgat.sim.simulation import make_phantom

    system = str(Path(__file__).resolve().parents[3] / "reproduce/systems/highna37.yaml")
    phantom = {"kind": "shell_beads", "diameter_um": 8.0, "n_beads": 0}
    # planes 0.25 um apart and 0.54 um pixels: the shell spans twice as many planes as pixels
    config = SimulationConfig(system=system, depths_um="-5:5:41", view_size=21, phantom=phantom)
    volume = make_phantom(config, (41, 21, 21))
    lit = np.argwhere(volume > 0.5)
    planes, columns = np.ptp(lit[:, 0]) + 1, np.ptp(lit[:, 2]) + 1
    assert planes / columns == pytest.approx(0.5417 / 0.25, rel=0.1)
    shape = axial_lateral_aspect(volume, (0.25, 0.5417, 0.5417))
    assert shape["aspect"] == pytest.approx(1.0, abs=0.01)
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['voxel_size_um'\]"):
        SimulationConfig(phantom={**phantom, "voxel_size_um": [1, 1, 1]}).validate()
