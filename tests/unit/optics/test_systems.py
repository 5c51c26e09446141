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
    root = Path(__file__).resolve().parents[3] / "reproduce" / "systems"
    for name, base in (("small_aperture_disk", "small"), ("20x_0.45_aperture_disk", "20x/0.45")):
        system = load_system(str(root / f"{name}.yaml"))
        assert system.zernike_disk == "aperture"
        assert system.replace(name=base, zernike_disk="pupil") == load_system(base)


def test_presets_keep_a_centre_to_centre_pitch_and_the_unrotated_lattice():
    for name in PRESETS:
        system = load_system(name)
        assert (system.mla_pitch_convention, system.mla_orientation) == ("center", "pointy-top")
        assert system.pitch_px == pytest.approx(system.mla_pitch_mm * 1000.0 / system.pixel_um)
        offsets = system.lenslet_centers_px()[1:7] - system.lenslet_centers_px()[0]
        assert offsets[0] == pytest.approx([0.0, system.pitch_px])  # view 1 along +column


@pytest.mark.parametrize(
    ("convention", "spacing"), [("center", 1.0), ("row", 2 / math.sqrt(3)), ("corner", 0.866025)]
)
def test_the_pitch_convention_sets_the_centre_spacing_everywhere(tmp_path, convention, spacing):
    path = tmp_path / "mla.yaml"
    path.write_text(
        f"base: small\nname: mla\nmla_pitch_mm: 0.5\nmla_pitch_convention: {convention}\n"
    )
    system = system_from_yaml(path)
    assert system.center_pitch_mm == pytest.approx(0.5 * spacing, rel=1e-6)
    assert system.pitch_px == pytest.approx(500.0 * spacing / 6.5, rel=1e-6)
    centers = system.lenslet_centers_px()
    nearest = np.linalg.norm(centers[1:] - centers[0], axis=1).min()
    assert nearest == pytest.approx(system.pitch_px)
    same = load_system("small").replace(mla_pitch_mm=0.5 * spacing)  # the same array, quoted
    assert system.design == pytest.approx(same.design)


@pytest.mark.parametrize(
    ("orientation", "rotation", "view1_deg"),
    [
        ("pointy-top", 0.0, 0.0),
        ("pointy-top", 4.0, 4.0),
        ("flat-top", 0.0, 30.0),
        ("flat-top", 2.5, -27.5),
        ("pointy-top", 62.0, 2.0),
    ],
)
def test_the_orientation_fields_turn_the_nominal_lattice(orientation, rotation, view1_deg):
    import torch

    from fgat.optics.pupil import lattice_angle

    system = load_system("small37").replace(mla_orientation=orientation, mla_rotation_deg=rotation)
    assert system.lattice_rotation_deg == pytest.approx(view1_deg)
    centers = system.lenslet_centers_px()
    d_row, d_col = centers[1] - centers[0]
    assert math.degrees(math.atan2(-d_row, d_col)) == pytest.approx(view1_deg)  # as displayed
    distances = np.linalg.norm(centers - centers[0], axis=1)
    unrotated = np.linalg.norm(load_system("small37").lenslet_centers_px() - centers[0], axis=1)
    np.testing.assert_allclose(distances, unrotated, atol=1e-9)  # the same rings, turned
    angle = lattice_angle(torch.from_numpy(centers))
    assert (math.degrees(angle) + view1_deg + 30.0) % 60.0 == pytest.approx(30.0)  # mod 60
    single = system.replace(n_lenslets=1)
    assert lattice_angle(torch.zeros(1, 2), -math.radians(single.lattice_rotation_deg)) == (
        pytest.approx(-math.radians(view1_deg))
    )


def test_bad_orientation_fields_are_refused_naming_them(tmp_path):
    path = tmp_path / "mla.yaml"
    for line, message in (
        ("mla_pitch_convention: diagonal", "mla_pitch_convention must be one of"),
        ("mla_orientation: sideways", "mla_orientation must be one of"),
        ("mla_rotation_deg: .nan", "mla_rotation_deg must be a finite number of degrees"),
        ("mla_rotation_deg: twelve", "mla_rotation_deg must be a finite number of degrees"),
    ):
        path.write_text(f"base: small\nname: mla\n{line}\n")
        with pytest.raises(ValueError, match=f"mla.yaml: .*{message}"):
            system_from_yaml(path)


def test_simulated_lenslets_follow_the_system_orientation():
    import torch

    from fgat.optics.pupil import lattice_angle
    from fgat.sim.simulation import Imperfections

    system = load_system("small37").replace(mla_orientation="flat-top", mla_rotation_deg=3.0)
    drawn = Imperfections(mla_rotation_deg=0.4).draw(system, 0)
    angle = math.degrees(lattice_angle(torch.from_numpy(drawn.centers)))
    assert angle == pytest.approx(-(-27.0 + 0.4))  # lattice_angle turns like theta
    nearest = np.linalg.norm(drawn.centers[1:] - drawn.centers[0], axis=1).min()
    assert nearest == pytest.approx(system.pitch_px)
