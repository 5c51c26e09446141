"""fgat.analysis against analytic and hand-built references."""

import numpy as np
import pytest

from fgat.analysis import cubic_interpolation, kymograph, sample_and_hold


def polynomial_series(times, coefficients):
    """Every voxel a cubic polynomial of time: sum_k c_k t^k with c_k of shape (Z, Y, X)."""
    t = np.asarray(times)[:, None, None, None]
    return sum(c * t**k for k, c in enumerate(coefficients))


def test_cubic_interpolation_is_exact_on_cubic_motion():
    rng = np.random.default_rng(0)
    coefficients = [rng.random((2, 3, 4)) + 2.0, *(rng.normal(size=(2, 3, 4)) for _ in range(3))]
    frames = np.linspace(0.0, 1.0, 6)
    query = np.linspace(0.0, 1.0, 51)
    expected = np.clip(polynomial_series(query, coefficients), 0, None)
    np.testing.assert_allclose(
        cubic_interpolation(polynomial_series(frames, coefficients), frames, query),
        expected,
        rtol=1e-5,
        atol=1e-5,
    )


def test_sample_and_hold_and_errors():
    frames = np.arange(4.0)[:, None, None, None] * np.ones((4, 1, 2, 2))
    times = np.array([0.0, 0.1, 0.3, 0.6])
    held = sample_and_hold(frames, times, [0.0, 0.05, 0.1, 0.29, 0.3, 0.59, 0.6])
    np.testing.assert_array_equal(held[:, 0, 0, 0], [0, 0, 1, 1, 2, 2, 3])
    with pytest.raises(ValueError, match="strictly increasing"):
        sample_and_hold(frames, times[::-1], [0.1])
    with pytest.raises(ValueError, match="one per frame"):
        cubic_interpolation(frames, times[:3], [0.1])


def test_kymograph_takes_the_band_around_a_row():
    series = np.zeros((2, 3, 8, 5))
    series[1, 2, 4, 3] = 7.0  # row 4 = the centre row of 8
    series[0, 0, 2, 1] = 9.0  # two rows off the centre: outside the +-1 band
    np.testing.assert_array_equal(kymograph(series), [[0] * 5, [0, 0, 0, 7, 0]])
    np.testing.assert_array_equal(
        kymograph(series, row=2, half_width=0), [[0, 9, 0, 0, 0], [0] * 5]
    )
    with pytest.raises(ValueError, match=r"expected a \(T, Z, Y, X\) series"):
        kymograph(series[0])
