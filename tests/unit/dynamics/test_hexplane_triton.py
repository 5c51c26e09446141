"""The Triton HexPlane features against a float64 reference and the PyTorch path.

Without a GPU the kernel runs in Triton's interpreter (``TRITON_INTERPRET=1``, set before Triton
is imported, hence a fresh process); with one it is compiled and compared on the GPU as well.
"""

import pytest
import torch

from fgat.dynamics import HexPlane
from tests.conftest import on_each_path, run_interpreted

pytest.importorskip("triton")

CHANNELS, SPATIAL, TEMPORAL, LEVELS = 5, (6, 7, 9), 4, 2


def hexplane(seed: int, dtype: torch.dtype, device: str) -> HexPlane:
    """A HexPlane whose spatio-temporal planes vary too (they start at one), with a channel
    count that is not a power of two and unequal resolutions."""
    field = HexPlane(CHANNELS, SPATIAL, TEMPORAL, levels=LEVELS, seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    for plane in field.planes:
        plane.data += 0.3 * torch.rand(plane.shape, generator=g)
    return field.to(device, dtype)


def features_and_grads(seed, dtype, device, backend, times):
    """Features at ``times`` and the planes' gradients of a random weighting of them."""
    g = torch.Generator().manual_seed(seed)
    positions = torch.rand(60, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2  # some beyond
    positions[0] = torch.tensor([1.0, -1.0, 1.0])  # on the last and first nodes
    field = hexplane(seed, dtype, device)
    stamps = [torch.tensor(t, dtype=dtype, device=device) for t in times]
    features = field.at_times(positions.to(device, dtype), stamps, backend=backend)
    weights = [torch.rand(f.shape, generator=g, dtype=torch.float64) for f in features]
    loss = sum((f * w.to(device, dtype)).sum() for f, w in zip(features, weights))
    grads = torch.autograd.grad(loss, list(field.planes))
    return [t.detach().double().cpu() for t in (*features, *grads)]


def hexplane_errors(seed: int, device: str) -> dict[str, dict[str, float]]:
    """Largest relative L2 error over the features and the plane gradients of the Triton path
    and the PyTorch path (float32) against the PyTorch path in float64, and of the one against
    the other; at two times (one of them the first node) and at one."""
    results = {}
    for times in ((0.3, -1.0), (0.55,)):
        run = on_each_path(
            lambda dtype, backend: features_and_grads(seed, dtype, device, backend, times)
        )

        def largest(a, b):
            return max(float((x - y).norm() / y.norm()) for x, y in zip(run[a], run[b]))

        results[len(times)] = {
            "triton": largest("triton", "reference"),
            "torch": largest("torch", "reference"),
            "triton_vs_torch": largest("triton", "torch"),
        }
    return results


def anchoring(device: str) -> bool:
    """Whether the Triton path's features at ``t`` and at ``t_ref`` are equal bit for bit when
    the two times are: the exact anchoring of :class:`DeformationField` rests on it."""
    positions = torch.rand(40, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    now, reference = hexplane(0, torch.float32, device).at_times(
        positions.to(device), (torch.tensor(0.25, device=device), 0.25), backend="triton"
    )
    return bool(torch.equal(now, reference)) and bool(now.abs().max() > 0)


def check(results: dict) -> None:
    """As close to float64 as the PyTorch path (within a factor of two, or of eight float32
    epsilons), and within float32 rounding of it."""
    for errors in results.values():
        assert errors["triton"] <= 2 * errors["torch"] + 1e-6, results
        assert errors["triton_vs_torch"] < 1e-5, results


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.slow
def test_interpreted_kernel_matches_the_reference_and_the_pytorch_path(seed):
    check(run_interpreted(__name__, f"t.hexplane_errors({seed}, 'cpu')"))


@pytest.mark.slow
def test_interpreted_kernel_keeps_the_anchoring_exact():
    assert run_interpreted(__name__, "t.anchoring('cpu')") is True


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_kernel_matches_the_reference_and_the_pytorch_path_on_a_gpu(seed):
    check(hexplane_errors(seed, "cuda"))
    assert anchoring("cuda")


def test_backend_is_checked():
    field = hexplane(0, torch.float32, "cpu")
    positions = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="backend must be one of"):
        field.at_times(positions, (0.0,), backend="cuda")
    with pytest.raises(ValueError, match="takes float32 positions"):
        field.at_times(positions.double(), (0.0,), backend="triton")
    assert torch.equal(  # auto: the PyTorch path on a CPU
        field.at_times(positions, (0.0,))[0], field.at_times(positions, (0.0,), backend="torch")[0]
    )


@pytest.mark.slow
def test_triton_refuses_what_it_does_not_compute():
    messages = run_interpreted(__name__, "t.refusals()")
    assert "positions that need no gradient" in messages[0]
    assert "one or two times, each one value" in messages[1]
    assert "one or two times, each one value" in messages[2]


def refusals() -> list[str]:
    """The messages of ``backend='triton'`` for points that need a gradient, per-point times and
    three times."""
    field = hexplane(0, torch.float32, "cpu")
    points = torch.zeros(3, 3)
    messages = []
    for positions, times in (
        (points.clone().requires_grad_(), (0.0,)),
        (points, (torch.zeros(3),)),
        (points, (0.0, 0.1, 0.2)),
    ):
        with pytest.raises(ValueError) as error:
            field.at_times(positions, times, backend="triton")
        messages.append(str(error.value))
    return messages
