"""Tracking, speed classes and anomalous diffusion (Note S8.9, Eq. S62), each against an
independent reference: trackpy's own MSD, brute-force loops, Brownian statistics with known D,
the analytic antimode of a log-normal mixture, and blobs rendered at known positions."""

import numpy as np
import pandas as pd
import pytest
import trackpy as tp
from scipy.optimize import minimize_scalar
from scipy.stats import norm

from fgat.analysis.tracking import (
    anomalous_exponent,
    driven_and_free_tracks,
    mean_speeds,
    msd,
    odd_diameter_px,
    sliding_speeds,
    speed_threshold,
    track,
)

VOXEL_UM = np.array([2.0, 0.5, 0.5])  # (dz, dy, dx): anisotropic like an FLFM volume
BLOB_SIGMA_UM = np.array([2.0, 1.0, 1.0])
DIAMETER_UM = (14.0, 5.5, 5.5)  # 7 x 11 x 11 voxels: the blobs' full extent


def _table(positions: np.ndarray, columns, frame_interval_s: float = 1.0) -> pd.DataFrame:
    """``(N, T, D)`` positions as a trackpy-style table (frame, particle, position columns)."""
    n, t, _ = positions.shape
    table = pd.DataFrame(positions.reshape(n * t, -1), columns=columns)
    table["frame"] = np.tile(np.arange(t), n)
    table["particle"] = np.repeat(np.arange(n), t)
    table["t_s"] = table["frame"] * frame_interval_s
    return table


def _brute_force_msd(positions: np.ndarray) -> np.ndarray:
    """Eq. S62 as a double loop over lags and window starts, skipping windows with a NaN."""
    t = len(positions)
    out = np.full(t - 1, np.nan)
    for lag in range(1, t):
        squares = [
            np.sum((positions[s + lag] - positions[s]) ** 2)
            for s in range(t - lag)
            if np.all(np.isfinite(positions[s])) and np.all(np.isfinite(positions[s + lag]))
        ]
        if squares:
            out[lag - 1] = np.mean(squares)
    return out


def _phantom(**overrides):
    """Paper-like mixture: 1:5 driven/free, slow free cells at ~2 um/s, driven at 20 um/s."""
    kwargs = dict(n_frames=100, frame_interval_s=0.2, diffusion_um2_s=1.0, drift_um_s=20.0, seed=1)
    return driven_and_free_tracks(120, **{**kwargs, **overrides})


# ----------------------------------------------------------------------------- msd and alpha


@pytest.mark.parametrize("columns", [["y", "x"], ["z", "y", "x"]], ids=["2d", "3d"])
def test_msd_equals_trackpy_imsd(columns):
    rng = np.random.default_rng(0)
    positions = 50 + np.cumsum(rng.normal(size=(5, 40, len(columns))), axis=1)
    table = _table(positions, columns)
    reference = tp.imsd(table, mpp=1, fps=1, max_lagtime=39, pos_columns=columns)
    for particle, track_positions in enumerate(positions):
        lags, values = msd(track_positions)
        np.testing.assert_array_equal(lags, np.arange(1, 40))
        np.testing.assert_allclose(values, reference[particle].to_numpy(), rtol=1e-9, atol=1e-9)


def test_msd_with_gaps_equals_brute_force_and_trackpy():
    rng = np.random.default_rng(1)
    positions = np.cumsum(rng.normal(size=(30, 3)), axis=0)
    positions[[0, 4, 5, 17, 29]] = np.nan
    lags, values = msd(positions)
    np.testing.assert_allclose(values, _brute_force_msd(positions), rtol=1e-12)
    # trackpy's gap path on the rows that exist (it spans first to last found frame only)
    table = _table(positions[None], ["z", "y", "x"]).dropna()
    reference = tp.imsd(table, mpp=1, fps=1, max_lagtime=29, pos_columns=["z", "y", "x"])[0]
    np.testing.assert_allclose(values[: len(reference)], reference.to_numpy(), rtol=1e-9)


@pytest.mark.parametrize("dims", [2, 3])
def test_brownian_msd_is_2dDtau(dims):
    diffusion, dt = 0.7, 0.1
    rng = np.random.default_rng(dims)
    steps = rng.normal(scale=np.sqrt(2 * diffusion * dt), size=(300, 50, dims))
    ensemble = np.mean([msd(np.cumsum(s, axis=0))[1][:5] for s in steps], axis=0)
    expected = 2 * dims * diffusion * dt * np.arange(1, 6)
    np.testing.assert_allclose(ensemble, expected, rtol=0.05)


