import numpy as np
import pytest
import scipy.io

from fgat._core.conventions import DEPTH_AXES, VIEW_ORDER, orient_volume
from fgat.io.files import atomic_path
from fgat.io.images import (
    read_image,
    read_mat,
    read_tiff,
    read_voxel_size,
    volume_entries,
    volume_metadata,
    write_tiff,
)
from tests.conftest import SHARED_DATA


def test_ome_tiff_round_trip_with_voxel_size(tmp_path):
    volume = np.random.default_rng(0).random((4, 6, 5)).astype(np.float32)
    path = write_tiff(tmp_path / "v.ome.tif", volume, axes="ZYX", voxel_size_um=(1.5, 0.975, 0.975))
    np.testing.assert_array_equal(read_tiff(path, ndim=3), volume)
    assert read_voxel_size(path) == {"Z": 1.5, "Y": 0.975, "X": 0.975}
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_float64_is_stored_as_float32(tmp_path):
    """The values are numpy's float32 rounding of the float64 array, read back by fgat and by
    tifffile alike."""
    import tifffile

    volume = np.random.default_rng(3).normal(0.0, 1e3, (2, 3, 4, 5))
    path = write_tiff(tmp_path / "p.ome.tif", volume, axes="CZYX")
    read = read_tiff(path)
    assert read.dtype == np.float32
    np.testing.assert_array_equal(read, volume.astype(np.float32))
    np.testing.assert_array_equal(tifffile.imread(path), volume.astype(np.float32))


def test_failed_write_keeps_existing_file(tmp_path):
    target = tmp_path / "result.tif"
    target.write_bytes(b"user data")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as temporary:
            temporary.write_bytes(b"half")
            raise RuntimeError("killed")
    assert target.read_bytes() == b"user data"
    assert list(tmp_path.iterdir()) == [target]


def test_errors_name_file_and_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.tif"):
        read_tiff(tmp_path / "missing.tif")
    good = write_tiff(tmp_path / "good.ome.tif", np.ones((8, 8), np.float32))
    truncated = tmp_path / "truncated.tif"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ValueError, match="truncated.tif.*truncated or corrupt"):
        read_tiff(truncated)
    with pytest.raises(ValueError, match="good.ome.tif: expected 3D \\(Z, Y, X\\), got 2D"):
        read_tiff(good, ndim=3, axes="(Z, Y, X)")
    nan = write_tiff(tmp_path / "nan.ome.tif", np.array([[1.0, np.nan]], np.float32))
    with pytest.raises(
        ValueError, match="nan.ome.tif: 1 NaN/Inf value\\(s\\), first at index \\(0, 1\\)"
    ):
        read_tiff(nan)
    negative = write_tiff(tmp_path / "neg.ome.tif", np.array([[1.0, -2.0]], np.float32))
    with pytest.raises(ValueError, match="neg.ome.tif: expected non-negative"):
        read_tiff(negative, nonnegative=True)
    with pytest.raises(ValueError, match="unsupported file type"):
        read_image(tmp_path / "data.png")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        write_tiff(tmp_path / "nowhere" / "x.tif", np.ones((2, 2)))


def test_mat_reading(tmp_path):
    path = tmp_path / "centers.mat"
    scipy.io.savemat(path, {"centers": np.arange(14.0).reshape(7, 2), "other": np.ones(3)})
    np.testing.assert_array_equal(read_mat(path, "centers"), np.arange(14.0).reshape(7, 2))
    with pytest.raises(ValueError, match="name the one to read"):
        read_mat(path)
    with pytest.raises(ValueError, match="no variable 'x'"):
        read_mat(path, "x")
    np.testing.assert_array_equal(read_image(path, key="other", ndim=2), np.ones((1, 3)))


@pytest.mark.skipif(
    not (SHARED_DATA / "reticular1").exists(), reason="external 3DGAT data not present"
)
def test_reads_the_3dgat_scene():
    """The published scene's centres and views, value for value as scipy and tifffile read
    them."""
    import tifffile

    folder = SHARED_DATA / "reticular1"
    centers = read_mat(folder / "MLcenter_idxes.mat")
    (expected,) = [
        v for k, v in scipy.io.loadmat(folder / "MLcenter_idxes.mat").items() if k[:2] != "__"
    ]
    assert centers.shape == (7, 2)
    np.testing.assert_array_equal(centers, expected)
    sample = read_tiff(folder / "sample.tif", ndim=3, nonnegative=True)
    assert sample.shape == (7, 200, 200)
    np.testing.assert_array_equal(sample, tifffile.imread(folder / "sample.tif"))


