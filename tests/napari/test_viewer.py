"""fgat's files opened in a napari viewer through the plugin (``viewer.open(path,
plugin="fgat")``), and a layer saved back with the plugin's writer."""

import numpy as np
import pytest

pytest.importorskip("napari")

from fgat.io.images import read_tiff, volume_entries, write_tiff  # noqa: E402
from fgat.io.zarr_series import ZarrSeriesWriter  # noqa: E402
from fgat.napari.writer import write_volume  # noqa: E402
from tests.napari.conftest import DEPTHS, VOXEL  # noqa: E402

UM = ("micrometer",) * 3


def test_viewer_opens_fgat_files_through_the_plugin(make_napari_viewer, tmp_path, volume):
    down = write_tiff(
        tmp_path / "down.ome.tif",
        volume[::-1],
        voxel_size_um=VOXEL,
        metadata=volume_entries("down", DEPTHS[::-1]),
    )
    with ZarrSeriesWriter(
        tmp_path / "two.ome.zarr",
        (2, *volume.shape),
        voxel_size_um=VOXEL,
        time_interval_s=2.0,
        metadata=volume_entries("up", DEPTHS),
        channel_names=["GFP", "mCherry"],
    ) as writer:
        writer.append(np.stack([volume, 2 * volume]))
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(down), plugin="fgat")
    np.testing.assert_array_equal(layer.data, volume)
    np.testing.assert_allclose(layer.scale, VOXEL)
    np.testing.assert_allclose(layer.translate, (-6.0, 0.0, 0.0))
    assert [str(unit) for unit in layer.units] == list(UM)
    assert tuple(layer.axis_labels) == ("z", "y", "x") and layer.name == "down"
    channels = viewer.open(str(tmp_path / "two.ome.zarr"), plugin="fgat")
    assert [c.name for c in channels] == ["two GFP", "two mCherry"]
    for channel in channels:
        np.testing.assert_allclose(channel.scale, (2.0, *VOXEL))
        assert [str(unit) for unit in channel.units] == ["second", *UM]
        assert channel.metadata["fgat"]["depths_um"] == DEPTHS
    copy = tmp_path / "copy.ome.tif"
    data, state, _ = layer.as_layer_data_tuple()
    assert write_volume(str(copy), data, state) == [str(copy)]
    np.testing.assert_array_equal(read_tiff(copy), volume[::-1])  # written as recorded: down
    (again,) = viewer.open(str(copy), plugin="fgat")
    np.testing.assert_allclose(again.translate, layer.translate)
    assert again.metadata["fgat"] == layer.metadata["fgat"]


def test_viewer_opens_a_calibration_folder(make_napari_viewer, tmp_path):
    from fgat.instrument.calibration import Calibration, save_calibration
    from fgat.instrument.lattice import HexLattice

    lattice = HexLattice((40.0, 52.0), 18.0, 7.0)
    write_tiff(tmp_path / "mla.tif", np.ones((96, 104), np.float32))
    folder = tmp_path / "calibration"
    folder.mkdir()
    save_calibration(Calibration(lattice.centers(7), lattice, source="mla.tif"), folder)
    viewer = make_napari_viewer()
    image, points, cells = viewer.open(str(folder), plugin="fgat")
    assert [layer.name for layer in (image, points, cells)] == [
        "calibration: mla.tif",
        "calibration: lenslet centres",
        "calibration: lenslet lattice",
    ]
    np.testing.assert_allclose(points.data, lattice.centers(7), atol=1e-6)
    assert list(points.features["view"]) == list(range(7))
    assert cells.nshapes == 7 and set(cells.shape_type) == {"polygon"}
