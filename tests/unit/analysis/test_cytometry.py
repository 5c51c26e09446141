"""Volumetric cytometry (Notes S8.7-S8.8): blob detection against known Gaussian blobs, the
fraction tests against scipy.stats on the same tables, and the classification of the cell
phantom against its truth."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from scipy.spatial import cKDTree

from fgat.analysis import cytometry
from fgat.analysis.cytometry import (
    BLOB_COLUMNS,
    cell_phantom,
    classify_cells,
    compare_fractions,
    detect_blobs,
    marker_classes,
)

AXES = ["z", "y", "x"]
VOXEL = (2.0, 0.5, 0.5)
MARKERS = ("CD11b", "Ferritin")
PHANTOM_VOXEL = (1.0, 0.5, 0.5)
CELL_RADIUS = 3.5


def gaussian_blobs(shape, voxel, centres_um, sigma_um, amplitudes):
    """Sum of isotropic (in um) Gaussians sampled at voxel centres ``(i + 0.5) * voxel``."""
    grids = np.meshgrid(
        *[(np.arange(n) + 0.5) * v for n, v in zip(shape, voxel)], indexing="ij", sparse=True
    )
    volume = np.zeros(shape)
    for centre, amplitude in zip(centres_um, amplitudes):
        r2 = sum((g - c) ** 2 for g, c in zip(grids, centre))
        volume += amplitude * np.exp(-0.5 * r2 / sigma_um**2)
    return volume


@pytest.fixture(scope="module")
def phantom():
    return cell_phantom(
        (32, 96, 96),
        voxel_size_um=PHANTOM_VOXEL,
        n_cells=40,
        marker_names=MARKERS,
        class_ratio=(1, 1, 1, 1),
        nucleus_radius_um=2.0,
        cell_radius_um=CELL_RADIUS,
        seed=0,
        background=0.1,
        noise_std=0.05,
    )


def classify(channels, **overrides):
    options = dict(
        voxel_size_um=PHANTOM_VOXEL,
        sigma_um=1.0,
        thresholds={"CD11b": 0.2, "Ferritin": 0.2},
        match_radius_um=CELL_RADIUS / 2,
        marker_sigma_um=0.7 * CELL_RADIUS,
    )
    return classify_cells(
        channels["nuclei"], {name: channels[name] for name in MARKERS}, **(options | overrides)
    )


def test_detect_blobs_finds_anisotropic_gaussians_at_subvoxel_positions():
    shape = (24, 96, 96)
    rng = np.random.default_rng(7)
    lattice = np.array([(z, y, x) for z in (12.0, 34.0) for y in (10.0, 26.0) for x in (12, 36)])
    centres = lattice + rng.uniform(-1.5, 1.5, lattice.shape)  # off the voxel grid in um
    volume = gaussian_blobs(shape, VOXEL, centres, 2.0, rng.uniform(0.6, 1.0, len(centres)))
    volume += 0.1 + rng.normal(0.0, 0.02, shape)

    blobs = detect_blobs(volume, voxel_size_um=VOXEL, sigma_um=2.0, threshold=0.2)

    assert list(blobs.columns) == list(BLOB_COLUMNS)
    assert len(blobs) == len(centres)  # no false positives
    distance, nearest = cKDTree(blobs[AXES].to_numpy()).query(centres)
    assert sorted(nearest) == list(range(len(centres)))  # one detection per blob
    error = np.abs(blobs[AXES].to_numpy()[nearest] - centres)
    assert np.all(error <= np.asarray(VOXEL)), error.max(axis=0)  # within one voxel per axis
    sizes = blobs[["sigma_z", "sigma_y", "sigma_x"]].to_numpy()
    assert np.all((sizes > 2.0 / np.sqrt(2) - 1e-9) & (sizes < 2.0 * np.sqrt(2) + 1e-9))


def test_detect_blobs_empty_result_is_a_table_with_the_columns(monkeypatch):
    monkeypatch.setattr(cytometry, "blob_log", lambda *args, **kwargs: np.empty((0, 6)))
    volume = gaussian_blobs((8, 16, 16), (1, 1, 1), [(4, 8, 8)], 1.5, [1.0])
    blobs = detect_blobs(volume, voxel_size_um=(1, 1, 1), sigma_um=1.5, threshold=0.5)
    assert blobs.empty and list(blobs.columns) == list(BLOB_COLUMNS)


@pytest.mark.parametrize(
    "volume, options, match",
    [
        (np.ones((8, 8)), {}, "volume"),
        (np.zeros((8, 16, 16)), {}, "empty"),
        (np.full((8, 16, 16), np.nan), {}, "finite"),
        (None, {"voxel_size_um": (0.0, 1.0, 1.0)}, "voxel_size_um"),
        (None, {"voxel_size_um": (1.0, 1.0)}, "voxel_size_um"),
        (None, {"sigma_um": -1.0}, "sigma_um"),
        (None, {"sigma_um": (1.0, 2.0)}, "sigma_um"),
        (None, {"threshold": 0.0}, "threshold"),
        (None, {"threshold": 1.5}, "threshold"),
    ],
)
def test_detect_blobs_bad_input(volume, options, match):
    if volume is None:
        volume = gaussian_blobs((8, 16, 16), (1, 1, 1), [(4, 8, 8)], 1.5, [1.0])
    kwargs = dict(voxel_size_um=(1.0, 1.0, 1.0), sigma_um=1.5, threshold=0.5) | options
    with pytest.raises(ValueError, match=match):
        detect_blobs(volume, **kwargs)


def test_compare_fractions_matches_scipy_on_the_same_tables():
    counts, reference = [31, 12, 25, 9], [40, 22, 18, 20]
    result = compare_fractions(counts, reference)

    table = np.array([counts, reference])
    assert result.chi2_pvalue == pytest.approx(stats.chi2_contingency(table).pvalue, rel=1e-12)
    assert result.chi2_dof == 3
    n, m = sum(counts), sum(reference)
    fisher = [
        stats.fisher_exact([[c, n - c], [r, m - r]]).pvalue for c, r in zip(counts, reference)
    ]
    np.testing.assert_allclose(result.fisher_pvalues, fisher, rtol=1e-12)
    np.testing.assert_allclose(result.fractions, np.array(counts) / n)
    np.testing.assert_allclose(result.reference_fractions, np.array(reference) / m)


def test_compare_fractions_two_classes_use_scipy_default_yates_correction():
    result = compare_fractions([30, 10], [20, 20])
    expected = stats.chi2_contingency(np.array([[30, 10], [20, 20]]), correction=True)
    assert result.chi2_pvalue == pytest.approx(expected.pvalue, rel=1e-12)


def test_compare_fractions_dicts_are_aligned_by_class_and_empty_classes_dropped():
    classes = marker_classes(MARKERS)
    counts = dict(zip(classes, [10, 0, 5, 7]))
    reference = dict(zip(reversed(classes), [9, 4, 0, 8]))  # keys in another order
    result = compare_fractions(counts, reference)

    assert result.classes == tuple(classes)
    np.testing.assert_array_equal(result.reference_counts, [8, 0, 4, 9])
    expected = stats.chi2_contingency(np.array([[10, 5, 7], [8, 4, 9]])).pvalue
    assert result.chi2_pvalue == pytest.approx(expected, rel=1e-12)
    assert result.fisher_pvalues[1] == 1.0


def test_compare_fractions_identical_and_halved_class():
    same = compare_fractions([25, 25, 25, 25], [50, 50, 50, 50])
    assert same.chi2_pvalue == pytest.approx(1.0)
    np.testing.assert_allclose(same.fisher_pvalues, 1.0)

    halved = compare_fractions([250, 250, 250, 125], [250, 250, 250, 250])
    assert halved.chi2_pvalue < 0.05
    assert halved.fisher_pvalues[3] < 0.05


@pytest.mark.parametrize(
    "counts, reference, match",
    [
        ([5, -1, 3], [4, 4, 4], "non-negative"),
        ([5, 1.5, 3], [4, 4, 4], "whole"),
        ([5, 1, 3], [4, 4], "classes"),
        ({"a": 1, "b": 2}, {"a": 1, "c": 2}, "different classes"),
        ({"a": 1, "b": 2}, [1, 2], "both"),
        ([0, 0, 0], [4, 4, 4], "zero total"),
        ([3, 4], [0, 0], "zero total"),
        ([3], [4], "two classes"),
    ],
)
def test_compare_fractions_bad_input(counts, reference, match):
    with pytest.raises(ValueError, match=match):
        compare_fractions(counts, reference)


def test_cell_phantom_truth(phantom):
    channels, truth = phantom
    assert set(channels) == {"nuclei", *MARKERS}
    assert all(c.shape == (32, 96, 96) and c.dtype == np.float32 for c in channels.values())
    assert truth["class"].value_counts().to_dict() == dict.fromkeys(marker_classes(MARKERS), 10)
    centres = truth[AXES].to_numpy()
    assert cKDTree(centres).query(centres, k=2)[0][:, 1].min() >= 2 * CELL_RADIUS
    again, truth_again = cell_phantom(
        (32, 96, 96),
        voxel_size_um=PHANTOM_VOXEL,
        n_cells=40,
        nucleus_radius_um=2.0,
        cell_radius_um=CELL_RADIUS,
        seed=0,
        background=0.1,
        noise_std=0.05,
    )
    pd.testing.assert_frame_equal(truth, truth_again)
    np.testing.assert_array_equal(channels["CD11b"], again["CD11b"])


def test_classify_cells_recovers_phantom_classes(phantom):
    channels, truth = phantom
    table = classify(channels)

    assert list(table.columns[:4]) == ["nucleus", *AXES]
    for name in MARKERS:
        assert {f"{name}_matched", f"{name}_signal", f"{name}_positive"} <= set(table.columns)
    distance, nearest = cKDTree(table[AXES].to_numpy()).query(truth[AXES].to_numpy())
    found = distance < CELL_RADIUS / 2
    correct = found & (table["class"].to_numpy()[nearest] == truth["class"].to_numpy())
    assert correct.mean() >= 0.9, correct.mean()
    assert len(table) <= len(truth) + 2  # few spurious nuclei

    classes = marker_classes(MARKERS)
    detected = table["class"].value_counts().reindex(classes, fill_value=0)
    expected = truth["class"].value_counts().reindex(classes, fill_value=0)
    assert compare_fractions(detected.to_dict(), expected.to_dict()).chi2_pvalue > 0.05


def test_classify_cells_noise_only_marker_is_negative():
    channels, truth = cell_phantom(
        (24, 64, 64),
        voxel_size_um=PHANTOM_VOXEL,
        n_cells=10,
        class_ratio=(1, 1, 0, 0),  # no CD11b+ cell: that channel is background and noise
        nucleus_radius_um=2.0,
        cell_radius_um=CELL_RADIUS,
        seed=3,
        background=0.1,
        noise_std=0.05,
    )
    table = classify(channels)
    assert not table["CD11b_positive"].any()
    assert table["class"].str.startswith("CD11b-").all()


def test_classify_cells_bad_input(phantom):
    channels = phantom[0]
    with pytest.raises(ValueError, match="thresholds"):
        classify(channels, thresholds={"CD11b": 0.2})
    nuclei = channels["nuclei"]
    for markers, thresholds, match in (
        ({"CD11b": channels["CD11b"][:-1]}, {"CD11b": 0.2}, "shape"),
        ({"Ferritin": np.zeros_like(nuclei)}, {"Ferritin": 0.2}, "'Ferritin' is empty"),
        ({}, {}, "at least one marker"),
    ):
        with pytest.raises(ValueError, match=match):
            classify_cells(
                nuclei,
                markers,
                voxel_size_um=PHANTOM_VOXEL,
                sigma_um=1.0,
                thresholds=thresholds,
                match_radius_um=2.0,
            )
    with pytest.raises(ValueError, match="match_radius_um"):
        classify(channels, match_radius_um=0.0)


@pytest.mark.parametrize(
    "options, match",
    [
        ({"nucleus_radius_um": 4.0}, "nucleus_radius_um"),
        ({"class_ratio": (1, 1, 1)}, "class_ratio"),
        ({"marker_layout": "nucleus"}, "marker_layout"),
        ({"n_cells": 500}, "cannot fit"),
        ({"n_cells": 30}, "could not place"),
        ({"voxel_size_um": (1.0, -0.5, 0.5)}, "voxel_size_um"),
    ],
)
def test_cell_phantom_bad_input(options, match):
    kwargs = (
        dict(
            voxel_size_um=PHANTOM_VOXEL,
            n_cells=4,
            nucleus_radius_um=2.0,
            cell_radius_um=CELL_RADIUS,
            seed=0,
        )
        | options
    )
    with pytest.raises(ValueError, match=match):
        cell_phantom((16, 48, 48), **kwargs)