def test_command_line_scalars():
    from fgat._core.validation import parse_overrides, parse_scalar

    assert [parse_scalar(t) for t in ("50", "1e-3", "false", "null", "beads", "-22.5:22.5:31")] == [
        50,
        1e-3,
        False,
        None,
        "beads",
        "-22.5:22.5:31",
    ]
    assert parse_overrides({"kind": "beads", "n": "4", "5": "0.1", "shift": ["0.5", "1"]}) == {
        "kind": "beads",
        "n": 4,
        5: 0.1,
        "shift": [0.5, 1],
    }


def test_write_csv_takes_mappings_or_sequences(tmp_path):
    import csv

    from fgat.io.files import write_csv

    path = write_csv(tmp_path / "t.csv", ["a", "b"], [{"b": 2, "a": 1, "extra": 9}, [3, 4.5]])
    with open(path, newline="") as handle:
        assert list(csv.reader(handle)) == [["a", "b"], ["1", "2"], ["3", "4.5"]]
    assert [p.name for p in tmp_path.iterdir()] == ["t.csv"]  # no temporary left behind


def test_a_single_time_point_series_reads_back_with_its_time_axis(tmp_path):
    from fgat.io.images import read_series

    one = np.arange(60, dtype=np.float32).reshape(1, 3, 4, 5)
    write_tiff(tmp_path / "one.ome.tif", one, axes="TZYX")
    assert read_tiff(tmp_path / "one.ome.tif").shape == (3, 4, 5)  # what TIFF readers do
    np.testing.assert_array_equal(read_series(tmp_path / "one.ome.tif"), one)
    many = np.arange(120, dtype=np.float32).reshape(2, 3, 4, 5)
    write_tiff(tmp_path / "many.ome.tif", many, axes="TZYX")
    np.testing.assert_array_equal(read_series(tmp_path / "many.ome.tif"), many)
    write_tiff(tmp_path / "image.ome.tif", one[0, 0])
    with pytest.raises(ValueError, match="image.ome.tif: expected 3D or 4D"):
        read_series(tmp_path / "image.ome.tif")


def test_volume_metadata_round_trip_up_and_down(tmp_path):
    volume = np.arange(4 * 3 * 2, dtype=np.float32).reshape(4, 3, 2)  # every plane distinct
    depths = [-9.0, -3.0, 3.0, 9.0]
    voxel = (6.0, 0.975, 0.975)
    up = write_tiff(
        tmp_path / "up.ome.tif",
        volume,
        axes="ZYX",
        voxel_size_um=voxel,
        metadata=volume_entries("up", depths),
    )
    down = write_tiff(
        tmp_path / "down.ome.tif",
        orient_volume(volume, "down"),
        axes="ZYX",
        voxel_size_um=voxel,
        metadata=volume_entries("down", depths[::-1]),
    )
    assert volume_metadata(up) == {
        "content": "volume",
        "depth_axis": "up",
        "depth_axis_convention": DEPTH_AXES["up"],
        "depths_um": [-9.0, -3.0, 3.0, 9.0],
        "view_order": VIEW_ORDER,
    }
    recorded = volume_metadata(down)
    assert recorded["depth_axis"] == "down" and recorded["depths_um"] == [9.0, 3.0, -3.0, -9.0]
    assert recorded["depth_axis_convention"].startswith("Z is flipped: index k holds")
    assert recorded["view_order"] == VIEW_ORDER
    assert read_voxel_size(down) == {"Z": 6.0, "Y": 0.975, "X": 0.975}
    np.testing.assert_array_equal(read_tiff(down), volume[::-1])
    for index, depth in enumerate(recorded["depths_um"]):  # the same depth, the same plane
        np.testing.assert_array_equal(read_tiff(down)[index], volume[depths.index(depth)])
    series = write_tiff(  # a merged series keeps what the first file recorded
        tmp_path / "series.ome.tif",
        np.stack([volume[::-1]] * 2)[:, None],
        axes="TCZYX",
        metadata=recorded,
    )
    assert volume_metadata(series) == recorded