def test_directed_line_has_alpha_two():
    positions = np.outer(np.arange(60.0), [0.3, -1.2, 2.5])
    assert anomalous_exponent(*msd(positions)) == pytest.approx(2.0, abs=1e-12)


def test_alpha_separates_free_from_driven_phantom():
    positions, driven = _phantom()
    alphas = np.array([anomalous_exponent(*msd(p)) for p in positions])
    assert abs(np.mean(alphas[~driven]) - 1) < 0.15
    assert abs(np.median(alphas[~driven]) - 1) < 0.15
    assert np.all(alphas[driven] > 1.6)


def test_alpha_default_fit_range_and_max_lag():
    lags = np.arange(1, 41)
    values = np.where(lags <= 10, lags**1.0, 10.0 * (lags / 10.0) ** 2)  # kink at lag 10
    assert anomalous_exponent(lags, values) == pytest.approx(1.0)  # first quarter: lags 1-10
    assert anomalous_exponent(lags, values, max_lag=3) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="two or more"):
        anomalous_exponent(lags, values, max_lag=1)


# --------------------------------------------------------------------- speeds and threshold


def test_sliding_speeds_of_constant_velocity_with_gap():
    velocity = np.array([0.0, 3.0, 4.0])  # um/frame: 5 um per frame
    positions = np.arange(10.0)[:, None] * velocity
    table = _table(positions[None], ["z", "y", "x"], frame_interval_s=0.5)
    table = table[table["frame"] != 6]  # a gap (as linked with memory)
    speeds = sliding_speeds(table, 2)
    np.testing.assert_array_equal(speeds["frame"], [0, 1, 2, 3, 5, 7])  # no window ends at 6
    np.testing.assert_allclose(speeds["speed_um_s"], 10.0)
    np.testing.assert_allclose(speeds["t_s"], speeds["frame"] * 0.5)
    from_interval = sliding_speeds(table.drop(columns="t_s"), 2, frame_interval_s=0.5)
    pd.testing.assert_frame_equal(from_interval, speeds)
    assert mean_speeds(table, 2).loc[0] == pytest.approx(10.0)


def _mixture_antimode(weights, log_medians, log_sigmas) -> float:
    """The density minimum of a two-component log-normal mixture in log space, numerically."""

    def density(x):
        return np.sum(weights * norm.pdf(x, log_medians, log_sigmas))

    low, high = log_medians
    return float(np.exp(minimize_scalar(density, bounds=(low, high), method="bounded").x))


def test_speed_threshold_near_true_antimode_of_lognormal_mixture():
    weights, medians, sigmas = np.array([5 / 6, 1 / 6]), np.log([3.0, 25.0]), np.array([0.35, 0.3])
    truth = _mixture_antimode(weights, medians, sigmas)
    rng = np.random.default_rng(4)
    fast = rng.random(600) < weights[1]  # about 1 fast cell in 6
    logs = rng.normal(medians[fast.astype(int)], sigmas[fast.astype(int)])
    speeds = np.exp(logs)
    assert abs(speed_threshold(speeds) / truth - 1) < 0.15


def test_speed_threshold_classifies_phantom_cells():
    positions, driven = _phantom()
    table = _table(positions, ["z", "y", "x"], frame_interval_s=0.2)
    speeds = mean_speeds(table, 5)
    threshold = speed_threshold(speeds)
    assert 2.5 < threshold < 20.0  # between the free (~2 um/s) and driven (20 um/s) speeds
    assert np.mean((speeds.to_numpy() > threshold) == driven) >= 0.9


def test_speed_threshold_rejects_unimodal_and_too_few():
    unimodal = np.exp(np.random.default_rng(5).normal(1.0, 0.3, 200))
    with pytest.raises(ValueError, match="not bimodal"):
        speed_threshold(unimodal)
    with pytest.raises(ValueError, match="at least 4"):
        speed_threshold([1.0, 10.0, 11.0])
    with pytest.raises(ValueError, match="positive"):
        speed_threshold([1.0, 2.0, 10.0, 0.0])


def test_phantom_mixture_and_drift():
    positions, driven = _phantom(seed=2)
    assert positions.shape == (120, 100, 3) and driven.sum() == 20
    drift = (positions[:, -1, 2] - positions[:, 0, 2]) / (99 * 0.2)
    assert np.mean(drift[driven]) == pytest.approx(20.0, abs=0.5)
    assert abs(np.mean(drift[~driven])) < 0.5


