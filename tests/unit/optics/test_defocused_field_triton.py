"""The JPGM's lenslet fields as Triton kernels against the PyTorch path and a float64 reference.

:class:`fgat.optics.psf._DefocusedField` takes the kernels of
:mod:`fgat.optics.defocused_field_triton` for float32 on a GPU. Without a GPU they run in
Triton's interpreter (``TRITON_INTERPRET=1``, set before Triton is imported, hence one fresh
process for the whole file); with one they are compiled and compared on the GPU as well. The
inputs are the maps that the small system's aberrated JPGM hands to the function, cut to boxes
that are no multiple of the kernels' block, at depths where the phase reaches 240 to 300 rad.

Tolerances are first-order worst-case bounds on float32 rounding, elementwise (unit roundoff
``eps = 2^-24``), computed in float64 from the float32 inputs (:func:`rounding_bounds`), for the
phase's multiply-adds fused or not (Triton's interpreter before 3.7 and PyTorch's CPU kernels
may round the product too): ``f = a0 + z (a1 + z a2)`` is within ``4 eps F`` of exact, ``F =
|a0| + |z a1| + |z^2 a2|``, and the phase within ``eps (2 |Phi| + 3 |z D| + 3 q f^2 + 8 q |f|
F)``. A field's error is its amplitude times that plus ``3 eps`` (sine and cosine within CUDA's
2 ulp of ``sinf``/``cosf``, the product with ``A`` half an ulp). ``dL/dphase = Im(g) Re(u) -
Re(g) Im(u)`` adds ``3 eps |g| A`` to ``|g|`` times the field's error, ``f`` in ``-2 q z^k f
dL/dphase`` its ``4 eps F``, and the weighted sum over ``Z`` depths ``(Z + 3) eps`` times the sum
of magnitudes. Both float32 paths must stay within the bound of float64 and within twice it of
each other.
"""

import contextlib
import functools
import os
from unittest import mock

import pytest
import torch

import fgat.optics.psf as psf
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system
from tests.conftest import run_interpreted

pytest.importorskip("triton")

EPS = 2.0**-24
"""float32 unit roundoff."""
ABERRATION = {5: 0.1, 7: -0.08, 11: 0.05}
"""Zernike coefficients (Noll index: waves) of the JPGM the maps come from."""
CASES = {
    "7 views, 5 depths, 37 x 29 px": (
        slice(None), slice(20, 57), slice(26, 55), (-350.0, -61.5, 0.0, 75.0, 380.0)
    ),
    "1 view, 1 depth, aperture edge": (slice(4, 5), slice(58, 81), slice(0, 31), (250.0,)),
    "2 views, 3 depths, 20 x 20 px": (
        slice(5, 7), slice(61, 81), slice(30, 50), (-120.0, 10.25, 250.0)
    ),
}  # fmt: skip
"""Views, rows and columns of the maps' box and the depths (um) of each case."""
NAMES = ("field", "zernike", "defocus", "a0", "a1", "a2")


@functools.cache
def jpgm_maps() -> tuple[tuple[torch.Tensor, ...], float]:
    """The maps ``A, Phi, D, a0, a1, a2`` ``(7, 1, 81, 81)`` (float64) and the quartic
    coefficient that the small system's aberrated JPGM passes to ``_DefocusedField``."""
    recorded = []
    apply = psf._DefocusedField.apply

    def record(*arguments):
        recorded.append(arguments)
        return apply(*arguments)

    model = OpticsSpec(load_system("small"), (0.0,), zernike=ABERRATION).jpgm(
        method="mft", dtype=torch.float64
    )
    with mock.patch.object(psf._DefocusedField, "apply", record), torch.no_grad():
        model()
    *maps, _, quartic = recorded[0]
    return tuple(m.contiguous() for m in maps), quartic


def case_inputs(name: str, device: str):
    """float32 maps, depths and incoming gradient ``(V, Z, H, W)`` of case ``name``."""
    views, rows, cols, depths = CASES[name]
    maps, quartic = jpgm_maps()
    maps = tuple(m[views, :, rows, cols].float().contiguous().to(device) for m in maps)
    depths = torch.tensor(depths, device=device)
    shape = (maps[0].shape[0], len(depths), *maps[0].shape[2:])
    generator = torch.Generator().manual_seed(len(name))
    grad = torch.randn(shape, generator=generator, dtype=torch.complex64).to(device)
    return maps, depths, quartic, grad


def lenslet_fields(maps, depths, quartic, grad, fused: bool = True):
    """The field of ``_DefocusedField`` and the gradients of its maps but the aperture under
    the incoming gradient ``grad``; ``fused=False`` keeps it on the PyTorch path."""
    maps = [m.clone().requires_grad_(k > 0) for k, m in enumerate(maps)]
    unfused = mock.patch.object(psf, "_fused_field", lambda *tensors: False)
    with contextlib.nullcontext() if fused else unfused:
        field = psf._DefocusedField.apply(*maps, depths, quartic)
        grads = torch.autograd.grad(field, maps[1:], grad)
    return (field.detach(), *grads)


