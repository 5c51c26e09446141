"""The Triton plane regularisers (Eqs. S30-S32) against a float64 reference and the PyTorch
path.

Without a GPU the kernel runs in Triton's interpreter (``TRITON_INTERPRET=1``, set before Triton
is imported, hence a fresh process); with one it is compiled and compared on the GPU as well.
"""

import pytest
import torch

from fgat.dynamics import plane_regularisers
from tests.conftest import on_each_path, run_interpreted

pytest.importorskip("triton")

SHAPES = [(1, 2, 4, 5), (1, 2, 4, 5), (1, 2, 4, 5), (1, 2, 3, 2), (1, 3, 70, 33), (2, 3)]
"""Planes of shared and distinct shapes, one whose time axis has no second difference, one
larger than a program's block, one without leading axes."""

WEIGHTS = {"tv": 0.3, "sm": 0.5, "l1": 0.7}


def terms_and_grads(seed, dtype, device, backend, terms):
    """The regularisers of mixed memberships (Eq. S30 only, Eqs. S31-S32 only, both) and the
    planes' gradients of their weighted sum."""
    g = torch.Generator().manual_seed(seed)
    planes = [
        (torch.rand(s, generator=g, dtype=torch.float64) * 2).to(device, dtype).requires_grad_()
        for s in SHAPES
    ]
    tv, temporal = [planes[0], planes[1], planes[3], planes[5]], planes[1:5]
    values = plane_regularisers(tv, temporal, terms, backend=backend)
    total = sum(WEIGHTS[k] * v for k, v in values.items())
    grads = torch.autograd.grad(total, planes, allow_unused=True, materialize_grads=True)
    return {k: float(v.detach()) for k, v in values.items()}, [t.double().cpu() for t in grads]


def regulariser_errors(seed: int, device: str, terms=("tv", "sm", "l1")) -> dict:
    """Relative errors of the values (largest over the terms) and of the gradients (largest
    over the planes) of the Triton path and the PyTorch path (float32) against the PyTorch
    path in float64."""
    runs = on_each_path(lambda dtype, backend: terms_and_grads(seed, dtype, device, backend, terms))
    reference_values, reference_grads = runs.pop("reference")
    return {
        name: {
            "values": max(abs(values[k] / reference_values[k] - 1) for k in terms),
            "grads": max(
                float((a - b).norm() / b.norm()) if b.norm() > 0 else float(a.abs().max())
                for a, b in zip(grads, reference_grads)
            ),
        }
        for name, (values, grads) in runs.items()
    }


def check(errors: dict) -> None:
    """As close to float64 as the PyTorch path (within a factor of two, or of eight float32
    epsilons)."""
    for part in ("values", "grads"):
        assert errors["triton"][part] <= 2 * errors["torch"][part] + 1e-6, errors


@pytest.mark.parametrize("terms", [("tv", "sm", "l1"), ("sm",)], ids=["all", "sm only"])
@pytest.mark.slow
def test_interpreted_kernel_matches_the_reference_and_the_pytorch_path(terms):
    check(run_interpreted(__name__, f"t.regulariser_errors(0, 'cpu', {terms})"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_kernel_matches_the_reference_and_the_pytorch_path_on_a_gpu(seed):
    check(regulariser_errors(seed, "cuda"))
    check(regulariser_errors(seed, "cuda", ("l1",)))
