import math

import numpy as np
import pytest
import torch
from scipy.special import eval_jacobi

from fgat.optics.zernike import DEFAULT_INDICES, noll_to_nm, zernike, zernike_basis, zernike_phase

# Noll (1976), Table 1: j -> (n, m), sign of m = sin (odd j) / cos (even j).
NOLL_TABLE = {
    1: (0, 0),
    2: (1, 1),
    3: (1, -1),
    4: (2, 0),
    5: (2, -2),
    6: (2, 2),
    7: (3, -1),
    8: (3, 1),
    9: (3, -3),
    10: (3, 3),
    11: (4, 0),
    12: (4, 2),
    13: (4, -2),
    14: (4, 4),
    15: (4, -4),
    16: (5, 1),
    17: (5, -1),
    18: (5, 3),
    19: (5, -3),
    20: (5, 5),
    21: (5, -5),
    22: (6, 0),
}


def reference_zernike(j, rho, theta):
    """Independent float64 Noll Zernike via the Jacobi form of the radial polynomial."""
    n, m = NOLL_TABLE[j]
    k = (n - abs(m)) // 2
    radial = (-1) ** k * rho ** abs(m) * eval_jacobi(k, abs(m), 0, 1 - 2 * rho**2)
    if m == 0:
        return math.sqrt(n + 1) * radial
    angular = np.cos(m * theta) if m > 0 else np.sin(-m * theta)
    return math.sqrt(2 * (n + 1)) * radial * angular


def test_noll_indices_match_noll_table():
    assert {j: noll_to_nm(j) for j in NOLL_TABLE} == NOLL_TABLE
    assert DEFAULT_INDICES == tuple(range(5, 22))


@pytest.mark.parametrize("j", list(NOLL_TABLE))
def test_against_independent_float64_formula(j):
    rng = np.random.default_rng(j)
    rho = rng.uniform(0, 1, 500)
    theta = rng.uniform(-np.pi, np.pi, 500)
    ours = zernike(j, torch.from_numpy(rho), torch.from_numpy(theta)).numpy()
    np.testing.assert_allclose(ours, reference_zernike(j, rho, theta), rtol=1e-12, atol=1e-12)


def test_orthonormal_on_the_unit_disk():
    # Gauss-Legendre in rho (exact for these polynomials) times a uniform grid in theta.
    nodes, weights = np.polynomial.legendre.leggauss(40)
    rho = 0.5 * (nodes + 1)
    theta = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    r, t = np.meshgrid(rho, theta, indexing="ij")
    w = (0.5 * weights * rho)[:, None] * (2 * np.pi / 64) / np.pi  # dA / pi
    basis = zernike_basis(range(1, 23), torch.from_numpy(r), torch.from_numpy(t)).numpy()
    gram = np.einsum("aij,bij,ij->ab", basis, basis, w)
    np.testing.assert_allclose(gram, np.eye(22), atol=1e-12)


def test_zero_outside_and_float32(dtype):
    rho = torch.tensor([0.0, 0.5, 1.0, 1.0001, 2.0], dtype=dtype)
    theta = torch.zeros_like(rho)
    value = zernike(4, rho, theta)
    assert value.dtype == dtype
    assert value[3:].abs().max() == 0
    assert value[2].item() == pytest.approx(math.sqrt(3), rel=1e-6)  # defocus at the edge


def test_phase_rms_is_coefficient_norm():
    # With RMS normalisation the pupil RMS of sum c_j Z_j (in waves) is ||c||_2.
    nodes, weights = np.polynomial.legendre.leggauss(40)
    rho = 0.5 * (nodes + 1)
    theta = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    r, t = np.meshgrid(rho, theta, indexing="ij")
    w = torch.from_numpy((0.5 * weights * rho)[:, None] * (2 * np.pi / 64) / np.pi)
    basis = zernike_basis(DEFAULT_INDICES, torch.from_numpy(r), torch.from_numpy(t))
    c = torch.from_numpy(np.random.default_rng(0).uniform(-1, 1, 17))
    waves = zernike_phase(c, basis) / (2 * math.pi)
    assert float(torch.sqrt((waves**2 * w).sum())) == pytest.approx(float(c.norm()), rel=1e-10)


def test_phase_gradient_and_shape_error():
    rho = torch.rand(8, 8, dtype=torch.float64)
    theta = torch.rand(8, 8, dtype=torch.float64)
    basis = zernike_basis([5, 6], rho, theta)
    c = torch.tensor([0.1, -0.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: zernike_phase(x, basis), (c,))
    with pytest.raises(ValueError, match="expected \\(2,\\)"):
        zernike_phase(torch.zeros(3, dtype=torch.float64), basis)
    with pytest.raises(ValueError, match="Noll index"):
        noll_to_nm(0)
