import numpy as np
import pytest

from fgat.optics.systems import PRESETS, FLFMSystem, load_system, system_from_yaml


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load(name):
    system = load_system(name)
    assert system.n_lenslets == 7
    centers = system.lenslet_centers_px()
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
