"""The napari reader and writer: every kind of fgat output opens with its layers, scales, axes
and metadata; files fgat did not write are declined; a read layer saved and read again is the
same."""

import json
import math

import numpy as np
import pytest

from fgat._core.conventions import DEPTH_AXES, VIEW_ORDER
from fgat.io.images import read_tiff, volume_entries, write_tiff
from fgat.io.zarr_series import ZarrSeriesWriter
from fgat.napari import reader
from fgat.napari.reader import get_reader, identify
from fgat.napari.writer import write_volume
from tests.napari.conftest import DEPTHS, SIMULATION, VOXEL, layers_of

UM = ("micrometer",) * 3


def only(layers):
    (layer,) = layers
    return layer


def test_volume_up_and_down_show_the_same_array_at_the_same_depths(tmp_path, volume):
    up = write_tiff(
        tmp_path / "up.ome.tif", volume, voxel_size_um=VOXEL, metadata=volume_entries("up", DEPTHS)
    )
    down = write_tiff(
        tmp_path / "down.ome.tif",
        volume[::-1],
        voxel_size_um=VOXEL,
        metadata=volume_entries("down", DEPTHS[::-1]),
    )
    shown = {}
    for path in (up, down):
        data, kwargs, kind = only(layers_of(path))
        assert kind == "image" and kwargs["name"] == path.name.split(".")[0]
        assert kwargs["scale"] == VOXEL and kwargs["translate"] == (-6.0, 0.0, 0.0)
        assert kwargs["axis_labels"] == ("z", "y", "x") and kwargs["units"] == UM
        assert isinstance(data, np.memmap)  # not read until shown, even reversed
        metadata = kwargs["metadata"]
        assert metadata["fgat"]["depths_um"] == DEPTHS and metadata["fgat"]["depth_axis"] == "up"
        assert metadata["fgat"]["depth_axis_convention"] == DEPTH_AXES["up"]
        assert metadata["path"] == str(path) and metadata["kind"] == "volume"
        shown[path.name] = (np.asarray(data), metadata)
    np.testing.assert_array_equal(shown["up.ome.tif"][0], volume)
    np.testing.assert_array_equal(shown["down.ome.tif"][0], volume)
    assert shown["up.ome.tif"][1]["recorded_depth_axis"] == "up"
    assert shown["down.ome.tif"][1]["recorded_depth_axis"] == "down"
    assert "reversed" in shown["down.ome.tif"][1]["shown"]


def test_series_time_axis_in_seconds_when_recorded(tmp_path, volume):
    series = np.stack([volume, 2 * volume, 3 * volume])
    timed = write_tiff(
        tmp_path / "timed.ome.tif",
        series,
        axes="TZYX",
        voxel_size_um=VOXEL,
        metadata=volume_entries("up", DEPTHS),
        time_interval_s=0.25,
    )
    data, kwargs, _ = only(layers_of(timed))
    np.testing.assert_array_equal(data, series)
    assert kwargs["scale"] == (0.25, *VOXEL) and kwargs["translate"] == (0.0, -6.0, 0.0, 0.0)
    assert kwargs["axis_labels"] == ("t", "z", "y", "x")
    assert kwargs["units"] == ("second", *UM) and kwargs["metadata"]["time_interval_s"] == 0.25
    frames = write_tiff(
        tmp_path / "frames.ome.tif", series, axes="TZYX", metadata=volume_entries("up", DEPTHS)
    )
    _, kwargs, _ = only(layers_of(frames))  # no interval, no voxel size: frames and pixels
    assert kwargs["scale"] == (1.0,) * 4 and kwargs["units"] == ("pixel",) * 4


