"""The cross-information of JPGM (Note S4) against independent references: central finite
differences of the forward model, dense float64 linear algebra, and a linear model whose
Jacobians, blocks and leakage are known exactly."""

import numpy as np
import pytest
import torch
from torch import nn

from fgat.optics.crossinfo import (
    combined_metric,
    cross_information,
    estimated_blocks,
    fourier_metric,
    jpgm_jacobians,
)
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system

DEPTHS = [-10.0, -5.0, 0.0, 5.0, 10.0]


@pytest.fixture(scope="module")
def scene():
    """The small system's JPGM (float64, MFT) at an aberrated, shifted point off the pixel grid
    (bilinear crops have kinks at whole pixels), and a random 5 x 24 x 24 object."""
    generator = torch.Generator().manual_seed(0)
    jpgm = JPGM(load_system("small"), DEPTHS, crop_radius_px=16, dtype=torch.float64, method="mft")
    with torch.no_grad():
        jpgm.zernike_coefficients.copy_(0.05 * torch.randn(17, generator=generator))
        jpgm.intercepts.copy_(torch.rand(7, 2, generator=generator) * 0.8 - 0.4)
        jpgm.slopes.copy_(torch.rand(7, 2, generator=generator) * 0.6 - 0.3)
    volume = torch.zeros(5, 24, 24, dtype=torch.float64)
    volume[:, 8:16, 8:16] = torch.rand(5, 8, 8, generator=generator, dtype=torch.float64)
    return jpgm, volume, cross_information(jpgm, volume)


def predict(jpgm, volume, theta):
    """The predicted views at the parameter vector ``(c, b.flatten(), s.flatten())``."""
    c, b, s = torch.split(theta, [17, 14, 14])
    probe = JPGM(load_system("small"), DEPTHS, crop_radius_px=16, dtype=torch.float64, method="mft")
    with torch.no_grad():
        probe.zernike_coefficients.copy_(c)
        probe.intercepts.copy_(b.reshape(7, 2))
        probe.slopes.copy_(s.reshape(7, 2))
        return FLFMOperator(probe(), volume.shape).forward(volume).reshape(-1)


def test_jacobian_columns_equal_central_differences(scene):
    jpgm, volume, info = scene
    theta = torch.cat(
        [jpgm.zernike_coefficients, jpgm.intercepts.flatten(), jpgm.slopes.flatten()]
    ).detach()
    jacobian = torch.cat([info.jacobian_pupil, info.jacobian_geometry], dim=1)
    assert jacobian.shape == (7 * 24 * 24, 45)
    step = 1e-5
    for column in (0, 6, 16, 17, 24, 30, 31, 44):  # Zernike, intercepts (row, col), slopes
        offset = torch.zeros_like(theta)
        offset[column] = step
        reference = predict(jpgm, volume, theta + offset) - predict(jpgm, volume, theta - offset)
        reference /= 2 * step
        assert float((jacobian[:, column] - reference).norm() / reference.norm()) < 1e-5


def test_blocks_schur_complements_and_standard_errors_against_dense_algebra(scene):
    _, _, info = scene
    hessian = info.hessian.numpy()
    jacobian = torch.cat([info.jacobian_pupil, info.jacobian_geometry], dim=1).numpy()
    np.testing.assert_allclose(hessian, jacobian.T @ jacobian, rtol=1e-10, atol=1e-12)
    for block in (info.schur_pupil, info.schur_geometry):
        np.testing.assert_array_equal(block.numpy(), block.numpy().T)
        assert np.linalg.eigvalsh(block.numpy()).min() > 0
    # det H = det A det S_G = det D det S_P
    logdet = np.linalg.slogdet(hessian)[1]
    assert logdet == pytest.approx(
        np.linalg.slogdet(info.A.numpy())[1] + np.linalg.slogdet(info.schur_geometry.numpy())[1],
        rel=1e-10,
    )
    assert logdet == pytest.approx(
        np.linalg.slogdet(info.D.numpy())[1] + np.linalg.slogdet(info.schur_pupil.numpy())[1],
        rel=1e-10,
    )
    covariance = 0.02**2 * np.linalg.inv(hessian)  # sigma^2 H^-1
    errors = info.standard_errors(0.02)
    np.testing.assert_allclose(errors["zernike"], np.sqrt(np.diag(covariance)[:17]), rtol=1e-8)
    geometry = np.sqrt(np.diag(covariance)[17:])
    np.testing.assert_allclose(errors["intercepts"].flatten(), geometry[:14], rtol=1e-8)
    np.testing.assert_allclose(errors["slopes"].flatten(), geometry[14:], rtol=1e-8)
    only = info.standard_errors(0.02, "zernike")  # the shifts known: A^-1
    assert set(only) == {"zernike"}
    np.testing.assert_allclose(
        only["zernike"], 0.02 * np.sqrt(np.diag(np.linalg.inv(info.A.numpy()))), rtol=1e-8
    )
    assert bool((only["zernike"] <= errors["zernike"]).all())  # the joint fit costs precision


