"""What the reader's tests open: fgat's outputs made by its own writers and commands."""

import contextlib
from pathlib import Path

import numpy as np
import pytest
import yaml

# Triton loads before any viewer draws: loaded after Mesa's software OpenGL it crashes the
# process (fgat.napari.widgets.keep_triton_out), and loaded first it stays importable for the
# tests that follow these.
with contextlib.suppress(ImportError):
    import triton  # noqa: F401

DEPTHS = [-6.0, -3.0, 0.0, 3.0, 6.0]
"""Depths of the test volumes' planes, um (ascending: fgat's ``up`` order)."""
VOXEL = (3.0, 0.975, 0.5)
"""(dz, dy, dx) of the test volumes, um (y and x differ, so a swap shows)."""
SIMULATION = {
    "system": "small",
    "depths_um": "-6:6:5",
    "view_size": 24,
    "photons": None,
    "background": 100,
    "phantom": {"kind": "beads", "n_beads": 4, "sigma": 1.0, "min_spacing": 5, "margin": [1, 4, 4]},
}
"""A tiny noise-free phantom seen by the small system: 5 planes of 24 x 24 voxels, 7 views."""


@pytest.fixture
def volume():
    """``(Z, Y, X)`` float32 values, every voxel distinct."""
    return np.random.default_rng(0).random((len(DEPTHS), 6, 7), dtype=np.float32)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The files and folders of ``python -m fgat simulate``, ``psf``, ``calibrate`` and
    ``deconvolve`` (``up`` and ``down``) on :data:`SIMULATION`, by name."""
    from fgat.app.cli import main

    root = tmp_path_factory.mktemp("made")
    config = root / "simulation.yaml"
    config.write_text(yaml.safe_dump(SIMULATION))
    paths = {
        "sim": root / "sim",
        "psf": root / "psf.ome.tif",
        "calibration": root / "calibration",
        "up": root / "up.ome.tif",
        "down": root / "down.ome.tif",
    }
    sensor = str(paths["sim"] / "sensor.ome.tif")
    commands = [
        ["simulate", "--config", str(config), "--out", str(paths["sim"])],
        ["psf", "--system", "small", "--depths-um=-6:6:5", "--crop-radius", "8"]
        + ["--out", str(paths["psf"])],
        ["calibrate", "--image", sensor, "--system", "small", "--out", str(paths["calibration"])],
    ]
    for axis in ("up", "down"):
        commands.append(
            ["deconvolve", "--measurement", sensor, "--psf", str(paths["sim"] / "psf.ome.tif")]
            + ["--centers", str(paths["sim"] / "centers.csv"), "--iterations", "3"]
            + ["--depth-axis", axis, "--out", str(paths[axis])]
        )
    for command in commands:
        assert main(command) == 0, command
    return paths


def layers_of(path: str | Path) -> list:
    """The layer data tuples fgat's reader makes of ``path`` (which it must accept)."""
    from fgat.napari.reader import get_reader

    reader = get_reader(str(path))
    assert reader is not None, path
    return reader(str(path))