def test_zarr_series_opened_lazily_with_channel_names(tmp_path, volume):
    dask = pytest.importorskip("dask")  # napari brings it

    frames = [np.stack([volume * (t + 1), volume + c]) for t, c in zip(range(3), range(3))]
    with ZarrSeriesWriter(
        tmp_path / "two.ome.zarr",
        (2, *volume.shape),
        voxel_size_um=VOXEL,
        time_interval_s=2.0,
        metadata=volume_entries("down", DEPTHS[::-1]),
        channel_names=["GFP", "mCherry"],
    ) as writer:
        for frame in frames:
            writer.append(frame)
    data, kwargs, kind = only(layers_of(tmp_path / "two.ome.zarr"))
    assert kind == "image" and isinstance(data, dask.array.Array) and kwargs["channel_axis"] == 1
    expected = np.stack(frames)[:, :, ::-1]  # shown up: z reversed
    np.testing.assert_array_equal(np.asarray(data), expected)
    assert kwargs["name"] == ["two GFP", "two mCherry"]
    assert len(set(kwargs["colormap"])) == 2 and kwargs["blending"] == ["additive"] * 2
    assert kwargs["scale"] == [(2.0, *VOXEL)] * 2
    assert kwargs["translate"] == [(0.0, -6.0, 0.0, 0.0)] * 2
    assert kwargs["units"] == [("second", *UM)] * 2
    assert [m["channel"] for m in kwargs["metadata"]] == ["GFP", "mCherry"]
    assert kwargs["metadata"][0]["fgat"]["depths_um"] == DEPTHS
    one = tmp_path / "one.ome.zarr"
    entries = volume_entries("up", DEPTHS)
    with ZarrSeriesWriter(one, (1, *volume.shape), voxel_size_um=VOXEL, metadata=entries) as w:
        w.append(volume)
    data, kwargs, _ = only(layers_of(one))
    assert data.shape == (1, *volume.shape) and "channel_axis" not in kwargs
    assert kwargs["axis_labels"] == ("t", "z", "y", "x") and kwargs["scale"] == (1.0, *VOXEL)
    assert kwargs["units"] == ("pixel", *UM) and kwargs["name"] == "one"


def test_merged_channels_are_named_by_their_index_in_the_data(tmp_path, volume):
    from fgat.app.pipeline import merge_channels

    pytest.importorskip("dask")  # napari brings it

    series = []
    for channel in (0, 2):
        path = tmp_path / f"ch{channel}.ome.tif"
        write_tiff(
            path,
            np.stack([volume + channel] * 2),
            axes="TZYX",
            voxel_size_um=VOXEL,
            metadata=volume_entries("up", DEPTHS),
            time_interval_s=0.5,
        )
        series.append(path)
    merged = merge_channels(series, tmp_path / "volumes.ome.zarr", [0, 2])
    data, kwargs, _ = only(layers_of(merged))
    assert kwargs["name"] == ["volumes channel 0", "volumes channel 2"]
    np.testing.assert_array_equal(np.asarray(data)[:, 1], np.stack([volume + 2] * 2))
    assert kwargs["scale"][0] == (0.5, *VOXEL)


def test_psf_stack_written_by_a_fit_is_one_layer_per_view_axis(tmp_path):
    stack = np.random.default_rng(1).random((7, len(DEPTHS), 9, 9), dtype=np.float32)
    path = write_tiff(  # as a fit's results folder writes it for a "down" scene
        tmp_path / "psf.ome.tif",
        stack,
        axes="CZYX",
        voxel_size_um=VOXEL,
        metadata=volume_entries("down", DEPTHS[::-1], content="psf"),
    )
    data, kwargs, _ = only(layers_of(path))
    np.testing.assert_array_equal(data, stack[:, ::-1])
    assert kwargs["axis_labels"] == ("view", "z", "y", "x")
    assert kwargs["scale"] == (1.0, *VOXEL) and kwargs["translate"] == (0.0, -6.0, 0.0, 0.0)
    assert kwargs["units"] == ("pixel", *UM)
    assert kwargs["metadata"]["kind"] == "psf" and kwargs["metadata"]["fgat"]["content"] == "psf"
    assert kwargs["metadata"]["fgat"]["view_order"] == VIEW_ORDER