def test_modal_profiles_are_unit_vectors(scene):
    _, _, info = scene
    for profile, block in ((info.eta_b, info.C_b), (info.eta_s, info.C_s)):
        assert float(profile.square().sum()) == pytest.approx(1.0, abs=1e-12)
        row = 3
        expected = np.linalg.norm(block.numpy()[row]) / np.linalg.norm(block.numpy())
        assert float(profile[row]) == pytest.approx(expected, rel=1e-12)
    assert info.C_b.shape == info.C_s.shape == (17, 14)


def test_views_and_diagonal_weights_select_rows(scene):
    jpgm, volume, info = scene
    pupil, geometry = jpgm_jacobians(jpgm, volume, views=[2, 5])
    rows = torch.cat([torch.arange(576) + 576 * v for v in (2, 5)])
    np.testing.assert_allclose(pupil.numpy(), info.jacobian_pupil[rows].numpy(), rtol=1e-12)
    weights = torch.zeros(7, 24, 24, dtype=torch.float64)
    weights[[2, 5]] = 1.0
    masked = cross_information(jpgm, volume, weights=weights.reshape(-1))
    np.testing.assert_allclose(
        masked.C.numpy(), (pupil.T @ geometry).numpy(), rtol=1e-10, atol=1e-14
    )


@pytest.mark.parametrize("estimate", ["zernike", "shifts"])
def test_one_estimated_group_computes_its_own_block_only(scene, estimate):
    """A fit that estimated one group gets that group's Jacobian (the other is empty, not
    computed) and the same sandwich standard errors as from the whole cross-information."""
    jpgm, volume, info = scene
    blocks = estimated_blocks(estimate)
    assert blocks == {"zernike": ("pupil",), "shifts": ("geometry",)}[estimate]
    one = cross_information(jpgm, volume, blocks=blocks)
    kept, full = ("jacobian_pupil", "A") if estimate == "zernike" else ("jacobian_geometry", "D")
    torch.testing.assert_close(getattr(one, kept), getattr(info, kept), rtol=0, atol=0)
    torch.testing.assert_close(getattr(one, full), getattr(info, full), rtol=1e-12, atol=0)
    other = one.jacobian_geometry if estimate == "zernike" else one.jacobian_pupil
    assert other.shape == (7 * 24 * 24, 0)
    residual = torch.randn(7 * 24 * 24, generator=torch.Generator().manual_seed(4)).double()
    expected = info.sandwich_errors(residual, estimate)
    got = one.sandwich_errors(residual, estimate)
    assert set(got) == set(expected)
    for name in got:
        torch.testing.assert_close(got[name], expected[name], rtol=1e-10, atol=0)
    assert estimated_blocks("joint") == ("pupil", "geometry")
    with pytest.raises(ValueError, match="blocks must be one or both"):
        jpgm_jacobians(jpgm, volume, blocks=("optics",))
    with pytest.raises(ValueError, match="estimate must be"):
        estimated_blocks("all")


def test_fourier_metric_is_the_dense_quadratic_form():
    generator = torch.Generator().manual_seed(1)
    residual = torch.randn(2, 4, 5, generator=generator, dtype=torch.float64)
    columns = torch.randn(3, 40, generator=generator, dtype=torch.float64)
    metric = combined_metric([(1.0, None), (0.25, fourier_metric(residual))])
    weighted = metric(columns)
    gram = (weighted.conj() @ weighted.T).real.numpy()
    # W = I + 0.25 F^H diag(1 / |F r|) F, F the per-view 2D DFT as a dense matrix
    dft = np.kron(np.fft.fft(np.eye(4)), np.fft.fft(np.eye(5)))
    spectra = np.abs(np.fft.fft2(residual.numpy())).reshape(2, -1)
    blocks = [dft.conj().T @ np.diag(1.0 / spectra[v]) @ dft for v in range(2)]
    dense = np.eye(40) + 0.25 * np.block(
        [[blocks[0], np.zeros((20, 20))], [np.zeros((20, 20)), blocks[1]]]
    )
    c = columns.numpy()
    np.testing.assert_allclose(gram, (c @ dense @ c.T).real, rtol=1e-10)


