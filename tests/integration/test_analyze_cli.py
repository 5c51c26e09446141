"""``fgat analyze fwhm|cytometry|track`` end to end on tiny synthetic OME-TIFF inputs with known
answers, and their refusals (missing voxel sizes, wrong dimensionality, no detections, existing
outputs)."""

import json
import math

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from fgat.analysis.cytometry import cell_phantom
from fgat.app.cli import main
from fgat.io.images import read_tiff, write_tiff

AXES = ["z", "y", "x"]
PIXEL_UM = 0.1
TUBE_SIGMA_PX = 2.0
TUBE_X_PX = 31.3
MARKERS = ("CD11b", "Ferritin")
CELL_VOXEL_UM = (1.0, 0.5, 0.5)
TRACK_VOXEL_UM = np.array([2.0, 0.5, 0.5])
BLOB_SIGMA_UM = np.array([2.0, 1.0, 1.0])


def _error(capsys) -> str:
    return capsys.readouterr().err


# ---------------------------------------------------------------------------------- fwhm


def _tube_image(tmp_path, voxel_size_um=(PIXEL_UM, PIXEL_UM)):
    """A vertical Gaussian tube (s.d. ``TUBE_SIGMA_PX``) at column ``TUBE_X_PX`` on a linear
    background, and a segment table: one profile across it, one on the flat top rows."""
    x = np.arange(64)
    tube = np.exp(-0.5 * ((x - TUBE_X_PX) / TUBE_SIGMA_PX) ** 2)
    image = np.tile(tube + 0.002 * x + 0.1, (64, 1))
    path = tmp_path / "tubes.ome.tif"
    write_tiff(path, image, axes="YX", voxel_size_um=voxel_size_um)
    segments = tmp_path / "segments.csv"
    pd.DataFrame(
        {"center_y": [40.0], "center_x": [31.0], "axis_angle_rad": [math.pi / 2]}
        | {"half_length_px": [15.0]}
    ).to_csv(segments, index=False)
    return path, segments


def test_fwhm_width_of_a_gaussian_tube(tmp_path, capsys):
    image, segments = _tube_image(tmp_path)
    out = tmp_path / "out"
    args = ["analyze", "fwhm", "--image", str(image), "--segments", str(segments)]
    assert main([*args, "--out", str(out)]) == 0
    widths = pd.read_csv(out / "widths.csv")
    analytic = 2 * math.sqrt(2 * math.log(2)) * TUBE_SIGMA_PX * PIXEL_UM
    assert widths["width_um"].iloc[0] == pytest.approx(analytic, rel=0.05)
    assert (out / "widths.png").stat().st_size > 10_000
    assert "1 of 1 segments measured" in capsys.readouterr().out
    assert main([*args, "--out", str(out)]) == 2
    message = _error(capsys)
    assert "widths.csv: the file exists" in message and "--overwrite" in message
    assert main([*args, "--out", str(out), "--overwrite"]) == 0


def test_fwhm_refusals(tmp_path, capsys):
    image, segments = _tube_image(tmp_path)
    out = str(tmp_path / "out")
    flat = tmp_path / "flat.csv"
    pd.read_csv(segments).assign(axis_angle_rad=0.0).to_csv(flat, index=False)  # along the tube
    assert main(["analyze", "fwhm", "--image", str(image), "--segments", str(flat), "--out", out])
    message = _error(capsys)
    assert "no segment gave a width" in message and "monotone or flat" in message
    bare = tmp_path / "bare.ome.tif"
    write_tiff(bare, np.ones((8, 8)), axes="YX")
    assert main(
        ["analyze", "fwhm", "--image", str(bare), "--segments", str(segments)] + ["--out", out]
    )
    message = _error(capsys)
    assert str(bare) in message and "voxel size" in message and "--voxel-size-um" in message
    series = tmp_path / "series.ome.tif"
    write_tiff(series, np.ones((2, 2, 8, 8)), voxel_size_um=(1, 1, 1))
    assert main(
        ["analyze", "fwhm", "--image", str(series), "--segments", str(segments)] + ["--out", out]
    )
    assert "expected a 2-D (Y, X) image or a 3-D (Z, Y, X) volume" in _error(capsys)


