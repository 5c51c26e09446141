"""The Calibrate, Deconvolve and Fit widgets on a small simulated measurement (37 lenslets,
configs/simulate/realistic37.yaml): each writes what its command line writes from the same
inputs, shows its result as layers, stops on Cancel and reports a bad input in one line."""

import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("napari")
pytest.importorskip("pytestqt")
if not os.environ.get("DISPLAY"):  # pytest-xvfb sets it when Xvfb is installed (.ci/run)
    pytest.skip("no screen for Qt: install Xvfb and pytest-xvfb", allow_module_level=True)

from napari.layers import Image, Points, Shapes  # noqa: E402
from napari.utils.notifications import NotificationSeverity, notification_manager  # noqa: E402

from fgat.app.cli import main  # noqa: E402
from fgat.instrument.centres import read_centers  # noqa: E402
from fgat.io.images import read_tiff, read_voxel_size, volume_metadata, write_tiff  # noqa: E402
from fgat.napari.widgets import (  # noqa: E402
    CalibrateWidget,
    DeconvolveWidget,
    FitWidget,
    layer_file,
)

ROOT = Path(__file__).resolve().parents[2]
DEPTHS = "-4:4:25"
WAIT_MS = 180_000


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """The simulated measurement and what the command line makes of it: a calibration folder
    and a 5-iteration SHB volume."""
    root = tmp_path_factory.mktemp("measured")
    sim, calib = root / "sim", root / "calib"
    config = ROOT / "configs" / "simulate" / "realistic37.yaml"
    assert main(["simulate", "--config", str(config), "--out", str(sim)]) == 0
    frames = ["--image", str(sim / "flat.ome.tif"), "--flat", str(sim / "flat.ome.tif")]
    frames += ["--dark", str(sim / "dark.ome.tif"), "--system", "small37"]
    assert main(["calibrate", *frames, "--out", str(calib)]) == 0
    shb = root / "shb.ome.tif"
    words = ["deconvolve", "--measurement", str(sim / "sensor.ome.tif"), "--system", "small37"]
    words += [f"--depths-um={DEPTHS}", "--calibration", str(calib), "--iterations", "5"]
    assert main([*words, "--out", str(shb)]) == 0
    return {"root": root, "sim": sim, "calib": calib, "shb": shb}


def docked(viewer, widget):
    """``widget`` in a dock of ``viewer``, its layer menus filled."""
    viewer.window.add_dock_widget(widget)
    widget.reset_choices()
    return widget


def run_to_end(qtbot, widget):
    widget.start()
    qtbot.waitUntil(lambda: not widget.running, timeout=WAIT_MS)
    return widget.outcome


def cancel_after(qtbot, widget, wait_ms: int):
    """Start ``widget``, press Cancel ``wait_ms`` ms after its run began, wait for its end."""
    widget.start()
    qtbot.waitUntil(lambda: widget.monitor is not None, timeout=WAIT_MS)
    qtbot.wait(wait_ms)
    widget.cancel()
    qtbot.waitUntil(lambda: not widget.running, timeout=WAIT_MS)
    return widget.outcome


def sensor_layer(viewer, measured):
    """The sensor image opened from its file (napari's own TIFF reader: fgat's declines a
    simulation's sensor image), which the widgets pass on as that file."""
    (layer,) = viewer.open(measured["sim"] / "sensor.ome.tif", plugin="napari")
    layer.name = "sensor"
    return layer


def test_a_layer_is_passed_as_its_file_until_it_is_edited(make_napari_viewer, measured, tmp_path):
    """Opened from a TIFF and unchanged: the file itself (its folder's sidecars with it); edited
    since: its data as they are now, in a file of their own."""
    viewer = make_napari_viewer()
    sensor = sensor_layer(viewer, measured)
    assert layer_file(sensor, tmp_path) == measured["sim"] / "sensor.ome.tif"
    shb = viewer.open(measured["shb"], plugin="fgat")[0]  # fgat's reader: the volume as recorded
    assert layer_file(shb, tmp_path) == measured["shb"]
    sensor.data = sensor.data + 1
    edited = layer_file(sensor, tmp_path)
    assert edited == tmp_path / "sensor.tif"
    np.testing.assert_array_equal(
        read_tiff(edited), read_tiff(measured["sim"] / "sensor.ome.tif") + 1
    )