class LinearOptics(nn.Module):
    """A stand-in for JPGM whose 'PSF' is linear in its parameters: ``base + sum_j c_j P_j +
    sum_g theta_g G_g``, with the JPGM parameter names, so that Jacobians, blocks and the
    leakage of a refit are known exactly."""

    def __init__(self, pupil_basis, geometry_basis, base):
        super().__init__()
        self.zernike_coefficients = nn.Parameter(
            torch.zeros(pupil_basis.shape[0], dtype=base.dtype)
        )
        self.intercepts = nn.Parameter(torch.zeros(2, 2, dtype=base.dtype))
        self.slopes = nn.Parameter(torch.zeros(2, 2, dtype=base.dtype))
        self.register_buffer("xi", torch.zeros(1, dtype=base.dtype))
        self.zernike_indices = tuple(range(5, 5 + pupil_basis.shape[0]))
        self.pupil_basis, self.geometry_basis, self.base = pupil_basis, geometry_basis, base

    def forward(self):
        geometry = torch.cat([self.intercepts.flatten(), self.slopes.flatten()])
        return (
            self.base
            + torch.tensordot(self.zernike_coefficients, self.pupil_basis, dims=1)
            + torch.tensordot(geometry, self.geometry_basis, dims=1)
        )


class PlaneSum:
    """An 'operator' whose views are the PSF planes summed: linear, no volume needed."""

    def __init__(self, psf):
        self.psf = psf

    def forward(self, volume):
        return self.psf.sum(dim=1)


def linear_model(seed, orthogonal):
    generator = torch.Generator().manual_seed(seed)
    shape = (2, 1, 6, 6)  # (V, Z, h, w): 72 image pixels
    pupil = torch.randn(4, *shape, generator=generator, dtype=torch.float64)
    geometry = torch.randn(8, *shape, generator=generator, dtype=torch.float64)
    if orthogonal:  # disjoint pixel supports: the image responses cannot overlap
        pupil[..., :3, :] = 0.0
        geometry[..., 3:, :] = 0.0
    base = torch.randn(shape, generator=generator, dtype=torch.float64)
    return LinearOptics(pupil, geometry, base), pupil.reshape(4, -1).T, geometry.reshape(8, -1).T


def test_cross_information_vanishes_for_orthogonal_groups():
    model, _, geometry = linear_model(0, orthogonal=True)
    info = cross_information(model, torch.zeros(1, 1, 1), operator=PlaneSum)
    assert float(info.C.abs().max()) == 0.0
    np.testing.assert_allclose(info.jacobian_geometry.numpy(), geometry.numpy(), rtol=1e-14)
    np.testing.assert_allclose(info.schur_pupil.numpy(), info.A.numpy(), rtol=1e-14)
    assert float(info.leakage(torch.ones(8)).abs().max()) == 0.0


def test_leakage_map_is_exact_on_a_linear_model():
    model, pupil, geometry = linear_model(1, orthogonal=False)
    info = cross_information(model, torch.zeros(1, 1, 1), operator=PlaneSum)
    delta = torch.tensor([0.3, -0.1, 0.2, 0.05, 0.0, 0.4, -0.2, 0.1], dtype=torch.float64)
    # the refit: least-squares Zernike change that best explains the image the shift produced
    measured, *_ = np.linalg.lstsq(pupil.numpy(), -(geometry @ delta).numpy(), rcond=None)
    np.testing.assert_allclose(info.leakage(delta).numpy(), measured, rtol=1e-10)
    regularised = cross_information(
        model, torch.zeros(1, 1, 1), operator=PlaneSum, lambda_pupil=2.0, lambda_geometry=0.5
    )
    np.testing.assert_allclose((regularised.A - info.A).numpy(), 2.0 * np.eye(4), atol=1e-12)
    np.testing.assert_allclose((regularised.D - info.D).numpy(), 0.5 * np.eye(8), atol=1e-12)


