"""Faults of fgat's I/O layer: a full disk, a quota, a truncated TIFF, YAML that is not text or
gives a key twice. Each ends in one line naming the file (and the bytes, the key, the lines),
and nothing partial is left under the user's name."""

import errno
import json
import shutil
import time
from collections import namedtuple

import numpy as np
import pytest
import tifffile

from fgat._core.resources import DiskFullError, check_disk_space, disk_full_error, format_bytes
from fgat.io.files import write_json
from fgat.io.images import read_tiff, read_voxel_size, tiff_shape, write_tiff
from fgat.io.yaml_files import load_yaml, read_yaml
from fgat.io.zarr_series import write_zarr

Usage = namedtuple("Usage", "total used free")


def no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def over_quota(*args, **kwargs):
    raise OSError(errno.EDQUOT, "Disk quota exceeded")


def test_a_full_disk_during_a_tiff_write_is_one_line_and_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(tifffile, "imwrite", no_space)
    volume = np.zeros((4, 50, 50), np.float32)
    with pytest.raises(DiskFullError) as caught:
        write_tiff(tmp_path / "volume.ome.tif", volume)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"cannot write {tmp_path / 'volume.ome.tif'}: the disk is full")
    assert f"needs about {format_bytes(volume.nbytes)}" in message  # 40.0 kB
    assert list(tmp_path.iterdir()) == []  # neither the target nor the temporary


def test_a_quota_is_named_and_an_existing_file_is_kept(tmp_path, monkeypatch):
    target = tmp_path / "summary.json"
    target.write_text("previous")
    monkeypatch.setattr(type(target), "write_text", over_quota)
    with pytest.raises(DiskFullError, match="summary.json: the disk quota is exceeded"):
        write_json(target, {"a": 1.0})
    monkeypatch.undo()
    assert target.read_text() == "previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_other_os_errors_are_not_called_a_full_disk(tmp_path, monkeypatch):
    def denied(*args, **kwargs):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(tifffile, "imwrite", denied)
    with pytest.raises(OSError) as caught:
        write_tiff(tmp_path / "v.tif", np.zeros((2, 2), np.float32))
    assert not isinstance(caught.value, DiskFullError) and caught.value.errno == errno.EIO
    assert list(tmp_path.iterdir()) == []


def test_free_space_is_checked_before_writing(tmp_path, monkeypatch):
    volume = np.zeros((10, 100, 100), np.float32)  # 400 kB
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10**9, 10**9 - 1000, 1000))
    monkeypatch.setattr(tifffile, "imwrite", lambda *a, **k: pytest.fail("write started"))
    with pytest.raises(DiskFullError) as caught:
        write_tiff(tmp_path / "v.ome.tif", volume)
    assert str(caught.value) == (
        f"cannot write {tmp_path / 'v.ome.tif'}: needs about 400.0 kB of disk space; only "
        f"1.0 kB free in {tmp_path}; free some space or write elsewhere"
    )
    assert list(tmp_path.iterdir()) == []


def test_free_space_of_a_folder_not_made_yet_is_that_of_its_parent(tmp_path, monkeypatch):
    seen = []

    def usage(path):
        seen.append(path)
        return Usage(100, 50, 50)

    monkeypatch.setattr(shutil, "disk_usage", usage)
    check_disk_space(tmp_path / "new" / "deeper", 50)  # exactly the room left: accepted
    with pytest.raises(DiskFullError, match="needs about 51 B of disk space; only 50 B free"):
        check_disk_space(tmp_path / "new" / "deeper", 51, what="--out new/deeper")
    assert seen == [tmp_path, tmp_path]


def test_disk_full_error_names_path_bytes_and_free_room(tmp_path, monkeypatch):
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10, 8, 2_500_000))
    error = disk_full_error(tmp_path / "x.tif", OSError(errno.ENOSPC, "full"), 3_000_000)
    assert str(error) == (
        f"cannot write {tmp_path / 'x.tif'}: the disk is full (No space left on device); needs "
        "about 3.0 MB; 2.5 MB free there; free some space or write elsewhere (nothing was left "
        "under that name)"
    )


