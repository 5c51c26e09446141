"""The Triton deformation (anchoring and Eq. S22) against a float64 reference and the PyTorch
path.

Without a GPU the kernel runs in Triton's interpreter (``TRITON_INTERPRET=1``, set before Triton
is imported, hence a fresh process); with one it is compiled and compared on the GPU as well.
"""

import pytest
import torch

from fgat.dynamics import DeformationField, HexPlane, apply_deformation
from fgat.dynamics.deformation import anchored_increments
from tests.conftest import on_each_path, run_interpreted

pytest.importorskip("triton")

MIN_SCALE = 0.05


def heads_and_gaussians(seed: int) -> list[torch.Tensor]:
    """Head outputs at ``t`` and ``t_ref`` ``(N, 11)`` and canonical Gaussians (float64) with
    scales and intensities that the increments push below their floors, and one rotation
    increment of zero norm (its normalisation floored)."""
    g = torch.Generator().manual_seed(seed)
    n = 64
    now = torch.randn(n, 11, generator=g, dtype=torch.float64) * 0.5
    reference = torch.randn(n, 11, generator=g, dtype=torch.float64) * 0.5
    now[0, 6:10] = torch.tensor([0.25, 0.5, -0.75, 0.125], dtype=torch.float64)
    reference[0, 6:10] = now[0, 6:10] + torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 10
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2
    quats = torch.nn.functional.normalize(
        torch.randn(n, 4, generator=g, dtype=torch.float64), dim=1
    )
    intensities = torch.rand(n, generator=g, dtype=torch.float64) + 0.5
    now[1:5, 10] = -3.0  # intensities clamped at zero
    return [now, reference, means, scales, quats, intensities]


def deformed(inputs, dtype, kernel: bool):
    """``G_t`` and the gradients of a random weighting of it with respect to both head
    outputs, by the kernel or by :func:`anchored_increments` and :func:`apply_deformation`."""
    from fgat.dynamics.deformation_triton import deformed_gaussians

    now, reference, *gaussians = [t.to(dtype) for t in inputs]
    now.requires_grad_(True)
    reference.requires_grad_(True)
    if kernel:
        outputs = deformed_gaussians(now, reference, *gaussians, MIN_SCALE)
    else:
        increments = anchored_increments(now, reference)
        outputs = apply_deformation(*gaussians, increments, min_scale=MIN_SCALE)
    g = torch.Generator().manual_seed(7)
    loss = sum(
        (o * torch.randn(o.shape, generator=g, dtype=torch.float64).to(dtype)).sum()
        for o in outputs
    )
    grads = torch.autograd.grad(loss, (now, reference))
    return [t.detach().double().reshape(len(t), -1) for t in (*outputs, *grads)]


def kernel_errors(seed: int) -> dict[str, float]:
    """Largest per-Gaussian error of the kernel (float32) against the PyTorch composition in
    float64, relative to the larger of the row's norm and one (the values are of order one:
    a small intensity left by cancelling terms keeps their rounding): the deformed Gaussians
    and both head outputs' gradients."""
    inputs = heads_and_gaussians(seed)
    names = ("means", "scales", "quats", "intensities", "grad_now", "grad_reference")
    return {
        name: float(((a - b).norm(dim=1) / b.norm(dim=1).clamp(min=1.0)).max())
        for name, a, b in zip(
            names, deformed(inputs, torch.float32, True), deformed(inputs, torch.float64, False)
        )
    }


def field_errors(seed: int) -> dict[str, float]:
    """Relative L2 errors of ``DeformationField.deform`` on the Triton path (float32) against
    the PyTorch path in float64: the deformed Gaussians and every parameter's gradient."""
    torch.manual_seed(seed)
    field = DeformationField(HexPlane(4, (5, 6, 7), 3, levels=2, seed=seed), width=16)
    field.reference_time = -0.4
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.add_(0.3 * torch.randn_like(parameter))
    _, _, means, scales, quats, intensities = heads_and_gaussians(seed)
    positions = torch.rand(64, 3, dtype=torch.float64) * 2 - 1
    weights = [
        torch.randn(t.shape, dtype=torch.float64) for t in (means, scales, quats, intensities)
    ]

    def run(dtype, backend):
        model = DeformationField(HexPlane(4, (5, 6, 7), 3, levels=2), width=16).to(dtype)
        model.load_state_dict(field.state_dict())
        model.reference_time = field.reference_time
        gaussians = [t.to(dtype) for t in (means, scales, quats, intensities)]
        outputs = model.deform(
            positions.to(dtype),
            torch.tensor(0.3, dtype=dtype),
            gaussians,
            min_scale=MIN_SCALE,
            backend=backend,
        )
        loss = sum((o * w.to(dtype)).sum() for o, w in zip(outputs, weights))
        grads = torch.autograd.grad(loss, list(model.parameters()))
        return [t.detach().double() for t in (*outputs, *grads)]

    runs = on_each_path(run)

    def largest(a, b, parts):
        return max(float((x - y).norm() / y.norm()) for x, y in zip(runs[a][parts], runs[b][parts]))

    return {
        part: {
            "triton": largest("triton", "reference", parts),
            "torch": largest("torch", "reference", parts),
            "triton_vs_torch": largest("triton", "torch", parts),
        }
        for part, parts in (("gaussians", slice(0, 4)), ("parameters", slice(4, None)))
    }


def check_field(results: dict) -> None:
    """As close to float64 as the PyTorch path (within a factor of two, or of eight float32
    epsilons), and within float32 rounding of it."""
    for errors in results.values():
        assert errors["triton"] <= 2 * errors["torch"] + 1e-6, results
        assert errors["triton_vs_torch"] < 1e-4, results


@pytest.mark.slow
def test_interpreted_kernel_matches_float64_per_gaussian():
    errors = run_interpreted(__name__, "t.kernel_errors(0)")
    for name, error in errors.items():
        assert error < 1e-5, (name, errors)


@pytest.mark.slow
def test_interpreted_field_deforms_as_the_pytorch_path():
    check_field(run_interpreted(__name__, "t.field_errors(1)"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_compiled_kernel_matches_float64_on_a_gpu():
    torch.set_default_device("cuda")
    try:
        errors, field = kernel_errors(1), field_errors(2)
    finally:
        torch.set_default_device("cpu")
    for name, error in errors.items():
        assert error < 1e-5, (name, errors)
    check_field(field)


@pytest.mark.slow
def test_triton_refuses_canonical_gaussians_that_need_a_gradient():
    message = run_interpreted(__name__, "t.refusal()")
    assert "Gaussians that need no gradient" in message


def refusal() -> str:
    field = DeformationField(HexPlane(4, (5, 6, 7), 3, levels=2), width=16)
    gaussians = [t.float() for t in heads_and_gaussians(0)[2:]]
    gaussians[0].requires_grad_(True)
    with pytest.raises(ValueError) as error:
        field.deform(torch.zeros(64, 3), 0.0, gaussians, backend="triton")
    return str(error.value)
