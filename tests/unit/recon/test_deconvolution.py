import numpy as np
import pytest
import scipy.signal
import torch
from skimage.restoration import richardson_lucy

from fgat.optics.acquisition import MeasuredOperator
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system
from fgat.recon.deconvolution import deconvolve, iterate_deconvolution, momentum, poisson_cost
from fgat.sim.phantoms import beads


def algorithm_s1_reference(image, psf, iterations):
    """Literal float64 transcription of Algorithm S1 with scipy convolutions (A^T 1 = 1 assumed)."""
    views, depths = psf.shape[:2]

    def forward(volume):
        return np.stack(
            [
                sum(
                    scipy.signal.fftconvolve(volume[z], psf[v, z], mode="same")
                    for z in range(depths)
                )
                for v in range(views)
            ]
        )

    def adjoint(residual):
        return np.stack(
            [
                sum(
                    scipy.signal.correlate(residual[v], psf[v, z], mode="same", method="fft")
                    for v in range(views)
                )
                for z in range(depths)
            ]
        )

    estimate = np.ones((depths, *image.shape[1:]))
    previous = estimate.copy()
    epsilon = max(image.mean() * 1e-6, 1e-8)
    for k in range(iterations):
        beta = max(0.0, (k - 1) / (k + 2))
        point = np.maximum(estimate + beta * (estimate - previous), epsilon)
        ratio = image / np.maximum(forward(point), 1e-10)
        previous, estimate = estimate, np.maximum(point * adjoint(ratio), 0)
    return estimate


def small_problem(seed=0):
    rng = np.random.default_rng(seed)
    psf = rng.random((2, 3, 5, 5))
    truth = rng.random((3, 16, 18))
    operator = FLFMOperator(torch.from_numpy(psf), truth.shape)
    scale = float(operator.adjoint(torch.ones(2, 16, 18, dtype=torch.float64)).max())
    psf = psf / scale  # max(A^T 1) = 1, the normalisation Algorithm S1 assumes
    operator = FLFMOperator(torch.from_numpy(psf), truth.shape)
    image = operator.forward(torch.from_numpy(truth)).numpy()
    return psf, operator, image / image.max()


def test_momentum_schedule():
    assert [momentum(k) for k in range(4)] == [0.0, 0.0, 0.25, 0.4]
    assert momentum(1000) == pytest.approx(1.0, abs=3e-3)


def test_shb_is_algorithm_s1_exactly():
    psf, operator, image = small_problem()
    ours = deconvolve(torch.from_numpy(image), operator, 12, method="shb").numpy()
    np.testing.assert_allclose(ours, algorithm_s1_reference(image, psf, 12), rtol=1e-9, atol=1e-12)


def test_result_is_in_measurement_units_for_any_normalisation():
    psf, operator, image = small_problem()
    reference = deconvolve(torch.from_numpy(image), operator, 8).numpy()
    scaled_operator = FLFMOperator(torch.from_numpy(psf * 7.0), (3, 16, 18))
    ours = deconvolve(
        torch.from_numpy(image * 50.0 + 20.0), scaled_operator, 8, background=20.0
    ).numpy()
    np.testing.assert_allclose(ours, reference * 50.0 / 7.0, rtol=1e-9)


def test_first_two_shb_steps_are_rl():
    _, operator, image = small_problem(1)
    steps = {
        m: [
            s.estimate
            for s in iterate_deconvolution(torch.from_numpy(image), operator, 3, method=m)
        ]
        for m in ("rl", "shb")
    }
    torch.testing.assert_close(steps["shb"][0], steps["rl"][0])
    torch.testing.assert_close(steps["shb"][1], steps["rl"][1])
    assert not torch.allclose(steps["shb"][2], steps["rl"][2])


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 1e-5)])
def test_single_view_rl_equals_scikit_image(dtype, tol):
    rng = np.random.default_rng(3)
    image = rng.random((40, 50)) + 0.1
    psf = rng.random((7, 9))
    psf /= psf.sum()
    reference = richardson_lucy(image, psf, num_iter=25, clip=False)
    operator = FLFMOperator(torch.tensor(psf[None, None], dtype=dtype), (1, 40, 50))
    ours = deconvolve(torch.from_numpy(image[None]), operator, 25, method="rl")[0].double().numpy()
    assert np.abs(ours - reference).max() <= tol * np.abs(reference).max()