def test_calibrate_widget_writes_the_commands_calibration(
    make_napari_viewer, qtbot, measured, tmp_path
):
    viewer = make_napari_viewer()
    sim = measured["sim"]
    flat = viewer.add_image(read_tiff(sim / "flat.ome.tif"), name="flat")
    dark = viewer.add_image(read_tiff(sim / "dark.ome.tif"), name="dark")
    widget = docked(viewer, CalibrateWidget(viewer))
    widget.image.value, widget.flat.value, widget.dark.value = flat, flat, dark
    widget.system.value, widget.out.value = "small37", tmp_path / "calib"
    assert run_to_end(qtbot, widget) == ("done", None)
    mine, theirs = tmp_path / "calib", measured["calib"]
    np.testing.assert_allclose(
        read_centers(mine / "centers.csv"), read_centers(theirs / "centers.csv"), atol=1e-9
    )
    assert (mine / "calibration.yaml").read_text().split("\nsource:")[0] == (
        theirs / "calibration.yaml"
    ).read_text().split("\nsource:")[0]
    points = [layer for layer in viewer.layers if isinstance(layer, Points)]
    shapes = [layer for layer in viewer.layers if isinstance(layer, Shapes)]
    assert len(points) == 1 and len(shapes) == 1
    np.testing.assert_allclose(points[0].data, read_centers(theirs / "centers.csv"), atol=1e-6)
    assert widget.status.value.startswith("37 of 37 views found, residual RMS")


def test_deconvolve_widget_gives_the_commands_volume_as_a_layer(
    make_napari_viewer, qtbot, measured, tmp_path
):
    viewer = make_napari_viewer()
    sensor = sensor_layer(viewer, measured)
    widget = docked(viewer, DeconvolveWidget(viewer))
    widget.measurement.value, widget.calibration.value = sensor, measured["calib"]
    widget.system.value, widget.depths.value = "small37", DEPTHS
    widget.iterations.value, widget.out.value = 5, tmp_path / "shb.ome.tif"
    assert run_to_end(qtbot, widget) == ("done", None)
    expected = read_tiff(measured["shb"])
    np.testing.assert_allclose(read_tiff(tmp_path / "shb.ome.tif"), expected, rtol=1e-6)
    assert volume_metadata(tmp_path / "shb.ome.tif") == volume_metadata(measured["shb"])
    layer = viewer.layers["SHB sensor"]
    assert isinstance(layer, Image) and layer.data.shape == expected.shape
    np.testing.assert_allclose(np.asarray(layer.data), expected, rtol=1e-6)
    size = read_voxel_size(measured["shb"])
    np.testing.assert_allclose(layer.scale, [size["Z"], size["Y"], size["X"]], rtol=1e-6)
    depths = volume_metadata(measured["shb"])["depths_um"]
    assert layer.translate[0] == pytest.approx(depths[0])
    layer.save(str(tmp_path / "saved.ome.tif"), plugin="fgat")  # File > Save Selected Layers
    np.testing.assert_array_equal(read_tiff(tmp_path / "saved.ome.tif"), expected)
    assert volume_metadata(tmp_path / "saved.ome.tif") == volume_metadata(measured["shb"])
    assert read_voxel_size(tmp_path / "saved.ome.tif") == pytest.approx(size)


def test_deconvolve_cancel_stops_within_an_iteration(make_napari_viewer, qtbot, measured, tmp_path):
    viewer = make_napari_viewer()
    widget = docked(viewer, DeconvolveWidget(viewer))
    widget.measurement.value, widget.calibration.value = (
        sensor_layer(viewer, measured),
        measured["calib"],
    )
    widget.iterations.value, widget.out.value = 2000, tmp_path / "long.ome.tif"
    kind, line = cancel_after(qtbot, widget, 1500)
    assert kind == "cancelled" and "of 2000" in line, line
    done = int(line.split("after iteration ")[1].split(" of")[0])
    assert 1 <= done < 2000
    assert not (tmp_path / "long.ome.tif").exists()  # nothing half-written
    assert widget.cancel_latency_s < 5.0


def bad_calibrate(viewer, measured, tmp_path):
    """An image of noise: no lattice to find."""
    write_tiff(tmp_path / "noise.tif", np.random.default_rng(0).normal(100, 3, (360, 400)))
    widget = CalibrateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    (noise,) = viewer.open(tmp_path / "noise.tif", plugin="napari")
    widget.reset_choices()
    widget.image.value, widget.out.value = noise, tmp_path / "calib"
    return widget


def bad_deconvolve(viewer, measured, tmp_path):
    """A folder that is not a calibration."""
    widget = docked(viewer, DeconvolveWidget(viewer))
    (tmp_path / "empty").mkdir()
    widget.measurement.value = sensor_layer(viewer, measured)
    widget.calibration.value = tmp_path / "empty"
    widget.out.value = tmp_path / "volume.ome.tif"
    return widget


