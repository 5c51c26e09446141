"""Bad input to ``fgat analyze crossinfo|fwhm|cytometry|track``: one line naming the option or
file, exit code 2, within seconds and before any detection; no output folder or partial file
left behind by a failed run."""

import csv
import errno
import math
import time

import numpy as np
import pandas as pd
import pytest
import yaml

import fgat.analysis.cytometry
import fgat.analysis.tracking
import fgat.app.crossinfo_tables  # noqa: F401  imported here: the timings exclude imports
from fgat._core import resources
from fgat.analysis.scales import BALL_DIAMETER_PER_SIGMA, check_length_um
from fgat.app.cli import main
from fgat.io.images import write_tiff

CELL_VOXEL_UM = (1.0, 0.5, 0.5)
CELL_SHAPE = (16, 40, 40)  # extent (16, 20, 20) um
NUCLEI_UM = np.array([[8.0, 4.0, 4.0], [7.5, 4.5, 15.5], [8.5, 10.0, 10.0], [8.0, 16.0, 4.5]])
NUCLEI_UM = np.vstack([NUCLEI_UM, [[7.0, 15.5, 15.0]]])  # 5 nuclei, >= 6 um apart
POSITIVE = [1, 3]  # the nuclei with a marker signal
TRACK_VOXEL_UM = (2.0, 0.5, 0.5)
TRACK_SHAPE = (12, 48, 48)  # extent (24, 24, 24) um
TRACK_SIGMA_UM = np.array([2.0, 1.0, 1.0])
CELLS_UM = np.array(
    [[10.0, 5.0, 5.0], [12.0, 5.5, 17.0], [9.0, 12.0, 11.0], [13.0, 19.0, 5.5], [11.0, 18.5, 18.0]]
)
QUICK_S = 2.0


