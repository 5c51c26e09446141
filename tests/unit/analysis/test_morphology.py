"""fgat.analysis.morphology (Note S8.2) against analytic profiles: sampled Gaussians, blurred
rectangles and straight tubes of Gaussian cross-section."""

import math

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import brentq
from scipy.special import erf

from fgat.analysis.morphology import (
    FwhmResult,
    Segment,
    fwhm_with_reason,
    profile_fwhm,
    subtract_end_background,
    tubule_widths,
)

SIGMA_PER_FWHM = 1 / (2 * math.sqrt(2 * math.log(2)))
OFFSETS = np.arange(10) / 10


def linear_background(x):
    return 5 + 0.3 * x


def gaussian_profile(fwhm, offset):
    """A sampled Gaussian of the given FWHM (samples) centred ``offset`` past the middle sample,
    on a linear background; long enough that its ends are background."""
    n = int(8 * fwhm) + 1
    x = np.arange(n, dtype=np.float64)
    sigma = fwhm * SIGMA_PER_FWHM
    return 10 * np.exp(-((x - n // 2 - offset) ** 2) / (2 * sigma**2)) + linear_background(x)


def blurred_box(x, width, sigma):
    """A box of ``width`` centred at 0 convolved with a unit-area Gaussian of ``sigma``."""
    scale = sigma * math.sqrt(2)
    return 0.5 * (erf((x + width / 2) / scale) - erf((x - width / 2) / scale))


def blurred_box_fwhm(width, sigma):
    """Analytic FWHM of :func:`blurred_box`: twice the root of f(x) = f(0) / 2 for x > 0."""
    half = blurred_box(0.0, width, sigma) / 2
    return 2 * brentq(lambda x: blurred_box(x, width, sigma) - half, 0, width / 2 + 10 * sigma)


@pytest.mark.parametrize("fwhm", [4.0, 6.5, 10.0])
@pytest.mark.parametrize("offset", OFFSETS)
def test_gaussian_fwhm_at_any_subpixel_offset(fwhm, offset):
    assert profile_fwhm(gaussian_profile(fwhm, offset)) == pytest.approx(fwhm, rel=0.03)


@pytest.mark.parametrize(("width", "sigma"), [(3.0, 1.5), (6.0, 1.0), (10.0, 2.0)])
@pytest.mark.parametrize("offset", OFFSETS)
def test_blurred_rectangle_fwhm_at_any_subpixel_offset(width, sigma, offset):
    n = 2 * math.ceil(width / 2 + 8 * sigma) + 1
    x = np.arange(n, dtype=np.float64)
    profile = 7 * blurred_box(x - n // 2 - offset, width, sigma) + linear_background(x)
    expected = blurred_box_fwhm(width, sigma)
    assert expected >= 4
    assert profile_fwhm(profile) == pytest.approx(expected, rel=0.03)


def test_linear_background_is_removed_exactly():
    x = np.arange(37, dtype=np.float64)
    bump = np.where(np.abs(x - 18) < 5, 1.0, 0.0)
    corrected = subtract_end_background(bump + linear_background(x), end_fraction=0.1)
    np.testing.assert_allclose(corrected, bump, atol=1e-12)


def test_result_reports_peak_and_crossings():
    result = fwhm_with_reason(gaussian_profile(8.0, 0.0))
    assert isinstance(result, FwhmResult)
    assert result.reason == ""
    assert result.peak == pytest.approx(10, rel=1e-3)
    assert result.left == pytest.approx(32 - 4, abs=0.05)
    assert result.right == pytest.approx(32 + 4, abs=0.05)
    assert result.fwhm == pytest.approx(result.right - result.left)


x40 = np.arange(40, dtype=np.float64)


@pytest.mark.parametrize(
    "profile",
    [
        pytest.param(linear_background(x40), id="linear-ramp"),
        pytest.param(np.sqrt(x40), id="concave-ramp"),
        pytest.param(np.exp(x40 / 8), id="convex-ramp"),
        pytest.param(np.full(40, 3.0), id="flat"),
        pytest.param(np.exp(-(x40**2) / 18), id="peak-at-first-sample"),
        pytest.param(
            np.exp(-((x40 - 39) ** 2) / 18) + 0.01 * np.sin(x40), id="peak-at-last-sample"
        ),
        pytest.param(np.exp(-((x40 - 2) ** 2) / 18), id="peak-next-to-edge"),
        pytest.param(1 - np.exp(-((x40 - 20) ** 2) / 18), id="dip"),
    ],
)
def test_unmeasurable_profiles_give_nan_with_a_reason(profile):
    result = fwhm_with_reason(profile)
    assert math.isnan(result.fwhm)
    assert result.reason
    assert math.isnan(profile_fwhm(profile))


@pytest.mark.parametrize(
    ("profile", "end_fraction", "match"),
    [
        (np.ones((4, 4)), 0.1, "1-D"),
        (np.array([0.0, 1.0]), 0.1, "at least 3"),
        (np.array([0.0, np.nan, 1.0, 0.0]), 0.1, "non-finite"),
        (np.array([0.0, np.inf, 1.0, 0.0]), 0.1, "non-finite"),
        (np.array([0.0, 1.0, 0.0]), 0.0, "end_fraction"),
        (np.array([0.0, 1.0, 0.0]), 0.5, "end_fraction"),
        (np.array([0.0, 1.0, 0.0]), -0.1, "end_fraction"),
    ],
)
def test_profile_fwhm_rejects_unusable_input(profile, end_fraction, match):
    with pytest.raises(ValueError, match=match):
        profile_fwhm(profile, end_fraction=end_fraction)


SHAPE = (64, 64)
CENTER = (31.6, 32.3)


def tube_image(angle_rad, sigma_px, amplitude=10.0, shape=SHAPE, center=CENTER):
    """A straight tube through ``center`` along ``(dy, dx) = (sin a, cos a)`` with a Gaussian
    cross-section of ``sigma_px``, on a linear background."""
    y, x = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    distance = (y - center[0]) * math.cos(angle_rad) - (x - center[1]) * math.sin(angle_rad)
    return amplitude * np.exp(-(distance**2) / (2 * sigma_px**2)) + 3 + 0.02 * x + 0.01 * y


def segments_along(angle_rad, half_length_px=12.3):
    """Three segments on the tube axis: at ``CENTER`` and 6 px either side along the axis."""
    axis = np.array([math.sin(angle_rad), math.cos(angle_rad)])
    return [
        Segment(tuple(np.asarray(CENTER) + shift * axis), angle_rad, half_length_px)
        for shift in (-6, 0, 6)
    ]


@pytest.mark.parametrize("degrees", [0, 30, 45, 90, 135])
@pytest.mark.parametrize("width_px", [1, 3])
def test_tubule_widths_match_the_gaussian_cross_section(degrees, width_px):
    angle, sigma_px, pixel_um = math.radians(degrees), 2.0, 0.065
    table = tubule_widths(
        tube_image(angle, sigma_px),
        segments_along(angle),
        voxel_size_um=(pixel_um, pixel_um),
        width_px=width_px,
    )
    expected_um = sigma_px / SIGMA_PER_FWHM * pixel_um
    assert list(table["segment"]) == [0, 1, 2]
    assert (table["reason"] == "").all()
    np.testing.assert_allclose(table["width_um"], expected_um, rtol=0.05)
    np.testing.assert_allclose(table["fwhm_px"] * pixel_um, table["width_um"])
    np.testing.assert_allclose(table["peak"], 10, rtol=0.05)


@pytest.mark.parametrize("degrees", [0, 90])
def test_profile_along_the_tube_axis_has_no_width(degrees):
    # on grid axes, so that interpolation leaves the profile exactly linear (no ripples)
    angle = math.radians(degrees)
    along = [Segment(s.center_yx, angle + math.pi / 2, 12.0) for s in segments_along(angle)]
    table = tubule_widths(tube_image(angle, 2.0), along, voxel_size_um=(0.1, 0.1))
    assert table["width_um"].isna().all()
    assert (table["reason"] != "").all()


def test_segment_profile_is_perpendicular_to_the_axis():
    segment = Segment((10.0, 20.0), math.radians(30), 5.0)
    src, dst = segment.profile_endpoints()
    axis = np.array([math.sin(segment.axis_angle_rad), math.cos(segment.axis_angle_rad)])
    assert np.dot(dst - src, axis) == pytest.approx(0, abs=1e-12)
    assert np.linalg.norm(dst - src) == pytest.approx(10.0)
    np.testing.assert_allclose((src + dst) / 2, segment.center_yx)


def test_segment_table_gives_the_same_widths_as_segments():
    angle = math.radians(45)
    segments = segments_along(angle)
    frame = pd.DataFrame(
        {
            "center_y": [s.center_yx[0] for s in segments],
            "center_x": [s.center_yx[1] for s in segments],
            "axis_angle_rad": angle,
            "half_length_px": 12.3,
        }
    )
    image = tube_image(angle, 2.5)
    pd.testing.assert_frame_equal(
        tubule_widths(image, frame, voxel_size_um=(0.1, 0.1)),
        tubule_widths(image, segments, voxel_size_um=(0.1, 0.1)),
    )


def test_volume_is_measured_on_its_mip_or_on_a_plane():
    angle, narrow, wide = math.radians(30), 1.8, 3.0
    volume = np.zeros((4, *SHAPE))
    volume[1] = tube_image(angle, narrow, amplitude=5.0)
    # wider and brighter: it dominates the maximum-intensity projection everywhere
    volume[3] = tube_image(angle, wide, amplitude=8.0)
    voxel = (0.3, 0.1, 0.1)
    segments = segments_along(angle)
    mip = tubule_widths(volume, segments, voxel_size_um=voxel)
    plane = tubule_widths(volume, segments, voxel_size_um=voxel, plane=1)
    np.testing.assert_allclose(mip["width_um"], wide / SIGMA_PER_FWHM * 0.1, rtol=0.05)
    np.testing.assert_allclose(plane["width_um"], narrow / SIGMA_PER_FWHM * 0.1, rtol=0.05)


IMAGE = tube_image(0.0, 2.0)
GOOD = [Segment(CENTER, 0.0, 10.0)]


@pytest.mark.parametrize(
    ("image", "segments", "kwargs", "match"),
    [
        (np.ones(10), GOOD, {"voxel_size_um": (0.1,)}, "image_or_volume"),
        (np.ones((2, 2, 8, 8)), GOOD, {"voxel_size_um": (1, 1, 1, 1)}, "image_or_volume"),
        (np.ones((0, 64)), GOOD, {"voxel_size_um": (0.1, 0.1)}, "empty"),
        (np.zeros(SHAPE), GOOD, {"voxel_size_um": (0.1, 0.1)}, "all zero"),
        (np.zeros((3, *SHAPE)), GOOD, {"voxel_size_um": (1, 0.1, 0.1)}, "all zero"),
        (np.full(SHAPE, np.nan), GOOD, {"voxel_size_um": (0.1, 0.1)}, "non-finite"),
        (IMAGE, GOOD, {"voxel_size_um": None}, "voxel_size_um is required"),
        (IMAGE, GOOD, {"voxel_size_um": (0.1, 0.0)}, "voxel_size_um"),
        (IMAGE, GOOD, {"voxel_size_um": (-0.1, -0.1)}, "voxel_size_um"),
        (IMAGE, GOOD, {"voxel_size_um": (0.3, 0.1, 0.1)}, "voxel_size_um"),
        (IMAGE, GOOD, {"voxel_size_um": (0.1, 0.2)}, "square pixels"),
        (IMAGE, GOOD, {"voxel_size_um": (0.1, 0.1), "plane": 0}, "plane"),
        (np.stack([IMAGE] * 2), GOOD, {"voxel_size_um": (1, 0.1, 0.1), "plane": 2}, "plane"),
        (IMAGE, GOOD, {"voxel_size_um": (0.1, 0.1), "width_px": 0}, "width_px"),
        (IMAGE, [], {"voxel_size_um": (0.1, 0.1)}, "segments is empty"),
        (IMAGE, [(1, 2, 3)], {"voxel_size_um": (0.1, 0.1)}, "Segment"),
        (IMAGE, pd.DataFrame({"center_y": [30]}), {"voxel_size_um": (0.1, 0.1)}, "lacks columns"),
        (IMAGE, [Segment((5.0, 32.0), 0.0, 10.0)], {"voxel_size_um": (0.1, 0.1)}, "outside"),
        (
            IMAGE,
            [Segment((32.0, 0.5), 0.0, 10.0)],
            {"voxel_size_um": (0.1, 0.1), "width_px": 3},
            "outside",
        ),
    ],
)
def test_tubule_widths_rejects_bad_input(image, segments, kwargs, match):
    with pytest.raises(ValueError, match=match):
        tubule_widths(image, segments, **kwargs)


@pytest.mark.parametrize(
    ("center", "angle", "half_length", "match"),
    [
        ((1.0, np.nan), 0.0, 5.0, "center_yx"),
        ((1.0, 2.0), np.inf, 5.0, "axis_angle_rad"),
        ((1.0, 2.0), 0.0, 0.5, "half_length_px"),
        ((1.0, 2.0), 0.0, np.nan, "half_length_px"),
    ],
)
def test_segment_rejects_bad_geometry(center, angle, half_length, match):
    with pytest.raises(ValueError, match=match):
        Segment(center, angle, half_length)