@pytest.fixture(scope="module")
def flfm_case():
    system = load_system("small")
    depths = np.linspace(-12, 12, 9)
    with torch.no_grad():
        psf = JPGM(system, depths)()
    truth = beads((9, 48, 48), 12, sigma=1.0, min_spacing=6, margin=(1, 8, 8), seed=4)
    operator = FLFMOperator(psf, truth.shape)
    clean = operator.forward(torch.from_numpy(truth))
    noisy = torch.poisson(clean / clean.max() * 500, generator=torch.Generator().manual_seed(0))
    return operator, truth, clean, noisy


def test_nonnegativity_and_flux(flfm_case):
    operator, _, _, noisy = flfm_case
    shifted = noisy - 3.0  # some pixels negative after the offset
    for step in iterate_deconvolution(shifted, operator, 15, method="shb"):
        assert step.estimate.min() >= 0
        flux = float(operator.forward(step.estimate).sum())
        assert flux == pytest.approx(float(shifted.clamp(min=0).sum()), rel=0.02)


def test_cost_decreases_and_tol_stops_early(flfm_case):
    operator, _, clean, _ = flfm_case
    costs = [s.cost for s in iterate_deconvolution(clean, operator, 30, method="rl")]
    assert all(b <= a + 1e-6 * abs(a) for a, b in zip(costs, costs[1:]))  # RL decreases Eq. S54
    seen = []
    deconvolve(clean, operator, 500, method="rl", tol=1e-4, callback=lambda k, v: seen.append(k))
    assert seen == list(range(len(seen))) and 2 < len(seen) < 500


def test_shb_reaches_rl_quality_in_fewer_iterations(flfm_case):
    operator, truth, _, noisy = flfm_case
    reference = torch.from_numpy(truth / truth.max())

    def errors(method):
        return [
            float(((s.estimate / s.estimate.max() - reference) ** 2).mean())
            for s in iterate_deconvolution(noisy, operator, 80, method=method)
        ]

    rl, shb = errors("rl"), errors("shb")
    assert min(shb[:20]) < rl[79]  # SHB within 20 iterations beats RL at 80 (4x)


def test_init_and_errors(flfm_case):
    operator, truth, clean, _ = flfm_case
    first = next(iterate_deconvolution(clean, operator, 1, init=torch.from_numpy(truth)))
    error_from_truth = float((first.estimate - torch.from_numpy(truth)).abs().mean())
    error_from_flat = float(
        (next(iterate_deconvolution(clean, operator, 1)).estimate - torch.from_numpy(truth))
        .abs()
        .mean()
    )
    assert error_from_truth < 0.5 * error_from_flat
    with pytest.raises(ValueError, match="method"):
        deconvolve(clean, operator, 5, method="admm")
    with pytest.raises(ValueError, match="positive integer"):
        deconvolve(clean, operator, 0)
    with pytest.raises(ValueError, match="init has shape"):
        deconvolve(clean, operator, 2, init=torch.ones(3, 3, 3))
    with pytest.raises(ValueError, match="NaN"):
        deconvolve(clean * float("nan"), operator, 2)
    with pytest.raises(ValueError, match="zero everywhere"):
        deconvolve(torch.zeros_like(clean), operator, 2)


def test_poisson_cost_formula():
    image = torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64)
    prediction = torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)
    assert poisson_cost(image, prediction) == pytest.approx(3.5 - (np.log(2.0) + 2 * np.log(1.0)))


def test_poisson_cost_with_weights():
    image = torch.tensor([1.0, 2.0, 5.0], dtype=torch.float64)
    prediction = torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)
    weights = torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64)
    expected = (2.0 - np.log(2.0)) + 0.5 * (1.0 - 2 * np.log(1.0))
    assert poisson_cost(image, prediction, weights) == pytest.approx(expected)