def test_calibration_folder_shows_centres_in_view_order_and_hexagonal_cells(tmp_path):
    from fgat.instrument.calibration import Calibration, save_calibration
    from fgat.instrument.lattice import HexLattice

    lattice = HexLattice((40.0, 52.0), 18.0, 7.0)
    centers = lattice.centers(7) + np.random.default_rng(2).normal(0, 0.2, (7, 2))
    image = np.random.default_rng(3).random((96, 104), dtype=np.float32)
    write_tiff(tmp_path / "mla.tif", image)
    folder = tmp_path / "calibration"
    folder.mkdir()
    save_calibration(Calibration(centers, lattice, source="mla.tif"), folder)  # relative
    layers = layers_of(folder)
    assert [kind for _, _, kind in layers] == ["image", "points", "shapes"]
    (picture, meta, _), (points, point_kwargs, _), (cells, cell_kwargs, _) = layers
    np.testing.assert_array_equal(picture, image)
    assert meta["name"] == "calibration: mla.tif"
    assert meta["metadata"]["source_found"] == str(tmp_path / "mla.tif")
    written = np.loadtxt(folder / "centers.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(points, written)
    np.testing.assert_allclose(points, centers, atol=1e-6)  # in the order saved: view order
    np.testing.assert_array_equal(point_kwargs["features"]["view"], np.arange(7))
    assert point_kwargs["text"]["string"] == "{view}"
    assert point_kwargs["metadata"]["lattice"]["pitch_px"] == 18.0
    assert len(cells) == 7 and cell_kwargs["shape_type"] == "polygon"
    for view, (cell, point) in enumerate(zip(cells, lattice.centers(7))):
        assert cell.shape == (6, 2)
        np.testing.assert_allclose(cell.mean(axis=0), point, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(cell - point, axis=1), 18.0 / math.sqrt(3))
        if view:  # every first-ring cell shares an edge (two corners) with the centre's cell
            gaps = np.linalg.norm(cells[0][:, None] - cell[None], axis=-1)
            assert (gaps < 1e-9).sum() == 2
    record = (
        (folder / "calibration.yaml").read_text().replace("source: mla.tif", "source: gone.tif")
    )
    (folder / "calibration.yaml").write_text(record)
    layers = layers_of(folder)
    assert [kind for _, _, kind in layers] == ["points", "shapes"]
    assert "'gone.tif' was not found" in layers[0][1]["metadata"]["note"]


def test_results_folder_volumes_are_aligned_and_named(tmp_path, volume):
    folder = tmp_path / "run1"
    folder.mkdir()
    for name, factor in (("volume", 1.0), ("shb", 2.0), ("truth", 3.0)):
        write_tiff(
            folder / f"{name}.ome.tif",
            factor * volume,
            voxel_size_um=VOXEL,
            metadata=volume_entries("up", DEPTHS),
        )
    (folder / "residual.json").write_text(json.dumps({"relative_residual": 0.1}))
    layers = layers_of(folder)
    names = [kwargs["name"] for _, kwargs, _ in layers]
    assert names == ["reconstruction (run1)", "SHB baseline (run1)", "ground truth (run1)"]
    for (data, kwargs, _), factor in zip(layers, (1.0, 2.0, 3.0)):
        np.testing.assert_allclose(data, factor * volume)
        assert kwargs["scale"] == VOXEL and kwargs["translate"] == (-6.0, 0.0, 0.0)
        assert kwargs["metadata"]["results"] == str(folder)
    assert len({kwargs["colormap"] for _, kwargs, _ in layers}) == 3
    (folder / "volume.ome.tif").unlink()
    (folder / "shb.ome.tif").unlink()
    assert identify(folder) is None  # a truth and a report are not a fit's results


def test_another_tool_s_ome_zarr_is_declined(tmp_path, volume):
    pytest.importorskip("ome_zarr")
    import zarr
    from ome_zarr.io import parse_url
    from ome_zarr.writer import write_image

    store = parse_url(tmp_path / "other.ome.zarr", mode="w").store
    write_image(np.stack([[volume]]), zarr.group(store=store), axes="tczyx")
    assert (tmp_path / "other.ome.zarr").is_dir()
    assert get_reader(str(tmp_path / "other.ome.zarr")) is None
    with ZarrSeriesWriter(tmp_path / "bare.ome.zarr", (1, *volume.shape), voxel_size_um=VOXEL) as w:
        w.append(volume)  # without fgat's entries, fgat's own store is no different
    assert get_reader(str(tmp_path / "bare.ome.zarr")) is None


def test_foreign_and_damaged_inputs_are_declined(tmp_path, volume):
    import tifffile

    tifffile.imwrite(tmp_path / "plain.tif", volume)
    write_tiff(tmp_path / "bare.ome.tif", volume, voxel_size_um=VOXEL)  # no fgat annotation
    ours = write_tiff(tmp_path / "cut.ome.tif", volume, metadata=volume_entries("up", DEPTHS))
    (tmp_path / "cut.ome.tif").write_bytes(ours.read_bytes()[:300])
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "fake.tif").write_text("not a TIFF")
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder" / "residual.json").write_text("{}")
    for name in (
        "plain.tif",
        "bare.ome.tif",
        "cut.ome.tif",
        "notes.txt",
        "fake.tif",
        "folder",
        "missing.ome.tif",
    ):
        assert get_reader(str(tmp_path / name)) is None, name
    good = write_tiff(tmp_path / "good.ome.tif", volume, metadata=volume_entries("up", DEPTHS))
    assert get_reader([str(good), str(tmp_path / "plain.tif")]) is None  # all or nothing
    assert len(get_reader([str(good), str(good)])([str(good), str(good)])) == 2