def rounding_bounds(maps, depths, quartic, grad, reference) -> list[torch.Tensor]:
    """Elementwise float32 rounding bounds (see the module's docstring) of the field and of the
    five gradients, from the float32 inputs and the float64 ``reference`` field."""
    amplitude, zernike, defocus, a0, a1, a2 = (m.double() for m in maps)
    z = depths.double()[:, None, None]
    frequency = a0 + z * (a1 + z * a2)
    terms = a0.abs() + (z * a1).abs() + (z * z * a2).abs()
    phase = (
        2 * zernike.abs()
        + 3 * (z * defocus).abs()
        + 3 * quartic * frequency**2
        + 8 * quartic * frequency.abs() * terms
    )
    field = EPS * amplitude * (phase + 3)
    grad = grad.cdouble()
    d_phase = (grad.imag * reference.real - grad.real * reference.imag).abs()
    d_phase_error = grad.abs() * (field + 3 * EPS * amplitude)
    bounds = [field]
    for k, weight in enumerate((1.0, z, frequency, z * frequency, z * z * frequency)):
        scale = 1.0 if k < 2 else 2 * quartic
        weight = scale * torch.as_tensor(weight, dtype=torch.float64).abs()
        error = weight * (d_phase_error + (len(depths) + 3) * EPS * d_phase)
        if k >= 2:  # the error of f in -2 q z^j f dL/dphase
            error = error + scale * z.abs() ** (k - 2) * 4 * EPS * terms * d_phase
        bounds.append(error.sum(dim=1, keepdim=True))
    return bounds


def worst(ours, theirs, bounds, factor: float = 1.0) -> dict[str, float]:
    """Largest ``|ours - theirs| / (factor bound)`` of the field and each gradient."""
    return {
        name: float(((a.cdouble() - b.cdouble()).abs() / (factor * bound)).nan_to_num(0.0).max())
        for name, a, b, bound in zip(NAMES, ours, theirs, bounds)
    }


def relative(ours, theirs) -> dict[str, float]:
    """Relative L2 errors of the field and each gradient (reported, not tested)."""
    return {
        name: float((a.cdouble() - b.cdouble()).norm() / b.cdouble().norm())
        for name, a, b in zip(NAMES, ours, theirs)
    }


def case_errors(name: str, device: str) -> dict:
    """Whether the Triton path applies, and the errors of case ``name`` on ``device``:
    bound-relative (:func:`worst`) of the Triton and the PyTorch paths against float64 and of the
    one against the other (against twice the bound), and relative L2 errors."""
    maps, depths, quartic, grad = case_inputs(name, device)
    ours = lenslet_fields(maps, depths, quartic, grad)
    torch_path = lenslet_fields(maps, depths, quartic, grad, fused=False)
    double = [m.double() for m in maps]
    reference = lenslet_fields(double, depths.double(), quartic, grad.cdouble())
    bounds = rounding_bounds(maps, depths, quartic, grad, reference[0])
    return {
        "fused": psf._fused_field(*maps, depths),
        "triton": worst(ours, reference, bounds),
        "torch": worst(torch_path, reference, bounds),
        "triton_vs_torch": worst(ours, torch_path, bounds, factor=2.0),
        "relative_l2": {
            "triton": relative(ours, reference),
            "torch": relative(torch_path, reference),
            "triton_vs_torch": relative(ours, torch_path),
        },
    }


def jpgm_stack_and_gradient(dtype: torch.dtype, device: str, fused: bool = True):
    """The aberrated small-system JPGM's PSF stack (matrix Fourier transform path) and the
    gradient of a weighted sum of it w.r.t. the Zernike coefficients."""
    model = OpticsSpec(load_system("small"), (-20.0, 0.0, 15.0), zernike=ABERRATION).jpgm(
        method="mft", dtype=dtype, device=device
    )
    unfused = mock.patch.object(psf, "_fused_field", lambda *tensors: False)
    with contextlib.nullcontext() if fused else unfused:
        stack = model()
        generator = torch.Generator().manual_seed(0)
        weights = torch.rand(stack.shape, generator=generator, dtype=torch.float64)
        loss = (stack * weights.to(device, dtype)).sum()
        (grad,) = torch.autograd.grad(loss, model.zernike_coefficients)
    return stack.detach().double(), grad.double()


def jpgm_errors(device: str) -> dict[str, dict[str, float]]:
    """Relative L2 errors of the float32 stack and gradient (Triton and PyTorch paths) against
    float64, and of the one against the other."""

    def relative_pair(a, b):
        return [float((x - y).norm() / y.norm()) for x, y in zip(a, b)]

    ours = jpgm_stack_and_gradient(torch.float32, device)
    torch_path = jpgm_stack_and_gradient(torch.float32, device, fused=False)
    reference = jpgm_stack_and_gradient(torch.float64, device)
    return {
        "triton": relative_pair(ours, reference),
        "torch": relative_pair(torch_path, reference),
        "triton_vs_torch": relative_pair(ours, torch_path),
    }