def test_a_full_disk_during_a_zarr_series_removes_the_store(tmp_path):
    def frames():
        yield np.zeros((2, 8, 8), np.float32)
        no_space()

    with pytest.raises(DiskFullError, match="series.ome.zarr: the disk is full"):
        write_zarr(tmp_path / "series.ome.zarr", frames(), axes="tzyx", voxel_size_um=(1, 1, 1))
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------- truncated TIFF
@pytest.fixture
def volume_file(tmp_path):
    rng = np.random.default_rng(0)
    return write_tiff(
        tmp_path / "volume.ome.tif",
        rng.random((5, 32, 32)).astype(np.float32),
        voxel_size_um=(2.0, 0.5, 0.5),
    )


@pytest.mark.parametrize("fraction", [0.3, 0.7, 0.99])
def test_a_truncated_tiff_is_called_so(volume_file, fraction, capsys):
    data = volume_file.read_bytes()
    cut = volume_file.with_name("cut.tif")
    cut.write_bytes(data[: int(len(data) * fraction)])
    for read in (tiff_shape, read_tiff, read_voxel_size):
        with pytest.raises(ValueError) as caught:
            read(cut)
        message = str(caught.value)
        assert message.startswith(f"{cut}: the TIFF file is truncated or corrupt (")
        assert "\n" not in message
    assert capsys.readouterr().err == ""  # tifffile's warnings are not printed besides


def test_a_whole_tiff_reads_as_written(volume_file):
    assert tiff_shape(volume_file) == ((5, 32, 32), np.dtype(np.float32))
    assert read_voxel_size(volume_file) == {"Z": 2.0, "Y": 0.5, "X": 0.5}


def test_page_data_past_the_end_of_the_file_is_refused(tmp_path):
    path = tmp_path / "plain.tif"
    tifffile.imwrite(path, np.ones((3, 16, 16), np.uint16), photometric="minisblack")
    data = path.read_bytes()
    path.write_bytes(data[:-100])
    with pytest.raises(ValueError, match="plain.tif: the TIFF file is truncated or corrupt"):
        read_tiff(path)


# ---------------------------------------------------------------------------------- YAML
@pytest.mark.parametrize(
    "text,key,first,again",
    [
        ("a: 1\nb: 2\na: 3\n", "a", 1, 3),
        ("phantom:\n  kind: beads\n  n_beads: 5\n  n_beads: 50\n", "n_beads", 3, 4),
        ("x: {k: 1, k: 2}\n", "k", 1, 1),
        ("- {a: 1}\n- a: 1\n  b: 2\n  a: 3\n", "a", 2, 4),
    ],
)
def test_a_key_given_twice_is_refused_with_both_lines(tmp_path, text, key, first, again):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as caught:
        read_yaml(path, f"config {path}")
    message = str(caught.value)
    assert message.startswith(f"config {path}: invalid YAML at line {again}, column ")
    assert f"duplicate key {key!r} at line {again} (first given at line {first})" in message


def test_merged_keys_may_be_overridden_and_plain_yaml_reads_as_pyyaml(tmp_path):
    import yaml

    text = "base: &b {a: 1, b: 2}\nc:\n  <<: *b\n  a: 5\nd: [1, 2.5, null, true]\n"
    assert load_yaml(text, "x") == yaml.safe_load(text)
    assert load_yaml(text, "x")["c"] == {"a": 5, "b": 2}


def test_a_yaml_file_that_is_not_text_is_named(tmp_path):
    path = tmp_path / "binary.yaml"
    path.write_bytes(b"system: small\n\xff\xfe\x00junk")
    with pytest.raises(ValueError) as caught:
        read_yaml(path, f"--config {path}")
    assert str(caught.value) == (
        f"--config {path}: not a UTF-8 text file (byte 0xff at offset 14); expected YAML text"
    )


def test_yaml_refusals_are_fast(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_text("".join(f"k{i}: {i}\n" for i in range(2000)) + "k7: 0\n")
    start = time.perf_counter()
    with pytest.raises(ValueError, match="duplicate key 'k7' at line 2001 \\(first given at"):
        read_yaml(path, str(path))
    assert time.perf_counter() - start < 2.0


def test_json_written_atomically_reads_back(tmp_path):
    path = write_json(tmp_path / "r.json", {"x": float("nan"), "y": [1.0, float("inf")]})
    assert json.loads(path.read_text()) == {"x": None, "y": [1.0, None]}
