"""The Triton voxelizer against the float64 dense reference and the PyTorch path.

Without a GPU the kernels run in Triton's interpreter (``TRITON_INTERPRET=1``, set before Triton
is imported, hence a fresh process); with one they are compiled and compared with the PyTorch
path on the same GPU as well.
"""

import os

import pytest
import torch

from fgat.gaussians.voxelize import (
    exponent_coefficients,
    precision_and_extent,
    voxelize,
    voxelize_dense,
)
from tests.conftest import run_interpreted

pytest.importorskip("triton")

SHAPE, VOXEL, ORIGIN = (10, 17, 15), (1.5, 0.975, 0.975), (-7.5, -8.2875, -7.3125)


def gaussians(n: int, seed: int, device: str = "cpu") -> list[torch.Tensor]:
    """Anisotropic, rotated Gaussians of a wide range of sizes, some across the grid's faces and
    corners, some entirely outside it, one of zero intensity."""
    g = torch.Generator().manual_seed(seed)
    extent = torch.tensor(SHAPE, dtype=torch.float64) * torch.tensor(VOXEL, dtype=torch.float64)
    means = (
        torch.tensor(ORIGIN)
        + (torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.5 - 0.25) * extent
    )
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) ** 2 * 3.0 + 0.2
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    intensities = torch.rand(n, generator=g, dtype=torch.float64) + 0.1
    means[0] += 1000.0  # outside the grid
    intensities[1] = 0.0
    return [t.to(device) for t in (means, scales, quats, intensities)]


def errors(volume, grads, reference, reference_grads) -> dict[str, float]:
    """Relative L2 errors of a volume and its four gradients against references."""

    def relative(a, b):
        return float((a.double() - b.double()).norm() / b.double().norm().clamp(min=1e-30))

    names = ("volume", "means", "scales", "quats", "intensities")
    values = [relative(volume, reference)] + [
        relative(a, b) for a, b in zip(grads, reference_grads)
    ]
    return dict(zip(names, values))


def rendered(arguments, backend: str, weights: torch.Tensor, **reference):
    """Volume and gradients of ``sum(weights * V)`` from ``voxelize`` (or ``voxelize_dense``
    when ``backend`` is ``dense``)."""
    arguments = [t.detach().clone().requires_grad_(True) for t in arguments]
    if backend == "dense":
        volume = voxelize_dense(*arguments, SHAPE, VOXEL, ORIGIN)
    else:
        volume = voxelize(*arguments, SHAPE, VOXEL, ORIGIN, backend=backend)
    grads = torch.autograd.grad((volume * weights).sum(), arguments)
    return volume.detach(), grads


def triton_errors(seed: int, device: str) -> dict[str, dict[str, float]]:
    """Relative errors of the Triton path (float32) and of the PyTorch path (float32) against
    the dense float64 reference, and of the one against the other, on ``device``."""
    double = gaussians(40, seed, device)
    single = [t.float() for t in double]
    weights = torch.rand(SHAPE, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    weights = weights.to(device)
    ours = rendered(single, "triton", weights.float())
    torch_path = rendered(single, "torch", weights.float())
    reference = rendered(double, "dense", weights)
    return {
        "triton": errors(*ours, *reference),
        "torch": errors(*torch_path, *reference),
        "triton_vs_torch": errors(*ours, *torch_path),
    }


def coefficient_errors(seed: int, device: str) -> dict[str, float]:
    """Largest per-Gaussian relative error of the coefficients kernel (float32) and of its
    gradients against the PyTorch composition in float64 (precision, then coefficients), on
    Gaussians that include scales of 1e-3 and 1e2 and a quaternion below the norm floor."""
    from fgat.gaussians.voxelize_triton import gaussian_coefficients

    g = torch.Generator().manual_seed(seed)
    means, scales, quats, _ = gaussians(64, seed)
    scales[3] = torch.tensor([1e-3, 0.5, 1e2], dtype=torch.float64)
    quats[2] *= 1e-14  # |q| below normalize_quaternion's floor
    offset = torch.rand(64, 3, generator=g, dtype=torch.float64) - 0.5
    weights = torch.randn(64, 10, generator=g, dtype=torch.float64)

    def run(dtype, kernel):
        inputs = [t.to(device, dtype).requires_grad_(True) for t in (means, scales, quats)]
        b = offset.to(device, dtype)
        if kernel:
            coefficients = gaussian_coefficients(*inputs, b)
        else:  # the voxelizer's offset: fixed centre voxel minus the mean
            precision, _ = precision_and_extent(inputs[1], inputs[2])
            coefficients = exponent_coefficients(precision, b + inputs[0].detach() - inputs[0])
        grads = torch.autograd.grad((coefficients * weights.to(device, dtype)).sum(), inputs)
        return [t.detach().double().cpu() for t in (coefficients, *grads)]

    names = ("coefficients", "means", "scales", "quats")
    return {
        name: float(((a - b).norm(dim=1) / b.norm(dim=1).clamp(min=1e-300)).max())
        for name, a, b in zip(names, run(torch.float32, True), run(torch.float64, False))
    }


def nothing_visible(device: str) -> float:
    """Largest value of the volume and of the gradients when every Gaussian lies outside the
    grid (no tile at all): zero expected."""
    arguments = [t.float() for t in gaussians(5, 3, device)]
    arguments[0] = arguments[0] + 1000.0
    volume, grads = rendered(arguments, "triton", torch.ones(SHAPE, device=device))
    return max(float(t.abs().max()) for t in (volume, *grads))


def check(results: dict[str, dict[str, float]]) -> None:
    """As close to float64 as the PyTorch path in float32 (within a factor of two, or of eight
    float32 epsilons: both sit at a few epsilons and round differently), and within float32
    rounding of it."""
    for name, error in results["triton"].items():
        assert error <= 2 * results["torch"][name] + 1e-6, (name, results)
        assert results["triton_vs_torch"][name] < 1e-5, (name, results)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.slow
def test_interpreted_kernels_match_the_reference_and_the_pytorch_path(seed):
    empty, errors = run_interpreted(
        __name__, f"[t.nothing_visible('cpu'), t.triton_errors({seed}, 'cpu')]"
    )
    assert float(empty) == 0.0
    check(errors)


@pytest.mark.slow
def test_interpreted_coefficients_kernel_matches_float64_per_gaussian():
    errors = run_interpreted(__name__, "t.coefficient_errors(0, 'cpu')")
    for name, error in errors.items():
        assert error < 2e-5, (name, errors)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_compiled_coefficients_kernel_matches_float64_per_gaussian_on_a_gpu():
    errors = coefficient_errors(1, "cuda")
    for name, error in errors.items():
        assert error < 2e-5, (name, errors)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_kernels_match_the_reference_and_the_pytorch_path_on_a_gpu(seed):
    assert nothing_visible("cuda") == 0.0
    check(triton_errors(seed, "cuda"))


def test_backend_is_checked():
    arguments = [t.float() for t in gaussians(3, 0)]
    with pytest.raises(ValueError, match="backend must be one of"):
        voxelize(*arguments, SHAPE, VOXEL, ORIGIN, backend="cuda")
    with pytest.raises(ValueError, match="takes float32"):
        voxelize(*gaussians(3, 0), SHAPE, VOXEL, ORIGIN, backend="triton")
    if os.environ.get("TRITON_INTERPRET") != "1":
        with pytest.raises(ValueError, match="runs on a GPU .* on cpu"):
            voxelize(*arguments, SHAPE, VOXEL, ORIGIN, backend="triton")
