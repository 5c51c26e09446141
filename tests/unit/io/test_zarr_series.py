"""Volume series as OME-Zarr: round trips, what ome-zarr-py reads, bounded memory, safe writes."""

import tracemalloc

import numpy as np
import pytest
from ome_zarr.io import parse_url
from ome_zarr.reader import Reader

from fgat.io.images import (
    read_series,
    read_time_interval,
    read_voxel_size,
    series_frames,
    volume_entries,
    volume_metadata,
    write_tiff,
)
from fgat.io.zarr_series import ZarrSeriesWriter, write_zarr

VOXEL = (1.5, 0.975, 0.975)


def test_ome_zarr_py_reads_the_series_with_its_axes_and_scales(tmp_path):
    series = np.random.default_rng(0).random((3, 2, 4, 5, 6), dtype=np.float32)
    path = write_zarr(tmp_path / "s.ome.zarr", series, voxel_size_um=VOXEL, time_interval_s=0.25)
    np.testing.assert_array_equal(read_series(path, ndim=5), series)
    assert read_voxel_size(path) == dict(zip("ZYX", VOXEL))
    (image, *_) = list(Reader(parse_url(str(path)))())
    np.testing.assert_array_equal(np.asarray(image.data[0]), series)
    axes = image.metadata["axes"]
    assert [a["name"] for a in axes] == list("tczyx")
    assert [a.get("unit") for a in axes] == ["second", None] + ["micrometer"] * 3
    assert [a["type"] for a in axes] == ["time", "channel", "space", "space", "space"]
    (scale,) = image.metadata["coordinateTransformations"][0]
    assert scale == {"type": "scale", "scale": [0.25, 1.0, *VOXEL]}


@pytest.mark.parametrize("axes", ["tzyx", "zyx"])
def test_series_without_channels_or_time_read_back_as_t_z_y_x(tmp_path, axes):
    rng = np.random.default_rng(1)
    array = rng.random((2, 3, 4, 5) if axes == "tzyx" else (3, 4, 5), dtype=np.float32)
    path = write_zarr(tmp_path / "v.ome.zarr", array, axes=axes, voxel_size_um=VOXEL)
    expected = array if axes == "tzyx" else array[None]
    np.testing.assert_array_equal(read_series(path), expected)
    (image, *_) = list(Reader(parse_url(str(path)))())
    assert "unit" not in image.metadata["axes"][0]  # frames, not seconds
    with pytest.raises(ValueError, match="axes must be 'tczyx', 'tzyx', 'czyx' or 'zyx'"):
        write_zarr(tmp_path / "w.ome.zarr", array, axes="yxz", voxel_size_um=VOXEL)


def test_frames_stream_through_one_at_a_time(tmp_path):
    """A generator of 1 MiB frames is written with the same peak of allocated memory for 16
    frames as for 4, a few frames' worth (the frame, its copy and the codec's buffers)."""
    shape = (1, 16, 128, 128)  # 1 MiB of float32
    frame_bytes = np.prod(shape) * 4

    def peak(count):
        frames = (np.full(shape, float(t), dtype=np.float32) for t in range(count))
        tracemalloc.start()
        write_zarr(tmp_path / f"{count}.ome.zarr", frames, voxel_size_um=VOXEL)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        return peak / frame_bytes

    short, long = peak(4), peak(16)
    assert long < 6 and long < 1.2 * short, (short, long)
    read = read_series(tmp_path / "16.ome.zarr")
    assert read.shape == (16, 16, 128, 128)
    np.testing.assert_array_equal(read[:, 0, 0, 0], np.arange(16, dtype=np.float32))


def test_writes_never_replace_or_leave_half_a_store(tmp_path):
    path = tmp_path / "s.ome.zarr"
    first = np.ones((2, 1, 2, 3, 3), np.float32)
    write_zarr(path, first, voxel_size_um=VOXEL)
    with pytest.raises(ValueError, match=r"s.ome.zarr: exists; choose another name"):
        write_zarr(path, 2 * first, voxel_size_um=VOXEL)
    with pytest.raises(ValueError, match=r"frame 1 has shape \(1, 2, 3, 4\), expected"):
        with ZarrSeriesWriter(path, (1, 2, 3, 3), voxel_size_um=VOXEL, overwrite=True) as writer:
            writer.append(np.zeros((1, 2, 3, 3), np.float32))
            writer.append(np.zeros((1, 2, 3, 4), np.float32))
    np.testing.assert_array_equal(read_series(path, ndim=5), first)  # the old store is whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ome.zarr"]  # no temporaries
    write_zarr(path, 2 * first, voxel_size_um=VOXEL, overwrite=True)
    np.testing.assert_array_equal(read_series(path, ndim=5), 2 * first)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ome.zarr"]
    tiff = write_tiff(tmp_path / "v.ome.zarr", first[0, 0], axes="ZYX")
    with pytest.raises(ValueError, match="exists and is not a Zarr store; it is not replaced"):
        write_zarr(tiff, first, voxel_size_um=VOXEL, overwrite=True)
    two_channels = np.ones((1, 2, 2, 3, 3), np.float32)
    write_zarr(tmp_path / "c.ome.zarr", two_channels, voxel_size_um=VOXEL)
    with pytest.raises(ValueError, match="image of 2 channels read as 4 dimensions"):
        read_series(tmp_path / "c.ome.zarr")