def _gaussians(shape, voxel_um, centres_um, sigma_um) -> np.ndarray:
    """Unit Gaussian blobs of s.d. ``sigma_um`` at ``centres_um`` on voxel centres
    ``(i + 0.5) * voxel``."""
    axes = [(np.arange(n) + 0.5) * v for n, v in zip(shape, voxel_um)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    volume = np.zeros(shape)
    for centre in centres_um:
        volume += np.exp(-0.5 * np.sum(((grid - centre) / sigma_um) ** 2, axis=-1))
    return volume


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    """Tiny OME-TIFF inputs: 5 nuclei and a marker on 2 of them; a 3-frame series of 5 cells
    drifting 0.3 um per frame; a tube image and segment tables; crossinfo configs."""
    folder = tmp_path_factory.mktemp("analyze")
    rng = np.random.default_rng(0)
    nuclei = _gaussians(CELL_SHAPE, CELL_VOXEL_UM, NUCLEI_UM, 1.0)
    marker = _gaussians(CELL_SHAPE, CELL_VOXEL_UM, NUCLEI_UM[POSITIVE], 1.0)
    for name, volume in (("nuclei", nuclei), ("marker", marker)):
        noisy = volume + 0.1 + 0.01 * rng.standard_normal(volume.shape)
        write_tiff(folder / f"{name}.ome.tif", noisy, axes="ZYX", voxel_size_um=CELL_VOXEL_UM)
    frames = [
        _gaussians(TRACK_SHAPE, TRACK_VOXEL_UM, CELLS_UM + 0.3 * t, TRACK_SIGMA_UM)
        for t in range(3)
    ]
    series = np.stack(frames) + 0.01 * rng.standard_normal((3, *TRACK_SHAPE))
    write_tiff(folder / "series.ome.tif", series, axes="TZYX", voxel_size_um=TRACK_VOXEL_UM)
    x = np.arange(64)
    tube = np.tile(np.exp(-0.5 * ((x - 31.3) / 2.0) ** 2) + 0.1, (64, 1))
    write_tiff(folder / "tube.ome.tif", tube, axes="YX", voxel_size_um=(0.1, 0.1))
    header = "center_y,center_x,axis_angle_rad,half_length_px\n"
    good = f"40,31,{math.pi / 2},15\n"
    for name, body in {
        "segments": good,
        "letter": good + "20,a,1.5708,15\n",
        "blank": good + "20,,1.5708,15\n",
        "infinite": "inf,31,1.5708,15\n",
        "short": good + "20,31\n",
        "negative_length": "40,31,1.5708,-15\n",
    }.items():
        (folder / f"{name}.csv").write_text(header + body)
    scene = {"system": "small", "depths_um": "-3:3:3", "view_size": 32, "seed": 0}
    scene["phantom"] = {"kind": "beads", "n_beads": 3, "sigma": 1.0}
    configs = {"huge": {"scene": {**scene, "view_size": 20000}, "refits": 2}}
    for name, config in configs.items():
        (folder / f"{name}.yaml").write_text(yaml.safe_dump(config))
    (folder / "empty.yaml").write_text("")
    (folder / "comments.yaml").write_text("# nothing set\n")
    (folder / "empty_mapping.yaml").write_text("{}\n")
    return folder


def _refused(capsys, argv, *expected, seconds=QUICK_S) -> str:
    """Run ``fgat`` on ``argv``: exit code 2, within ``seconds``, one line on stderr that holds
    every ``expected`` text; returns the line."""
    start = time.perf_counter()
    assert main(argv) == 2
    elapsed = time.perf_counter() - start
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    for text in expected:
        assert text in lines[0], (text, lines[0])
    assert elapsed < seconds, (elapsed, lines[0])
    return lines[0]


def _track(d, out, diameter=("14", "5.5", "5.5"), *extra):
    return [
        "analyze",
        "track",
        "--series",
        str(d / "series.ome.tif"),
        "--frame-interval-s",
        "1",
        "--diameter-um",
        *diameter,
        "--search-range-um",
        "2",
        "--minmass",
        "1",
        "--out",
        str(out),
        *extra,
    ]


def _cytometry(d, out, *extra, sigma="1.0"):
    return [
        "analyze",
        "cytometry",
        "--nuclei",
        str(d / "nuclei.ome.tif"),
        "--marker",
        f"M={d / 'marker.ome.tif'}",
        "--sigma-um",
        sigma,
        "--match-radius-um",
        "1.5",
        "--threshold",
        "M=0.3",
        "--out",
        str(out),
        *extra,
    ]


def _fwhm(d, out, segments="segments", *extra):
    return [
        "analyze",
        "fwhm",
        "--image",
        str(d / "tube.ome.tif"),
        "--segments",
        str(d / f"{segments}.csv"),
        "--out",
        str(out),
        *extra,
    ]


# ------------------------------------------------------------------------ lengths


@pytest.mark.parametrize(
    "diameter, expected",
    [
        (["0.001"], ["--diameter-um 0.001 um", "below 2 voxels of 0.5 um", "expected 1 to 24 um"]),
        (["1e6"], ["--diameter-um 1e+06 um", "beyond the volume's extent of 24 um"]),
        (["14", "5.5", "30"], ["--diameter-um (14, 5.5, 30) um", "along x 30 um", "to 24 um"]),
        (["40", "5.5", "5.5"], ["along z 40 um", "extent of 24 um"]),
    ],
    ids=["tiny", "huge", "wider-than-x", "taller-than-z"],
)
def test_track_diameter_outside_the_volume_is_refused(d, tmp_path, capsys, diameter, expected):
    out = tmp_path / "out"
    line = _refused(capsys, _track(d, out, diameter), *expected)
    assert "voxel size (2, 0.5, 0.5) um" in line and "extent (24, 24, 24) um" in line
    assert str(d / "series.ome.tif") in line
    assert not out.exists()


def test_track_search_range_beyond_the_volume_is_refused(d, tmp_path, capsys):
    argv = _track(d, tmp_path / "out")
    argv[argv.index("--search-range-um") + 1] = "1e6"
    _refused(capsys, argv, "--search-range-um 1e+06 um", "extent of 24 um")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "option, value, expected",
    [
        ("--sigma-um", "1500", ["--sigma-um 1500 um", "beyond the volume's extent of 20 um"]),
        ("--sigma-um", "1e6", ["--sigma-um 1e+06 um", "to 5.774 um"]),
        ("--sigma-um", "0.01", ["--sigma-um 0.01 um", "below 2 voxels of 0.5 um"]),
        ("--marker-sigma-um", "50", ["--marker-sigma-um 50 um", "extent of 20 um"]),
        ("--match-radius-um", "1e6", ["--match-radius-um 1e+06 um", "extent of 20 um"]),
    ],
    ids=["sigma-1500", "sigma-1e6", "sigma-tiny", "marker-sigma", "match-radius"],
)
def test_cytometry_lengths_outside_the_volume_are_refused(
    d, tmp_path, capsys, option, value, expected
):
    argv = _cytometry(d, tmp_path / "out")
    if option in argv:
        argv[argv.index(option) + 1] = value
    else:
        argv += [option, value]
    line = _refused(capsys, argv, *expected)
    assert "voxel size (1, 0.5, 0.5) um" in line and "extent (16, 20, 20) um" in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0"])
def test_non_finite_or_non_positive_lengths_are_refused(d, tmp_path, capsys, value):
    for argv, option in (
        (_track(d, tmp_path / "t", [value]), "--diameter-um"),
        (_cytometry(d, tmp_path / "c", sigma=value), "--sigma-um"),
    ):
        with pytest.raises(SystemExit) as stop:  # argparse's refusal of the option's type
            main(argv)
        assert stop.value.code == 2
        message = capsys.readouterr().err
        assert option in message and "finite number > 0" in message
    assert not (tmp_path / "t").exists() and not (tmp_path / "c").exists()


