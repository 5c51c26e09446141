import math
from pathlib import Path

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


def test_a_system_file_may_change_some_fields_of_a_base(tmp_path):
    (tmp_path / "mine.yaml").write_text("base: small\nname: mine\nzernike_disk: aperture\n")
    mine = system_from_yaml(tmp_path / "mine.yaml")
    assert mine == load_system("small").replace(name="mine", zernike_disk="aperture")
    # A base file relative to the file naming it, itself based on a shipped system.
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "wide.yaml").write_text("base: ../mine.yaml\nname: wide\nna: 0.5\n")
    wide = load_system(str(tmp_path / "sub" / "wide.yaml"))
    assert (wide.name, wide.na, wide.zernike_disk, wide.pixel_um) == ("wide", 0.5, "aperture", 6.5)
    (tmp_path / "loop.yaml").write_text("base: loop.yaml\nname: loop\n")
    with pytest.raises(ValueError, match="loop.yaml: base 'loop.yaml' leads back to a file"):
        system_from_yaml(tmp_path / "loop.yaml")
    (tmp_path / "lost.yaml").write_text("base: nowhere.yaml\nname: lost\n")
    with pytest.raises(ValueError, match="lost.yaml: base 'nowhere.yaml': no shipped system"):
        system_from_yaml(tmp_path / "lost.yaml")
    (tmp_path / "bad.yaml").write_text("base: small\nzernike_disk: lenslet\n")
    with pytest.raises(ValueError, match="bad.yaml: .*zernike_disk must be one of"):
        system_from_yaml(tmp_path / "bad.yaml")


def test_shipped_aperture_disk_systems_load():
    root = Path(__file__).resolve().parents[1] / "reproduce" / "systems"
    for name, base in (("small_aperture_disk", "small"), ("20x_0.45_aperture_disk", "20x/0.45")):
        system = load_system(str(root / f"{name}.yaml"))
        assert system.zernike_disk == "aperture"
        assert system.replace(name=base, zernike_disk="pupil") == load_system(base)