def test_file_names_the_reader_looks_for_are_fgat_s():
    from fgat.app.report import RESIDUAL_FILE
    from fgat.instrument.calibration import CALIBRATION_FILE

    assert reader.RESIDUAL_FILE == RESIDUAL_FILE
    assert reader.CALIBRATION_FILE == CALIBRATION_FILE


@pytest.mark.parametrize("axis", ["up", "down"])
def test_writer_round_trip(tmp_path, volume, axis):
    order = volume if axis == "up" else volume[::-1]
    depths = DEPTHS if axis == "up" else DEPTHS[::-1]
    series = write_tiff(
        tmp_path / "series.ome.tif",
        np.stack([order, order + 1]),
        axes="TZYX",
        voxel_size_um=VOXEL,
        metadata=volume_entries(axis, depths),
        time_interval_s=1.5,
    )
    psf = write_tiff(
        tmp_path / "psf.ome.tif",
        np.stack([order] * 3),
        axes="CZYX",
        voxel_size_um=VOXEL,
        metadata=volume_entries(axis, depths, content="psf"),
    )
    volume_file = write_tiff(
        tmp_path / "volume.ome.tif",
        order,
        voxel_size_um=VOXEL,
        metadata=volume_entries(axis, depths),
    )
    for path in (volume_file, series, psf):
        data, kwargs, _ = only(layers_of(path))
        copy = tmp_path / f"copy_{path.name}"
        assert write_volume(str(copy), data, kwargs) == [str(copy)]
        again, copied, _ = only(layers_of(copy))
        np.testing.assert_array_equal(again, data)
        for key in ("scale", "translate", "axis_labels", "units"):
            assert copied[key] == kwargs[key], (path.name, key)
        drop = ("path",)
        assert {k: v for k, v in copied["metadata"].items() if k not in drop} == {
            k: v for k, v in kwargs["metadata"].items() if k not in drop
        }
        np.testing.assert_array_equal(read_tiff(copy), read_tiff(path))  # the file's own order


def test_writer_refuses_what_is_not_a_volume(tmp_path, volume):
    with pytest.raises(ValueError, match="cannot write 'flat' as a volume: 2-D float32"):
        write_volume(str(tmp_path / "a.ome.tif"), volume[0], {"name": "flat"})
    with pytest.raises(ValueError, match="its first axis 'c' is neither time"):
        write_volume(
            str(tmp_path / "b.ome.tif"), volume[None], {"name": "x", "axis_labels": "czyx"}
        )
    path = tmp_path / "plain.ome.tif"  # a layer of another origin: sizes from um scales
    write_volume(
        str(path),
        volume,
        {"scale": VOXEL, "translate": (-6.0, 0, 0), "units": UM, "axis_labels": "zyx"},
    )
    _, kwargs, _ = only(layers_of(path))
    assert kwargs["scale"] == VOXEL and kwargs["metadata"]["fgat"]["depths_um"] == DEPTHS