def test_check_length_um_range_against_brute_force():
    """The valid range: D = factor * value with 2 * voxel <= D (y, x) and D <= extent (axes)."""
    voxel, shape = (2.0, 0.5, 0.25), (10, 40, 80)  # extent (20, 20, 20) um
    for value in np.geomspace(1e-3, 1e3, 61):
        for factor, axes in ((1.0, "ZYX"), (BALL_DIAMETER_PER_SIGMA, "YX")):
            diameter = factor * value
            valid = 2 * 0.5 <= diameter <= 20.0
            try:
                check_length_um("L", value, voxel, shape, diameter_per_value=factor, axes=axes)
                accepted = True
            except ValueError:
                accepted = False
            assert accepted == valid, (value, factor)
    np.testing.assert_allclose(check_length_um("L", (14, 5.5, 5.5), voxel, shape), [14.0, 5.5, 5.5])
    for bad in (math.nan, math.inf, -1.0, 0.0, (1.0, 2.0), "a"):
        with pytest.raises(ValueError, match="L must be one or three"):
            check_length_um("L", bad, voxel, shape)


def test_library_detectors_check_lengths_too():
    volume = _gaussians(CELL_SHAPE, CELL_VOXEL_UM, NUCLEI_UM, 1.0)
    with pytest.raises(ValueError, match="sigma_um 1500 um.*extent of 20 um"):
        fgat.analysis.cytometry.detect_blobs(
            volume, voxel_size_um=CELL_VOXEL_UM, sigma_um=1500, threshold=0.2
        )
    with pytest.raises(ValueError, match="diameter_um 0.001 um.*below 2 voxels"):
        fgat.analysis.tracking.track(
            np.stack([volume, volume]),
            voxel_size_um=CELL_VOXEL_UM,
            frame_interval_s=1.0,
            diameter_um=0.001,
            search_range_um=1.0,
        )


# ---------------------------------------------------------------- valid lengths still work


def test_valid_lengths_count_the_blobs(d, tmp_path, capsys):
    """5 blobs in, 5 cells and 5 tracks out, each where it was put."""
    assert main(_cytometry(d, tmp_path / "cyto")) == 0
    cells = pd.read_csv(tmp_path / "cyto" / "cells.csv")
    assert len(cells) == len(NUCLEI_UM)
    found = cells[["z", "y", "x"]].to_numpy()
    nearest = np.argmin(np.linalg.norm(found[:, None] - NUCLEI_UM[None], axis=-1), axis=1)
    assert sorted(nearest) == list(range(len(NUCLEI_UM)))
    assert np.all(np.linalg.norm(found - NUCLEI_UM[nearest], axis=1) < 0.5)
    assert sorted(nearest[cells["class"] == "M+"]) == POSITIVE
    assert "5 cells" in capsys.readouterr().out
    assert main(_track(d, tmp_path / "track")) == 0
    tracks = pd.read_csv(tmp_path / "track" / "trajectories.csv")
    assert tracks["particle"].nunique() == len(CELLS_UM) and len(tracks) == 3 * len(CELLS_UM)
    first = tracks[tracks["frame"] == 0][["z", "y", "x"]].to_numpy()
    distance = np.linalg.norm(first[:, None] - CELLS_UM[None], axis=-1).min(axis=1)
    assert np.all(distance < 0.5)
    speeds = pd.read_csv(tmp_path / "track" / "speeds.csv")
    # 0.3 um per frame on every axis; z is sampled at 2 um, so its centroid locks to voxels a little
    np.testing.assert_allclose(speeds["mean_speed_um_s"], 0.3 * math.sqrt(3), atol=0.08)


# ----------------------------------------------------------------------------- fwhm


@pytest.mark.parametrize(
    "segments, expected",
    [
        ("letter", "line 3 (segment 1), field center_x must be a finite number, got 'a'"),
        ("blank", "line 3 (segment 1), field center_x must be a finite number, got ''"),
        ("infinite", "line 2 (segment 0), field center_y must be a finite number, got 'inf'"),
        ("short", "line 3 (segment 1), field axis_angle_rad must be a finite number, got ''"),
        ("negative_length", "line 2 (segment 0), field half_length_px must be a finite number > 0"),
    ],
)
def test_fwhm_segment_numbers_name_file_line_and_field(d, tmp_path, capsys, segments, expected):
    line = _refused(capsys, _fwhm(d, tmp_path / "out", segments), expected)
    assert f"--segments {d / f'{segments}.csv'}" in line
    assert not (tmp_path / "out").exists()


