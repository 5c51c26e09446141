"""Numerical stress: every case finite within its tolerance, or refused up front (the fast
subset of ``python benchmarks/stress.py``, whose functions these tests call)."""

import pytest

from fgat.app.recipes import stress

pytestmark = pytest.mark.stress


@pytest.mark.parametrize("method", ["SHB", "3DGAT", "4DGAT"])
def test_intensity_scale_changes_nothing(method):
    for r in stress.scale_rows((method,), (1e-6, 1e6), steps=30):
        assert r["finite"] and abs(r["value"]) <= stress.SCALE_TOLERANCE_DB, r


def test_intensity_scale_changes_nothing_in_the_dynamic_stage():
    for r in stress.dynamic_scale_rows((1e-6, 1e6), steps=20):
        assert r["finite"] and abs(r["value"]) <= stress.SCALE_TOLERANCE_DB, r


def test_degenerate_gaussians_match_the_dense_reference_with_finite_gradients():
    rows = stress.gaussian_rows()
    assert [r["setting"] for r in rows] == list(stress.DEGENERATE)
    for r in rows:
        assert r["ok"], r


def test_float32_operator_and_jpgm_against_float64():
    for r in stress.precision_rows(quick=True) + stress.jpgm_precision_rows(quick=True):
        assert r["ok"], r


def test_ten_photons_without_background_stay_finite_and_non_negative():
    for r in stress.photon_rows():
        assert r["ok"], r


def test_aberrations_past_the_sampling_limit_are_refused():
    assert stress.refused(3.0) is None
    assert stress.refused(10.0).startswith("sampling: the pupil-plane phase varies by")


def test_a_nan_stops_the_step_naming_it():
    (r,) = stress.guard_rows()
    assert r["ok"], r


def test_thin_and_thick_depth_ranges_and_strong_aberrations_stay_physical():
    """Each depth sends at most its unit energy into the views' crops (Eq. S9) and at least
    most of it: a thin and a thick range, 0.5 to 2 waves RMS."""
    rows = stress.depth_range_rows() + stress.rms_rows(quick=True)
    for r in rows:
        assert r["ok"] and r["finite"] and 0.9 < r["value"] <= 1 + 1e-5, r


def test_a_crop_on_the_sensor_edge_is_computed_and_one_off_it_refused():
    on_edge, off = stress.sensor_edge_rows()
    assert on_edge["ok"] and on_edge["finite"] and on_edge["value"] > 0, on_edge
    assert off["ok"], off