def test_volume_metadata_absent_wrong_or_damaged(tmp_path):
    import tifffile

    plain = write_tiff(tmp_path / "plain.ome.tif", np.ones((3, 4, 4), np.float32))
    assert volume_metadata(plain) == {}
    unknown = write_tiff(
        tmp_path / "unknown.ome.tif",
        np.ones((3, 4, 4), np.float32),
        metadata=volume_entries("down"),
    )
    assert volume_metadata(unknown)["depths_um"] is None
    assert volume_metadata(unknown)["depth_axis_convention"] == DEPTH_AXES["down"]
    with pytest.raises(ValueError, match=r"cannot write .*bad.ome.tif: 2 depths_um for the Z axis"):
        write_tiff(
            tmp_path / "bad.ome.tif",
            np.ones((3, 4, 4), np.float32),
            axes="ZYX",
            metadata=volume_entries("up", [0, 1]),
        )
    with pytest.raises(ValueError, match=r"depth_axis must be one of \['up', 'down'\]"):
        volume_entries("Down")
    with pytest.raises(ValueError, match="depths_um must be finite numbers"):
        volume_entries("up", [0.0, float("nan")])
    for name, entries, message in (
        ("depths", {"depth_axis": "up", "depths_um": "[1, x]"}, "is not a list of numbers"),
        ("axis", {"depth_axis": "sideways"}, "depth_axis must be one of"),
    ):
        path = tmp_path / f"{name}.ome.tif"
        annotation = {"Namespace": "fgat.volume", "Value": entries}
        metadata = {"axes": "ZYX", "MapAnnotation": annotation}
        data = np.ones((2, 3, 3), np.float32)
        tifffile.imwrite(path, data, ome=True, metadata=metadata, photometric="minisblack")
        with pytest.raises(ValueError, match=f"{name}.ome.tif: .*{message}"):
            volume_metadata(path)
    (tmp_path / "text.tif").write_text("not a TIFF")
    with pytest.raises(ValueError, match="text.tif: not a readable TIFF file"):
        volume_metadata(tmp_path / "text.tif")
    with pytest.raises(FileNotFoundError, match="missing.tif"):
        volume_metadata(tmp_path / "missing.tif")


@pytest.mark.parametrize("unit, factor", [("nm", 1e-3), ("µm", 1.0), ("um", 1.0), ("mm", 1e3)])
def test_voxel_sizes_are_read_in_the_units_the_file_names(tmp_path, unit, factor):
    """OME's PhysicalSize*Unit converts to um (OME's default unit, no Unit attribute, is um)."""
    import tifffile

    path = tmp_path / "v.ome.tif"
    sizes = {"PhysicalSizeZ": 1500.0, "PhysicalSizeY": 975.0, "PhysicalSizeX": 975.0}
    units = {f"{key}Unit": unit for key in sizes}
    metadata = {"axes": "ZYX", **sizes, **units}
    tifffile.imwrite(path, np.zeros((2, 8, 9), np.float32), ome=True, metadata=metadata)
    assert read_voxel_size(path) == pytest.approx(
        {"Z": 1500.0 * factor, "Y": 975.0 * factor, "X": 975.0 * factor}
    )
    bare = tmp_path / "bare.ome.tif"
    tifffile.imwrite(
        bare, np.zeros((2, 8, 9), np.float32), ome=True, metadata={"axes": "ZYX", **sizes}
    )
    assert read_voxel_size(bare) == pytest.approx({"Z": 1500.0, "Y": 975.0, "X": 975.0})


def test_a_voxel_size_that_is_no_length_is_refused_naming_file_and_field(tmp_path):
    import tifffile

    path = tmp_path / "v.ome.tif"
    metadata = {"axes": "ZYX", "PhysicalSizeX": 1.0, "PhysicalSizeXUnit": "s"}
    tifffile.imwrite(path, np.zeros((2, 8, 9), np.float32), ome=True, metadata=metadata)
    with pytest.raises(ValueError, match=r"v\.ome\.tif: PhysicalSizeXUnit is in 's', expected"):
        read_voxel_size(path)