def dense_weighted_rl(matrix, image, weights, iterations, shb):
    """Float64 reference on a dense matrix ``A`` (pixels x voxels): the normalised weighted RL/SHB
    ``p * A^T(w I / max(A p, 1e-10)) / max(A^T w, 1e-6)`` with ``A`` divided by ``max(A^T w)``
    and ``w I`` by its maximum, back in measurement units; also each step's weighted cost."""
    image = np.where(weights > 0, image, 0.0)
    image_scale = image.max()
    image = image / image_scale
    sensitivity = matrix.T @ weights
    scale = sensitivity.max()
    matrix, sensitivity = matrix / scale, np.maximum(sensitivity / scale, 1e-6)
    estimate = np.ones(matrix.shape[1])
    previous = estimate.copy()
    epsilon = max(image.mean() * 1e-6, 1e-8)
    costs = []
    for k in range(iterations):
        beta = max(0.0, (k - 1) / (k + 2)) if shb else 0.0
        point = np.maximum(estimate + beta * (estimate - previous), epsilon)
        prediction = matrix @ point
        floored = np.maximum(prediction, 1e-10)
        costs.append(float((weights * (prediction - image * np.log(floored))).sum()))
        update = point * (matrix.T @ (weights * image / floored)) / sensitivity
        previous, estimate = estimate, np.maximum(update, 0)
    return estimate * image_scale / scale, costs


@pytest.mark.parametrize("method", ["rl", "shb"])
def test_weighted_rl_with_guard_and_gains_equals_a_dense_matrix_reference(method):
    rng = np.random.default_rng(7)
    psf = torch.from_numpy(rng.random((3, 2, 5, 5)))
    operator = MeasuredOperator(psf, (6, 7), 2, torch.tensor([0.7, 1.0, 0.85]))
    n_voxels = int(np.prod(operator.volume_shape))
    units = torch.eye(n_voxels, dtype=torch.float64).reshape(n_voxels, *operator.volume_shape)
    matrix = operator.forward(units).reshape(n_voxels, -1).T.numpy()  # (pixels, voxels)
    image = rng.random((3, 6, 7)) + 0.05
    weights = (rng.random((3, 6, 7)) > 0.25).astype(np.float64)
    image[weights == 0] *= 1e4  # junk under the mask
    steps = list(
        iterate_deconvolution(
            torch.from_numpy(image),
            operator,
            6,
            method=method,
            weights=torch.from_numpy(weights),
        )
    )
    expected, costs = dense_weighted_rl(matrix, image.ravel(), weights.ravel(), 6, method == "shb")
    np.testing.assert_allclose(
        steps[-1].estimate.numpy().ravel(), expected, rtol=1e-9, atol=1e-12 * expected.max()
    )
    np.testing.assert_allclose([s.cost for s in steps], costs, rtol=1e-9)


def test_guard_band_alone_switches_to_the_voxelwise_sensitivity():
    rng = np.random.default_rng(8)
    psf = torch.from_numpy(rng.random((2, 3, 5, 5)))
    image = torch.from_numpy(rng.random((2, 16, 18)) + 0.1)
    guarded = MeasuredOperator(psf, (16, 18), 3)
    torch.testing.assert_close(
        deconvolve(image, guarded, 5),
        deconvolve(image, guarded, 5, weights=torch.ones_like(image)),
        rtol=1e-12,
        atol=0,
    )
    plain = FLFMOperator(psf, (3, 16, 18))  # no guard, no weights: Algorithm S1, bit for bit
    assert torch.equal(
        deconvolve(image, MeasuredOperator(psf, (16, 18)), 5), deconvolve(image, plain, 5)
    )
    with pytest.raises(ValueError, match="do not broadcast"):
        deconvolve(image, plain, 2, weights=torch.ones(3, 16, 18))
    with pytest.raises(ValueError, match="non-negative and not all zero"):
        deconvolve(image, plain, 2, weights=torch.zeros_like(image))


def test_a_masked_hot_pixel_changes_nothing(flfm_case):
    """A pixel 1000x brighter than the brightest view pixel: masked, SHB gives the uncorrupted
    result (0.5% from the unmasked clean run; identical to the masked clean run); unmasked, it
    wrecks the reconstruction (measured: 36x the volume's norm)."""
    operator, _, clean, _ = flfm_case
    corrupt = clean.clone()
    corrupt[3, 20, 20] = 1e3 * clean.max()
    mask = torch.ones_like(clean)
    mask[3, 20, 20] = 0
    reference = deconvolve(clean, operator, 20)

    def distance(volume):
        return float((volume - reference).norm() / reference.norm())

    masked = deconvolve(corrupt, operator, 20, weights=mask)
    torch.testing.assert_close(masked, deconvolve(clean, operator, 20, weights=mask))
    assert distance(masked) < 0.02
    assert distance(deconvolve(corrupt, operator, 20)) > 1.0