@pytest.mark.parametrize("plane, expected", [("-1", "integer >= 0"), ("3", "(0 to 2)")])
def test_fwhm_plane_outside_the_volume_is_refused_before_any_output(
    tmp_path, capsys, plane, expected
):
    image, segments = _tube_image(tmp_path)
    volume = tmp_path / "volume.ome.tif"
    write_tiff(volume, np.stack([read_tiff(image)] * 3), voxel_size_um=(1, PIXEL_UM, PIXEL_UM))
    out = tmp_path / "out"
    args = ["analyze", "fwhm", "--image", str(volume), "--segments", str(segments)]
    try:
        code = main([*args, f"--plane={plane}", "--out", str(out)])
    except SystemExit as stop:  # argparse's own refusal of the option's type
        code = stop.code
    assert code == 2
    message = _error(capsys)
    assert "--plane" in message and expected in message
    assert not out.exists()
    assert main([*args, "--plane=2", "--out", str(out)]) == 0


# ----------------------------------------------------------------------------- cytometry


@pytest.fixture(scope="module")
def cells(tmp_path_factory):
    """The cell phantom's channels as OME-TIFF files, and its truth."""
    folder = tmp_path_factory.mktemp("cells")
    channels, truth = cell_phantom(
        (24, 64, 64),
        voxel_size_um=CELL_VOXEL_UM,
        n_cells=12,
        marker_names=MARKERS,
        nucleus_radius_um=2.0,
        cell_radius_um=3.5,
        seed=0,
        background=0.1,
        noise_std=0.05,
    )
    paths = {}
    for name, volume in channels.items():
        paths[name] = folder / f"{name}.ome.tif"
        write_tiff(paths[name], volume, axes="ZYX", voxel_size_um=CELL_VOXEL_UM)
    return paths, truth


def _cytometry(paths, out, *extra):
    return main(
        [
            "analyze",
            "cytometry",
            "--nuclei",
            str(paths["nuclei"]),
            *[f"--marker={name}={paths[name]}" for name in MARKERS],
            "--sigma-um",
            "1.0",
            "--marker-sigma-um",
            "2.45",
            "--match-radius-um",
            "1.75",
            "--out",
            str(out),
            *extra,
        ]
    )


def test_cytometry_counts_match_the_phantom(cells, tmp_path, capsys):
    paths, truth = cells
    expected = truth["class"].value_counts()
    reference = [f"--reference-counts={c}={n}" for c, n in expected.items()]
    assert _cytometry(paths, tmp_path, "--threshold", "CD11b=0.2", *reference) == 0
    counts = pd.read_csv(tmp_path / "counts.csv").set_index("class")
    assert counts["count"].to_dict() == expected.reindex(counts.index, fill_value=0).to_dict()
    assert counts["fraction"].sum() == pytest.approx(1.0)
    np.testing.assert_allclose(counts["fisher_p"], 1.0)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["cells"] == 12 and summary["chi2_p"] == pytest.approx(1.0)
    found = pd.read_csv(tmp_path / "cells.csv")
    distance, nearest = cKDTree(truth[AXES].to_numpy()).query(found[AXES].to_numpy())
    assert len(found) == 12 and np.all(distance < 1.0) and len(set(nearest)) == 12
    assert list(found["class"]) == list(truth["class"].iloc[nearest])
    for figure in ("montage.png", "fractions.png"):
        assert (tmp_path / figure).stat().st_size > 10_000
    assert "12 cells" in capsys.readouterr().out


def test_cytometry_refusals(cells, tmp_path, capsys):
    paths, _ = cells
    flat = tmp_path / "flat.ome.tif"
    write_tiff(flat, np.ones((64, 64)), axes="YX", voxel_size_um=CELL_VOXEL_UM[1:])
    assert _cytometry({**paths, "CD11b": flat}, tmp_path / "a") == 2
    message = _error(capsys)
    assert f"--marker CD11b={flat}: expected" in message and "3-D (Z, Y, X) volume" in message
    assert _cytometry(paths, tmp_path / "b", "--reference-counts=CD11b+=3") == 2
    assert "missing" in _error(capsys)
    assert not (tmp_path / "b" / "cells.csv").exists()


# --------------------------------------------------------------------------------- track