def test_singular_block_and_bad_arguments_are_named(scene):
    jpgm, volume, info = scene
    empty = cross_information(jpgm, torch.zeros_like(volume))  # no light: no information
    with pytest.raises(ValueError, match=r"the block D \(shifts\) is singular"):
        empty.schur_pupil
    with pytest.raises(ValueError, match="weights must be 4032 non-negative numbers"):
        cross_information(jpgm, volume, weights=torch.ones(10))
    with pytest.raises(ValueError, match="delta_geometry must have 28 entries"):
        info.leakage(torch.zeros(5))
    with pytest.raises(ValueError, match="estimate must be 'joint', 'zernike' or 'shifts'"):
        info.standard_errors(0.1, "all")


@pytest.mark.parametrize("estimate", ["joint", "zernike", "shifts"])
def test_sandwich_errors_are_the_least_squares_spread_under_unequal_noise(estimate):
    """On a linear model with pixel noise of known, unequal standard deviations ``v``, the
    least-squares estimates' spread over 4000 noisy refits is the sandwich with ``r = v``; with
    equal ``v = sigma`` the sandwich is the white-noise standard error."""
    model, pupil, geometry = linear_model(1, orthogonal=False)
    info = cross_information(model, torch.zeros(1, 1, 1), operator=PlaneSum)
    n = pupil.shape[0]
    generator = torch.Generator().manual_seed(3)
    spread = 0.05 * (1 + 4 * torch.rand(n, generator=generator, dtype=torch.float64))
    columns = {
        "zernike": pupil,
        "shifts": geometry,
        "joint": torch.cat([pupil, geometry], 1),
    }[estimate]
    noise = torch.randn(4000, n, generator=generator, dtype=torch.float64) * spread
    estimates = torch.linalg.lstsq(columns, noise.T).solution.T  # the refits' errors
    measured = estimates.std(dim=0)
    predicted = info.sandwich_errors(spread, estimate)
    flat = torch.cat(
        [predicted[g].reshape(-1) for g in ("zernike", "intercepts", "slopes") if g in predicted]
    )
    np.testing.assert_allclose(flat.numpy(), measured.numpy(), rtol=0.06)
    equal = info.sandwich_errors(torch.full((n,), 0.02, dtype=torch.float64), estimate)
    white = info.standard_errors(0.02, estimate)
    assert list(equal) == list(white)
    for group, value in white.items():
        np.testing.assert_allclose(equal[group].numpy(), value.numpy(), rtol=1e-10)
    with pytest.raises(ValueError, match=f"residual must have {n} entries"):
        info.sandwich_errors(torch.ones(n + 1), estimate)


def test_sandwich_errors_use_the_diagonal_weights(scene):
    jpgm, volume, _ = scene
    generator = torch.Generator().manual_seed(4)
    weights = (torch.rand(7 * 24 * 24, generator=generator) > 0.2).double()
    residual = torch.randn(7 * 24 * 24, generator=generator, dtype=torch.float64)
    info = cross_information(jpgm, volume, weights=weights)
    got = info.sandwich_errors(residual, "zernike", weights)["zernike"]
    used = weights > 0  # dense reference on the used rows only
    jacobian, r = info.jacobian_pupil[used], residual[used]
    inverse = torch.linalg.inv(jacobian.T @ jacobian)
    covariance = inverse @ (jacobian.T * r.square()) @ jacobian @ inverse
    np.testing.assert_allclose(got.numpy(), covariance.diagonal().sqrt().numpy(), rtol=1e-8)