@pytest.mark.parametrize("frames", [1, 4])
def test_series_frames_read_one_volume_at_a_time_from_tiff_and_zarr(tmp_path, frames):
    series = np.random.default_rng(2).random((frames, 3, 4, 5), dtype=np.float32)
    tiff = write_tiff(tmp_path / "s.ome.tif", series if frames > 1 else series[0], axes=None)
    store = write_zarr(tmp_path / "s.ome.zarr", series, axes="tzyx", voxel_size_um=VOXEL)
    for path in (tiff, store):
        count, volumes = series_frames(path)
        assert count == frames
        np.testing.assert_array_equal(np.stack(list(volumes)), read_series(path))
        np.testing.assert_array_equal(read_series(path), series)


def test_zarr_keeps_the_volume_entries(tmp_path):
    entries = volume_entries("down", [-1.0, 0.0, 1.0])
    path = tmp_path / "m.ome.zarr"
    with ZarrSeriesWriter(path, (1, 3, 2, 2), voxel_size_um=VOXEL, metadata=entries) as writer:
        writer.append(np.zeros((3, 2, 2), np.float32))
    assert volume_metadata(path) == {k: v for k, v in entries.items()}


def test_channels_appended_as_volumes_chunk_by_chunk(tmp_path):
    channels = [np.full((2, 3, 4), float(c), np.float32) for c in range(3)]
    with ZarrSeriesWriter(tmp_path / "c.ome.zarr", (3, 2, 3, 4), voxel_size_um=VOXEL) as writer:
        writer.append(channels)  # a sequence of (Z, Y, X) volumes
        writer.append(np.stack(channels) + 10)
        with pytest.raises(ValueError, match=r"frame 2 has shape \(2, 2, 3, 4\), expected"):
            writer.append(channels[:2])
        with pytest.raises(ValueError, match=r"frame 2 has shape \[\(2, 3, 4\), \(2, 3, 3\)"):
            writer.append([channels[0], channels[1][..., :3], channels[2]])
    read = read_series(tmp_path / "c.ome.zarr", ndim=5)
    np.testing.assert_array_equal(read[0], np.stack(channels))
    np.testing.assert_array_equal(read[1], np.stack(channels) + 10)


@pytest.mark.slow
def test_channel_merge_holds_one_time_point_however_long_the_series(tmp_path):
    """Merging three channels' series allocates about one time point of every channel plus one
    channel's read and encoding buffers, the same for 24 frames as for 3. The codecs free their
    buffers when they do, which moves the peak by up to two volumes from one merge to the next,
    so each length takes its lowest peak of three merges; a merge that stacked the series would
    grow by 63 volumes from 3 frames to 24."""
    from fgat.app.pipeline import merge_channels

    shape = (16, 128, 128)
    volume_bytes = np.prod(shape) * 4

    def peak(count):
        rng = np.random.default_rng(count)
        series = []
        for channel in range(3):
            path = tmp_path / f"{count}_{channel}.ome.tif"
            volumes = rng.random((count, *shape), dtype=np.float32)
            write_tiff(path, volumes, axes="TZYX", time_interval_s=2.5)
            series.append(path)
        peaks = []
        for _ in range(3):
            tracemalloc.start()
            merged = merge_channels(series, tmp_path / f"{count}.ome.zarr")
            peaks.append(tracemalloc.get_traced_memory()[1] / volume_bytes)
            tracemalloc.stop()
        expected = np.stack([read_series(path) for path in series], axis=1)
        np.testing.assert_array_equal(read_series(merged, ndim=5), expected)
        assert read_time_interval(merged) == 2.5  # the channels' time axis, in seconds
        return min(peaks)

    warm = write_tiff(tmp_path / "w.ome.tif", np.zeros((2, 2, 2, 2), np.float32), axes="TZYX")
    merge_channels([warm, warm], tmp_path / "w.ome.zarr")  # the imports, before measuring
    short, long = peak(3), peak(24)
    assert long < 8 and long < short + 2, (short, long)


def test_time_interval_read_back_from_tiff_and_zarr_in_seconds(tmp_path):
    import tifffile

    series = np.zeros((3, 2, 4, 4), np.float32)
    assert read_time_interval(write_tiff(tmp_path / "s.ome.tif", series, axes="TZYX")) is None
    timed = write_tiff(tmp_path / "t.ome.tif", series, axes="TZYX", time_interval_s=0.2)
    assert read_time_interval(timed) == pytest.approx(0.2)
    tifffile.imwrite(
        tmp_path / "ms.ome.tif",
        series,
        ome=True,
        photometric="minisblack",
        metadata={"axes": "TZYX", "TimeIncrement": 40.0, "TimeIncrementUnit": "ms"},
    )  # another tool's unit
    assert read_time_interval(tmp_path / "ms.ome.tif") == pytest.approx(0.04)
    assert (
        read_time_interval(
            write_zarr(tmp_path / "f.ome.zarr", series, axes="tzyx", voxel_size_um=VOXEL)
        )
        is None
    )
    zarr = write_zarr(
        tmp_path / "s.ome.zarr", series, axes="tzyx", voxel_size_um=VOXEL, time_interval_s=0.2
    )
    assert read_time_interval(zarr) == pytest.approx(0.2)