# -------------------------------------------------------------------------------- tracking


def _render(truth_um: np.ndarray, shape, noise=0.01, seed=0) -> np.ndarray:
    """``(T, Z, Y, X)`` volumes of unit Gaussian blobs at ``truth_um`` ``(T, N, 3)``; NaN rows
    are blobs absent from that frame."""
    axes = [(np.arange(n) + 0.5) * v for n, v in zip(shape, VOXEL_UM)]  # voxel centres
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    volumes = np.zeros((len(truth_um), *shape))
    for frame, centres in enumerate(truth_um):
        for centre in centres[np.all(np.isfinite(centres), axis=1)]:
            volumes[frame] += np.exp(-0.5 * np.sum(((grid - centre) / BLOB_SIGMA_UM) ** 2, -1))
    return volumes + noise * np.random.default_rng(seed).standard_normal(volumes.shape)


def _moving_blobs(n_frames=4):
    starts = np.array([[8.0, 5.2, 5.3], [12.3, 8.1, 17.7], [9.7, 18.0, 8.1]])  # um (z, y, x)
    steps = np.array([[0.6, 0.7, 0.35], [-0.8, 0.4, -0.6], [0.5, -0.55, 0.45]])  # um/frame
    return starts[None] + np.arange(n_frames)[:, None, None] * steps[None]


def test_track_recovers_positions_and_links_each_blob():
    truth = _moving_blobs()
    volumes = _render(truth, (12, 48, 48))
    tracks = track(
        volumes,
        voxel_size_um=VOXEL_UM,
        frame_interval_s=0.5,
        diameter_um=DIAMETER_UM,
        search_range_um=3.0,
        minmass=1.0,
    )
    assert list(tracks.columns) == ["frame", "particle", "t_s", "z", "y", "x", "mass"]
    assert len(tracks) == truth.shape[0] * truth.shape[1]
    np.testing.assert_allclose(tracks["t_s"], tracks["frame"] * 0.5)
    for _, one in tracks.groupby("particle"):
        assert list(one["frame"]) == [0, 1, 2, 3]
        found = one[["z", "y", "x"]].to_numpy()
        blob = np.argmin(np.sum((truth[0] - found[0]) ** 2, axis=1))
        assert np.all(np.abs(found - truth[:, blob]) / VOXEL_UM < 0.3)
    assert tracks["particle"].nunique() == truth.shape[1]


def test_track_memory_bridges_a_missing_frame():
    truth = _moving_blobs()
    truth[2, 1] = np.nan  # blob 1 vanishes in frame 2
    volumes = _render(truth, (12, 48, 48))
    kwargs = dict(
        voxel_size_um=VOXEL_UM,
        frame_interval_s=0.5,
        diameter_um=DIAMETER_UM,
        search_range_um=3.0,
        minmass=1.0,
    )
    assert track(volumes, memory=1, **kwargs)["particle"].nunique() == 3
    assert track(volumes, memory=0, **kwargs)["particle"].nunique() == 4


def test_odd_diameter_rounding():
    assert odd_diameter_px((8.0, 2.0, 2.95), (2.0, 0.5, 0.5)) == (5, 5, 5)
    assert odd_diameter_px(3.0, (2.0, 0.5, 0.25)) == (3, 7, 13)


@pytest.mark.parametrize(
    "volumes, kwargs, message",
    [
        (np.zeros((8, 8, 8)), {}, r"\(T, Z, Y, X\)"),
        (np.zeros((2, 0, 8, 8)), {}, "empty"),
        (np.zeros((2, 8, 16, 16)), {}, "no objects detected.*minmass.*diameter"),
        (np.ones((2, 8, 16, 16)), {"voxel_size_um": (0.0, 0.5, 0.5)}, "voxel_size_um"),
        (np.ones((2, 8, 16, 16)), {"frame_interval_s": -1.0}, "frame_interval_s"),
        (np.ones((2, 8, 16, 16)), {"diameter_um": 0.0}, "diameter_um"),
    ],
    ids=["ndim", "empty", "no-detections", "voxel", "interval", "diameter"],
)
def test_track_rejects_bad_input(volumes, kwargs, message):
    arguments = dict(
        voxel_size_um=VOXEL_UM, frame_interval_s=0.5, diameter_um=DIAMETER_UM, search_range_um=3.0
    )
    with pytest.raises(ValueError, match=message):
        track(volumes, **{**arguments, **kwargs})