def test_depth_chunked_jacobians_and_blocks_equal_the_whole_stacks(monkeypatch):
    """Accumulating the Jacobian over slices of planes, a few columns per pass, through a
    measured operator (guard band, gains) rebuilt for each slice, with the blocks and the
    sandwich summed over row blocks: the unchunked float64 result and dense products."""
    from functools import partial

    import fgat.optics.crossinfo as crossinfo
    from fgat.optics.acquisition import MeasuredOperator

    generator = torch.Generator().manual_seed(1)
    jpgm = JPGM(
        load_system("small"),
        [-6.0, 0.0, 6.0],
        crop_radius_px=6,
        zernike_indices=(4, 5, 6),
        dtype=torch.float64,
        method="mft",
    )
    with torch.no_grad():
        jpgm.zernike_coefficients.copy_(torch.tensor([0.05, -0.03, 0.02]))
        jpgm.intercepts.copy_(torch.rand(7, 2, generator=generator, dtype=torch.float64) - 0.5)
    volume = torch.rand(3, 12, 12, generator=generator, dtype=torch.float64)
    gains = torch.linspace(0.8, 1.2, 7, dtype=torch.float64)
    operator = partial(MeasuredOperator, view_shape=(8, 8), guard_px=2, gains=gains)
    n = 7 * 8 * 8
    weights = torch.rand(n, generator=generator, dtype=torch.float64)
    whole = cross_information(jpgm, volume, weights=weights, operator=operator)
    monkeypatch.setattr(crossinfo, "ROW_BLOCK", 100)  # several row blocks
    chunked = cross_information(
        jpgm, volume, weights=weights, operator=operator, chunk_size=5, depth_chunk=2
    )
    for a, b in (
        (whole.jacobian_pupil, chunked.jacobian_pupil),
        (whole.jacobian_geometry, chunked.jacobian_geometry),
    ):
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-12)
    dense = torch.cat([whole.jacobian_pupil, whole.jacobian_geometry], 1)
    hessian = dense.T @ (dense * weights[:, None])
    torch.testing.assert_close(chunked.hessian, 0.5 * (hessian + hessian.T), rtol=1e-9, atol=1e-14)
    residual = torch.randn(n, generator=generator, dtype=torch.float64)
    errors = chunked.sandwich_errors(residual, "joint", weights)
    scaled = dense * (weights * residual)[:, None]
    inverse = torch.linalg.inv(hessian)
    expected = (inverse @ (scaled.T @ scaled) @ inverse).diagonal().sqrt()
    torch.testing.assert_close(errors["zernike"], expected[:3], rtol=1e-6, atol=0)
    torch.testing.assert_close(errors["slopes"].reshape(-1), expected[17:], rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match="depth_chunk must be a positive"):
        jpgm_jacobians(jpgm, volume, operator=operator, depth_chunk=0)


@pytest.mark.slow
def test_bead_cross_information_is_the_full_one_of_isolated_beads():
    """One Gaussian bead per plane, the beads' images apart and inside the views: the full
    cross-information of that volume (operator, views) is the sum of the beads' own terms,
    which bead_cross_information computes from the PSF stack alone."""
    from fgat.optics.crossinfo import bead_cross_information, modal_profiles

    generator = torch.Generator().manual_seed(2)
    jpgm = JPGM(
        load_system("small"),
        [-6.0, 0.0, 6.0],
        crop_radius_px=6,
        zernike_indices=(5, 7, 8, 11),
        dtype=torch.float64,
        method="mft",
    )
    with torch.no_grad():
        jpgm.zernike_coefficients.copy_(torch.tensor([0.05, -0.03, 0.02, 0.04]))
        jpgm.intercepts.copy_(torch.rand(7, 2, generator=generator, dtype=torch.float64) - 0.5)
        jpgm.slopes.copy_(torch.rand(7, 2, generator=generator, dtype=torch.float64) - 0.5)
    offsets = np.arange(-4, 5)
    gaussian = np.exp(-0.5 * offsets.astype(float) ** 2)
    bead = torch.from_numpy(np.outer(gaussian, gaussian) / gaussian.sum() ** 2)
    volume = torch.zeros(3, 66, 66, dtype=torch.float64)
    for plane, centre in enumerate((11, 33, 55)):  # images 13 + 8 px wide, 22 px apart
        volume[plane, centre - 4 : centre + 5, centre - 4 : centre + 5] = bead
    full = cross_information(jpgm, volume).C
    beads = bead_cross_information(jpgm, sigma_px=1.0, depth_chunk=2, chunk_size=5)
    assert beads.shape == (4, 28)
    torch.testing.assert_close(beads, full, rtol=1e-8, atol=1e-12 * float(full.abs().max()))
    eta_b, eta_s = modal_profiles(beads)
    torch.testing.assert_close(eta_b, full[:, :14].norm(dim=1) / full[:, :14].norm())
    torch.testing.assert_close(eta_s, full[:, 14:].norm(dim=1) / full[:, 14:].norm())
    with pytest.raises(ValueError, match="depth_chunk must be >= 1"):
        bead_cross_information(jpgm, depth_chunk=0)