def _blob_series(tmp_path, truth_um, voxel_size_um=tuple(TRACK_VOXEL_UM)):
    """``(T, Z, Y, X)`` OME-TIFF of unit Gaussian blobs (s.d. ``BLOB_SIGMA_UM``) at
    ``truth_um`` ``(T, N, 3)``, with a little noise."""
    axes = [(np.arange(n) + 0.5) * v for n, v in zip((12, 48, 48), TRACK_VOXEL_UM)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    volumes = np.zeros((len(truth_um), 12, 48, 48))
    for frame, centres in enumerate(truth_um):
        for centre in centres:
            volumes[frame] += np.exp(-0.5 * np.sum(((grid - centre) / BLOB_SIGMA_UM) ** 2, -1))
    volumes += 0.01 * np.random.default_rng(0).standard_normal(volumes.shape)
    path = tmp_path / "series.ome.tif"
    write_tiff(path, volumes, axes="TZYX", voxel_size_um=voxel_size_um)
    return path


def _moving_blobs(n_frames=4):
    starts = np.array([[8.0, 5.2, 5.3], [12.3, 8.1, 17.7], [9.7, 18.0, 8.1]])  # um (z, y, x)
    steps = np.array([[0.6, 0.7, 0.35], [-0.8, 0.4, -0.6], [0.5, -0.55, 0.45]])  # um/frame
    return starts[None] + np.arange(n_frames)[:, None, None] * steps[None]


def _track(series, out, *extra):
    return main(
        [
            "analyze",
            "track",
            "--series",
            str(series),
            "--frame-interval-s",
            "0.5",
            "--diameter-um",
            "14",
            "5.5",
            "5.5",
            "--search-range-um",
            "3",
            "--minmass",
            "1",
            "--out",
            str(out),
            *extra,
        ]
    )


def test_track_positions_speeds_and_msd(tmp_path, capsys):
    truth = _moving_blobs()
    out = tmp_path / "out"
    assert _track(_blob_series(tmp_path, truth), out) == 0
    tracks = pd.read_csv(out / "trajectories.csv")
    assert tracks["particle"].nunique() == 3 and len(tracks) == 12
    for _, one in tracks.groupby("particle"):
        found = one.sort_values("frame")[AXES].to_numpy()
        blob = np.argmin(np.sum((truth[0] - found[0]) ** 2, axis=1))
        assert np.all(np.abs(found - truth[:, blob]) / TRACK_VOXEL_UM < 0.3)
    speeds = pd.read_csv(out / "speeds.csv")
    true_speeds = np.sort(np.linalg.norm(truth[1] - truth[0], axis=1) / 0.5)
    np.testing.assert_allclose(np.sort(speeds["mean_speed_um_s"]), true_speeds, rtol=0.15)
    assert set(speeds["class"]) == {"unclassified"}  # 3 cells: too few for a density split
    assert np.all(speeds["alpha"] > 1.6)  # straight lines: ballistic
    msd = pd.read_csv(out / "msd.csv")
    assert len(msd) == 3 * 3 and np.all(msd["lag_s"] == msd["lag_frames"] * 0.5)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["threshold_um_s"] is None and "at least 4" in summary["note"]
    for figure in ("speeds.png", "msd.png", "trajectories.png"):
        assert (out / figure).stat().st_size > 10_000
    assert "3 cells tracked over 4 frames" in capsys.readouterr().out


def test_track_refusals(tmp_path, capsys):
    series = _blob_series(tmp_path, _moving_blobs(2))
    assert _track(series, tmp_path / "a", "--minmass", "1e9") == 2
    assert "no objects detected" in _error(capsys)
    volume = tmp_path / "volume.ome.tif"
    write_tiff(volume, np.ones((4, 8, 8)), axes="ZYX", voxel_size_um=(1, 1, 1))
    assert _track(volume, tmp_path / "b") == 2
    assert f"--series {volume}: expected a 4-D (T, Z, Y, X)" in _error(capsys)
    bare = _blob_series(tmp_path, _moving_blobs(2), voxel_size_um=None)
    assert _track(bare, tmp_path / "c") == 2
    assert "PhysicalSizeZ/Y/X" in _error(capsys) and not (tmp_path / "c").exists()
    assert _track(bare, tmp_path / "c", "--voxel-size-um", "2", "0.5", "0.5") == 0