def test_fwhm_failed_run_leaves_no_folder(d, tmp_path, capsys):
    flat = tmp_path / "flat.ome.tif"
    write_tiff(flat, np.full((64, 64), 0.5) + np.arange(64) * 1e-3, voxel_size_um=(0.1, 0.1))
    argv = _fwhm(d, tmp_path / "new" / "out")
    argv[argv.index("--image") + 1] = str(flat)
    _refused(capsys, argv, "no segment gave a width", seconds=10)
    assert not (tmp_path / "new").exists()


# ------------------------------------------------------------------ writes that fail


class _FullDisk:
    """A ``csv.writer`` whose ``writerows`` writes the first row, then fails as a full disk."""

    def __init__(self, handle, *args, **kwargs):
        self.writer = _REAL_WRITER(handle, *args, **kwargs)
        self.handle = handle

    def writerow(self, row):
        return self.writer.writerow(row)

    def writerows(self, rows):
        for row in rows:
            self.writer.writerow(row)
            self.handle.flush()
            raise OSError(errno.ENOSPC, "No space left on device")


_REAL_WRITER = csv.writer


def test_disk_full_mid_csv_leaves_no_partial_widths_csv(d, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    assert main(_fwhm(d, out)) == 0
    before = (out / "widths.csv").read_bytes()
    (out / "notes.txt").write_text("mine")
    monkeypatch.setattr(csv, "writer", _FullDisk)
    line = _refused(
        capsys, _fwhm(d, out, "segments", "--overwrite"), str(out / "widths.csv"), seconds=10
    )
    assert "No space left on device" in line
    assert (out / "widths.csv").read_bytes() == before  # the previous table, whole
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "widths.csv", "widths.png"]
    fresh = tmp_path / "fresh"
    _refused(capsys, _fwhm(d, fresh), str(fresh / "widths.csv"), seconds=10)
    assert not fresh.exists()


def test_disk_full_on_a_summary_names_it_and_removes_the_run(d, tmp_path, capsys, monkeypatch):
    import fgat.io.files

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fgat.io.files, "write_json", full)
    out = tmp_path / "cyto"
    line = _refused(capsys, _cytometry(d, out), f"cannot write {out / 'summary.json'}", seconds=30)
    assert "No space left on device" in line
    assert not out.exists()  # cells.csv and counts.csv of the failed run went with the folder
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "notes.txt").write_text("mine")
    _refused(capsys, _cytometry(d, existing), "summary.json", seconds=30)
    assert [p.name for p in existing.iterdir()] == ["notes.txt"]


# -------------------------------------------------------------------------- crossinfo


def _crossinfo(d, config, out):
    return ["analyze", "crossinfo", "--config", str(d / config), "--out", str(out)]


def test_crossinfo_memory_is_estimated_before_the_scene(d, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda device=None: 16 * 2**30)
    line = _refused(
        capsys,
        _crossinfo(d, "huge.yaml", tmp_path / "out"),
        "(3, 20000, 20000) (Z, Y, X)",
        "need about",
        "this machine has 17.2 GB available",
        "view_size",
    )
    assert "TB" in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("config", ["empty.yaml", "comments.yaml", "empty_mapping.yaml"])
def test_crossinfo_empty_config_is_refused(d, tmp_path, capsys, config):
    _refused(
        capsys,
        _crossinfo(d, config, tmp_path / "out"),
        f"--config {d / config}: the file sets no field",
        "configs/crossinfo.yaml",
    )
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------- voxel sizes


def test_voxel_sizes_in_nm_are_read_in_um(d, tmp_path, capsys):
    """An OME-TIFF whose sizes are in nm: the lengths are checked against the sizes in um."""
    import tifffile

    series = tifffile.imread(d / "series.ome.tif")
    path = tmp_path / "series_nm.ome.tif"
    sizes = {f"PhysicalSize{a}": 1000 * v for a, v in zip("ZYX", TRACK_VOXEL_UM)}
    units = {f"PhysicalSize{a}Unit": "nm" for a in "ZYX"}
    tifffile.imwrite(path, series, ome=True, metadata={"axes": "TZYX", **sizes, **units})
    argv = _track(d, tmp_path / "out", ["0.001"])
    argv[argv.index("--series") + 1] = str(path)
    _refused(capsys, argv, "voxel size (2, 0.5, 0.5) um", "extent (24, 24, 24) um")


def test_zero_voxel_size_in_the_file_is_refused(d, tmp_path, capsys):
    path = tmp_path / "flat_pixels.ome.tif"
    write_tiff(path, np.ones((2, 4, 8, 8)), axes="TZYX", voxel_size_um=(2.0, 0.0, 0.5))
    argv = _track(d, tmp_path / "out")
    argv[argv.index("--series") + 1] = str(path)
    _refused(capsys, argv, f"--series {path}: PhysicalSizeY (um) must be a finite number > 0")
    assert not (tmp_path / "out").exists()