@pytest.mark.slow
def test_outputs_of_fgat_commands(made):
    """simulate, psf, calibrate and deconvolve (up and down), read as their layers."""
    from fgat.instrument.calibration import read_calibration
    from fgat.io.images import read_voxel_size
    from fgat.optics.systems import load_system

    voxel = tuple(load_system("small").grid_voxel_size_um(DEPTHS))
    data, kwargs, _ = only(layers_of(made["psf"]))
    assert data.shape[:2] == (7, 5) and kwargs["axis_labels"] == ("view", "z", "y", "x")
    assert kwargs["scale"] == (1.0, *voxel) and kwargs["translate"][1] == -6.0
    assert kwargs["metadata"]["fgat"]["depths_um"] == DEPTHS
    for name in ("psf.ome.tif", "truth.ome.tif"):
        _, kwargs, _ = only(layers_of(made["sim"] / name))
        assert kwargs["metadata"]["kind"] == ("psf" if name == "psf.ome.tif" else "volume")
        assert kwargs["translate"][-3] == -6.0
    for name in ("sensor.ome.tif", "views.ome.tif"):  # images, not volumes: not the reader's
        assert get_reader(str(made["sim"] / name)) is None
    shown = {}
    for axis in ("up", "down"):
        data, kwargs, _ = only(layers_of(made[axis]))
        sizes = read_voxel_size(made[axis])
        assert kwargs["scale"] == tuple(sizes[a] for a in "ZYX")
        assert kwargs["translate"] == (-6.0, 0.0, 0.0)
        assert kwargs["metadata"]["recorded_depth_axis"] == axis
        shown[axis] = np.asarray(data)
    np.testing.assert_array_equal(shown["down"], read_tiff(made["down"])[::-1])
    np.testing.assert_allclose(shown["down"], shown["up"], rtol=1e-4, atol=1e-4 * shown["up"].max())
    layers = layers_of(made["calibration"])
    assert [kind for _, _, kind in layers] == ["image", "points", "shapes"]
    calibration = read_calibration(made["calibration"])
    np.testing.assert_array_equal(layers[0][0], read_tiff(made["sim"] / "sensor.ome.tif"))
    np.testing.assert_array_equal(layers[1][0], calibration.centers)
    np.testing.assert_allclose(
        np.mean(layers[2][0], axis=1), calibration.lattice.centers(7), atol=1e-9
    )


@pytest.mark.slow
def test_results_folder_of_a_fit(tmp_path):
    """A 3-step static fit on a noise-free phantom: volume, SHB and truth aligned, the truth in
    counts (its forward projection through the phantom's PSF is the measurement in counts)."""
    import lightning.pytorch as pl
    import torch

    from fgat.app.callbacks import ReconstructionArtifacts
    from fgat.app.datamodules import PhantomDataModule
    from fgat.app.modules import StaticModule
    from fgat.recon import phantom_scene
    from fgat.sim.simulation import SimulationConfig

    trainer = pl.Trainer(
        max_steps=3,
        default_root_dir=tmp_path,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        accelerator="cpu",
        enable_checkpointing=False,
        callbacks=[ReconstructionArtifacts()],
    )
    module = StaticModule(
        n_gaussians=50, init_iterations=3, baseline_iterations=3, densification={"enabled": False}
    )
    trainer.fit(module, PhantomDataModule(SIMULATION))
    folder = tmp_path / "results" / "latest"
    layers = layers_of(folder)
    assert [kwargs["name"] for _, kwargs, _ in layers] == [
        "reconstruction (latest)",
        "SHB baseline (latest)",
        "ground truth (latest)",
    ]
    voxel = tuple(module.engine.scene.voxel_size_um)
    for _, kwargs, _ in layers:
        assert kwargs["scale"] == pytest.approx(voxel) and kwargs["translate"] == (-6.0, 0, 0)
    scene = phantom_scene(SimulationConfig(**SIMULATION))
    truth = torch.from_numpy(np.asarray(layers[2][0], dtype=np.float32))
    operator = scene.operator(torch.from_numpy(scene.psf))
    projected = operator.forward(operator.pad(truth)).numpy()
    counts = scene.measurement * scene.scale
    assert np.linalg.norm(projected - counts) < 1e-3 * np.linalg.norm(counts)
