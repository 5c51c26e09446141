import json
import subprocess
import sys

import pytest

from fgat.optics.design import flfm_design, format_design_table, parse_objective, round_half_up

# Table S1 of the supplement, as printed.
TABLE_S1 = {
    "20x/0.45": ("0.02250", "13.50", "6.667", "0.9750", "600", "1.9125", "7.1719", "72.0"),
    "40x/0.90": ("0.02250", "13.50", "13.333", "0.4875", "300", "0.9563", "1.7930", "18.0"),
    "60x/1.25": ("0.02083", "12.50", "20.000", "0.3250", "200", "0.6375", "0.7969", "8.0"),
}
COLUMNS = (
    "na_over_m",
    "pupil_diameter_mm",
    "total_magnification",
    "effective_pixel_um",
    "fov_um",
    "lateral_resolution_um",
    "axial_resolution_um",
    "dof_um",
)


@pytest.mark.parametrize("objective", TABLE_S1)
def test_table_s1_values(objective):
    design = flfm_design(*parse_objective(objective))
    for key, printed in zip(COLUMNS, TABLE_S1[objective]):
        decimals = len(printed.split(".")[1]) if "." in printed else 0
        assert abs(design[key] - float(printed)) <= 0.5 * 10**-decimals + 1e-12, key
        assert round_half_up(design[key], decimals) == printed, key


def test_printed_table_matches_table_s1():
    rows = {name: flfm_design(*parse_objective(name)) for name in TABLE_S1}
    lines = format_design_table(rows).splitlines()[2:]
    for line, (name, printed) in zip(lines, TABLE_S1.items()):
        assert line.split() == [name, *printed]


def test_relations_scale_as_expected():
    base = flfm_design(20, 0.45)
    doubled = flfm_design(20, 0.45, f_mla_mm=200)
    assert doubled["total_magnification"] == pytest.approx(2 * base["total_magnification"])
    assert doubled["fov_um"] == pytest.approx(base["fov_um"] / 2)
    assert base["lenslets_across_pupil"] == pytest.approx(13.5 / 4.0)


@pytest.mark.parametrize(
    "bad",
    [
        dict(magnification=0, na=0.45),
        dict(magnification=20, na=-1),
        dict(magnification=20, na=float("nan")),
    ],
)
def test_bad_inputs_name_the_field(bad):
    with pytest.raises(ValueError, match="must be a positive finite number"):
        flfm_design(**bad)


@pytest.mark.parametrize("text", ["20/0.45", "x/0.4", "20x", "20x/abc"])
def test_bad_objective(text):
    with pytest.raises(ValueError, match="MAGx/NA"):
        parse_objective(text)


@pytest.mark.parametrize("text", ["999x/9", "60x/1.8", "20x/1.78"])
def test_objective_beyond_any_immersion_index_is_refused(text):
    with pytest.raises(ValueError, match=r"NA < 1\.78 .*immersion index"):
        parse_objective(text)
    assert parse_objective("100x/1.7") == (100.0, 1.7)


@pytest.mark.slow
def test_cli_design_json_is_the_api_dict():
    out = subprocess.run(
        [sys.executable, "-m", "fgat", "design", "--objective", "20x/0.45", "--json"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert json.loads(out) == pytest.approx(flfm_design(20, 0.45))