def transform_errors(device: str) -> dict[str, float]:
    """Relative L2 differences between the Triton and the PyTorch paths of the field and of what
    else the JPGM's users differentiate: forward-mode directional derivatives under ``vmap``
    (the cross-information's Jacobians), ``torch.func.grad`` and a double backward. Each takes
    PyTorch operations on either path (from the forward's field, or the fields recomputed), so
    they differ by the fields' float32 rounding alone."""
    maps, depths, quartic, grad = case_inputs("2 views, 3 depths, 20 x 20 px", device)
    generator = torch.Generator().manual_seed(1)
    tangents = [torch.randn(3, *m.shape, generator=generator).to(device) for m in maps[1:]]

    def field(*phase_maps):
        return psf._DefocusedField.apply(maps[0], *phase_maps, depths, quartic)

    def loss(*phase_maps):
        return (field(*phase_maps) * grad).real.sum()

    def directional():
        return [
            torch.func.vmap(lambda *t: torch.func.jvp(field, maps[1:], t)[1])(*tangents),
        ]

    def gradient():
        return list(torch.func.grad(loss, argnums=(0, 1, 2, 3, 4))(*maps[1:]))

    def second():
        leaves = [m.clone().requires_grad_(True) for m in maps[1:]]
        first = torch.autograd.grad(loss(*leaves), leaves, create_graph=True)
        return list(torch.autograd.grad(sum(g.square().sum() for g in first), leaves))

    results = {}
    for name, derivative in (
        ("field", lambda: [field(*maps[1:])]),
        ("jvp", directional),
        ("grad", gradient),
        ("second", second),
    ):
        ours = derivative()
        with mock.patch.object(psf, "_fused_field", lambda *tensors: False):
            theirs = derivative()
        results[name] = max(
            float((a - b).norm() / b.norm()) for a, b in zip(ours, theirs, strict=True)
        )
    return results


def interpreted_results() -> dict:
    """Every case's errors, the JPGM's and the transforms' on the CPU (in Triton's
    interpreter)."""
    return {
        "cases": {name: case_errors(name, "cpu") for name in CASES},
        "jpgm": jpgm_errors("cpu"),
        "transforms": transform_errors("cpu"),
    }


def check_case(errors: dict) -> None:
    assert errors["fused"], "the Triton path did not apply"
    for name in NAMES:
        assert errors["triton"][name] <= 1.0, (name, errors)
        assert errors["torch"][name] <= 1.0, (name, errors)
        assert errors["triton_vs_torch"][name] <= 1.0, (name, errors)


def check_jpgm(errors: dict) -> None:
    """The Triton path's stack and gradient differ from the PyTorch path's by no more than twice
    that path's own float32 error, and are no further from float64."""
    for k in range(2):
        bound = 2 * errors["torch"][k]
        assert errors["triton_vs_torch"][k] <= bound, (k, errors)
        assert errors["triton"][k] <= bound, (k, errors)


def check_transforms(errors: dict[str, float]) -> None:
    """Within four times the fields' own difference between the paths (2.5e-8 relative with the
    same fused multiply-adds, 1.5e-6 where Triton's interpreter rounds their products), plus
    1e-7 for the sums' order."""
    for name in ("jvp", "grad", "second"):
        assert errors[name] <= 4 * errors["field"] + 1e-7, (name, errors)


@pytest.fixture(scope="module")
def interpreted():
    return run_interpreted(__name__, "t.interpreted_results()")


@pytest.mark.parametrize("name", CASES)
@pytest.mark.slow
def test_interpreted_kernels_match_the_pytorch_path_and_float64(interpreted, name):
    check_case(interpreted["cases"][name])


@pytest.mark.slow
def test_interpreted_kernels_leave_the_jpgm_stack_and_its_gradient_unchanged(interpreted):
    check_jpgm(interpreted["jpgm"])


@pytest.mark.slow
def test_interpreted_kernels_leave_jvp_functorch_grad_and_double_backward_unchanged(interpreted):
    check_transforms(interpreted["transforms"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
@pytest.mark.parametrize("name", CASES)
def test_compiled_kernels_match_the_pytorch_path_and_float64_on_a_gpu(name):
    check_case(case_errors(name, "cuda"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_compiled_kernels_leave_the_jpgm_stack_and_its_gradient_unchanged_on_a_gpu():
    check_jpgm(jpgm_errors("cuda"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_compiled_kernels_leave_jvp_functorch_grad_and_double_backward_unchanged_on_a_gpu():
    check_transforms(transform_errors("cuda"))


def test_other_types_and_devices_take_the_pytorch_path():
    maps, depths, _, _ = case_inputs("2 views, 3 depths, 20 x 20 px", "cpu")
    assert not psf._fused_field(*(m.double() for m in maps), depths.double())
    if os.environ.get("TRITON_INTERPRET") != "1":
        assert not psf._fused_field(*maps, depths)
