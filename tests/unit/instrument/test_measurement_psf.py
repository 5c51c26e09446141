"""A PSF file's recorded plane order: a stack written "down" (a fit's psf.ome.tif) is read in the
order the reconstruction asks for, as one written "up" is."""

import numpy as np
import pytest

from fgat.instrument.centres import write_centers
from fgat.instrument.measurement import measurement_model
from fgat.io.images import volume_entries, write_tiff

DEPTHS = [-4.0, 0.0, 4.0]


@pytest.mark.parametrize("wanted", ["up", "down"])
def test_psf_file_planes_follow_its_recorded_depth_axis(tmp_path, wanted):
    stack = np.random.default_rng(0).random((2, 3, 5, 5), dtype=np.float32)
    centers = tmp_path / "centers.csv"
    write_centers(centers, np.array([[10.0, 10.0], [10.0, 20.0]]))
    files = {
        axis: write_tiff(
            tmp_path / f"{axis}.ome.tif",
            stack if axis == "up" else stack[:, ::-1],
            axes="CZYX",
            voxel_size_um=(4.0, 1.0, 1.0),
            metadata=volume_entries(axis, DEPTHS if axis == "up" else DEPTHS[::-1], "psf"),
        )
        for axis in ("up", "down")
    }
    models = {
        axis: measurement_model(centers=str(centers), psf=str(path), depth_axis=wanted)
        for axis, path in files.items()
    }
    expected = stack if wanted == "up" else stack[:, ::-1]
    for model in models.values():
        np.testing.assert_array_equal(model.psf, expected)
        assert list(model.depths_um) == (DEPTHS if wanted == "up" else DEPTHS[::-1])