def bad_fit(viewer, measured, tmp_path):
    """A step budget below one."""
    widget = fit_widget(viewer, measured, tmp_path, steps=10)
    widget.overrides.value += " --trainer.max_steps=-5"
    return widget


@pytest.mark.parametrize("make", [bad_calibrate, bad_deconvolve, bad_fit])
def test_a_bad_input_shows_the_commands_line_once(
    make_napari_viewer, qtbot, measured, tmp_path, capsys, make
):
    viewer = make_napari_viewer()
    widget = make(viewer, measured, tmp_path)
    layers = len(viewer.layers)
    before = len(notification_manager.records)
    kind, line = run_to_end(qtbot, widget)
    shown = notification_manager.records[before:]
    assert kind == "error" and len(shown) == 1, shown
    assert shown[0].severity == NotificationSeverity.ERROR and shown[0].message == line
    assert "\n" not in line and "Traceback" not in line and line.startswith("fgat ")
    assert len(viewer.layers) == layers  # nothing added
    capsys.readouterr()
    assert main(widget.words(tmp_path)) == 2  # the same command on the command line
    assert capsys.readouterr().err.strip() == line


FIT_OVERRIDES = (
    "--data.init_args.truth=null --trainer.val_check_interval={steps} "
    "--trainer.max_steps={steps} --model.init_args.n_gaussians=200 --trainer.callbacks=[] "
    "--trainer.default_root_dir={root} --mlflow.tracking_uri=sqlite:///{root}/mlflow.db"
)


def fit_widget(viewer, measured, root: Path, steps: int):
    widget = docked(viewer, FitWidget(viewer))
    widget.measurement.value = sensor_layer(viewer, measured)
    widget.configs.value = [ROOT / "configs/base/common.yaml", ROOT / "configs/measured.yaml"]
    widget.calibration.value, widget.depths.value = measured["calib"], DEPTHS
    widget.overrides.value = FIT_OVERRIDES.format(steps=steps, root=root)
    return widget


@pytest.mark.slow
def test_fit_widget_gives_the_commands_volume_and_run(
    make_napari_viewer, qtbot, measured, tmp_path
):
    viewer = make_napari_viewer()
    widget = fit_widget(viewer, measured, tmp_path / "widget", steps=10)
    assert run_to_end(qtbot, widget) == ("done", None)
    words = ["fit", "--config", str(ROOT / "configs/base/common.yaml")]
    words += ["--config", str(ROOT / "configs/measured.yaml")]
    words += [f"--data.init_args.measurement={measured['sim'] / 'sensor.ome.tif'}"]
    words += [f"--data.init_args.calibration={measured['calib']}"]
    words += ["--data.init_args.system=small37", f"--data.init_args.depths_um={DEPTHS}"]
    words += ["--model.init_args.optics.estimate=none"]
    words += FIT_OVERRIDES.format(steps=10, root=tmp_path / "cli").split()
    assert main(words) == 0
    (cli,) = (tmp_path / "cli" / "results").iterdir()
    folder = widget.monitor.outputs["results"]
    assert folder.parent == tmp_path / "widget" / "results"
    np.testing.assert_allclose(
        read_tiff(folder / "volume.ome.tif"),
        read_tiff(cli / "volume.ome.tif"),
        rtol=1e-4,
        atol=1e-4,
    )
    layer = next(layer for layer in viewer.layers if layer.name != "sensor")
    np.testing.assert_allclose(np.asarray(layer.data), read_tiff(folder / "volume.ome.tif"))
    ((name, run_id, experiment, uri),) = widget.monitor.outputs["mlflow"]
    assert run_id == folder.name and experiment == "measured" and run_id in widget.status.value


@pytest.mark.slow
def test_fit_cancel_ends_a_complete_run_early(make_napari_viewer, qtbot, measured, tmp_path):
    viewer = make_napari_viewer()
    widget = fit_widget(viewer, measured, tmp_path, steps=20000)
    kind, line = cancel_after(qtbot, widget, 3000)
    step = widget.monitor.outputs["step"]
    assert kind == "cancelled" and line == f"fgat fit: cancelled at step {step}"
    assert 0 <= step < 20000
    assert (widget.monitor.outputs["results"] / "volume.ome.tif").is_file()
    assert any(layer.name != "sensor" for layer in viewer.layers)
    assert widget.cancel_latency_s < 30.0
