import numpy as np
import pytest
import scipy.signal
import torch
from skimage.restoration import richardson_lucy

from fgat.deconvolution import deconvolve, iterate_deconvolution, momentum, poisson_cost
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system
from fgat.phantoms import beads


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
