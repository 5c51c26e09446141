import math

import numpy as np
import pytest

from fgat.optics.systems import PRESETS, FLFMSystem, load_system, system_from_yaml


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load(name):
    system = load_system(name)
    centers = system.lenslet_centers_px()
    assert len(centers) == system.n_lenslets >= 7
    assert np.hypot(*(centers[1] - centers[0])) == pytest.approx(system.pitch_px)


def test_small_system_keeps_the_20x_invariants():
    small, full = load_system("small").design, load_system("20x/0.45").design
    for key in (
        "total_magnification",
        "effective_pixel_um",
        "lenslets_across_pupil",
        "dof_um",
        "lateral_resolution_um",
        "axial_resolution_um",
    ):
        assert small[key] == pytest.approx(full[key])


def test_yaml_errors_name_file_and_field(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("name: mine\nmagnification: 20\nna: 0.45\npitch: 3\n")
    with pytest.raises(ValueError, match="mine.yaml: unknown field\\(s\\) \\['pitch'\\]"):
        system_from_yaml(path)
    path.write_text("name: mine\nmagnification: 20\nna: 1.2\n")
    with pytest.raises(ValueError, match="mine.yaml: .*na \\(1.2\\) must be below immersion_index"):
        system_from_yaml(path)
    path.write_text("name: mine\nmagnification: 20\n")
    with pytest.raises(ValueError, match="missing required field 'na'"):
        system_from_yaml(path)
    path.write_text("name: mine\nmagnification: 20\nna: 0.45\nsensor_shape: [512, 512]\n")
    assert system_from_yaml(path).sensor_shape == (512, 512)
    with pytest.raises(ValueError, match="pixel_um must be a positive number"):
        FLFMSystem(name="x", magnification=20, na=0.45, pixel_um=0)


def test_sample_medium_and_lenslet_shape_fields(tmp_path):
    base = load_system("60x/1.25")
    assert base.sample_index is None and base.lenslet_shape == "circle"
    assert base.sample_medium_index == base.immersion_index
    water = base.replace(sample_index=1.33, lenslet_shape="hexagon")
    assert water.sample_medium_index == 1.33
    # NA above the sample index is allowed: the supercritical part of the pupil is dark.
    assert base.replace(na=1.45, sample_index=1.33).sample_medium_index == 1.33
    path = tmp_path / "water.yaml"
    path.write_text(
        "name: water\nmagnification: 60\nna: 1.3\nimmersion_index: 1.406\n"
        "sample_index: 1.33\nlenslet_shape: hexagon\n"
    )
    loaded = system_from_yaml(path)
    assert (loaded.sample_index, loaded.lenslet_shape) == (1.33, "hexagon")
    for bad in (0.0, -1.33, math.nan, math.inf, "water", True):
        with pytest.raises(ValueError, match="system 'x': sample_index must be a positive number"):
            FLFMSystem(name="x", magnification=60, na=1.3, immersion_index=1.406, sample_index=bad)
    with pytest.raises(ValueError, match="system 'x': lenslet_shape must be one of"):
        FLFMSystem(name="x", magnification=20, na=0.45, lenslet_shape="square")
    path.write_text("name: mine\nmagnification: 20\nna: 0.45\nsample_index: -1\n")
    with pytest.raises(ValueError, match="water.yaml: .*sample_index must be a positive number"):
        system_from_yaml(path)
