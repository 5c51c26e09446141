"""The anchored deformation applied to the canonical Gaussians (Eqs. S21-S22) as a Triton
kernel: the GPU path of :meth:`fgat.dynamics.DeformationField.deform`.

From the MLP's head outputs at ``t`` and at ``t_ref`` (``(N, 11)`` each: ``dmu``, ``ds``,
``dr``, ``di`` in :data:`~fgat.dynamics.deformation.HEADS` order) one program per block of
Gaussians forms the anchored increments (the difference of the two), normalises the rotation
increment ``(1, 0, 0, 0) + dr`` and writes ``mu + dmu``, ``max(s + ds, s_min)``,
``dr (x) r`` and ``max(i + di, 0)``; the backward recomputes them and writes the gradients of
both head outputs. The same arithmetic as :func:`~fgat.dynamics.apply_deformation` after
:meth:`~fgat.dynamics.DeformationField.forward`, which as PyTorch operations are about fifty
launches forward and eighty backward. The canonical Gaussians are constant (no gradient flows to
them). Float32 only. Triton's interpreter (``TRITON_INTERPRET=1``) runs the same kernel on CPU
tensors, which is how the tests compare it with the PyTorch path on a machine without a GPU.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from fgat.gaussians.rotation import QUATERNION_EPS

BLOCK = 128
"""Gaussians per program."""


@triton.jit
def _increment(now, reference, n, inside, k):
    """Anchored increment ``k``: head output ``k`` at ``t`` less the same at ``t_ref``."""
    return tl.load(now + 11 * n + k, mask=inside, other=0.0) - tl.load(
        reference + 11 * n + k, mask=inside, other=0.0
    )


@triton.jit
def _store_pair(grad_now, grad_reference, n, inside, k, grad):
    """``dL/d`` head output ``k``: ``grad`` at ``t``, ``-grad`` at ``t_ref``."""
    tl.store(grad_now + 11 * n + k, grad, mask=inside)
    tl.store(grad_reference + 11 * n + k, -grad, mask=inside)


@triton.jit
def _deform_kernel(
    out_means,
    out_scales,
    out_quats,
    out_intensities,
    grad_now,
    grad_reference,
    now,
    reference,
    means,
    scales,
    quats,
    intensities,
    count,
    min_scale,
    BACKWARD: tl.constexpr,
    EPS: tl.constexpr,
    BLOCK: tl.constexpr,
):
    """Forward: ``G_t`` into the four outputs. Backward: the four hold ``dL/dG_t``, reduced
    into the head outputs' gradients ``grad_now`` and ``grad_reference`` (its negative)."""
    n = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    inside = n < count
    rw = 1.0 + _increment(now, reference, n, inside, 6)  # the rotation increment, unnormalised
    rx = _increment(now, reference, n, inside, 7)
    ry = _increment(now, reference, n, inside, 8)
    rz = _increment(now, reference, n, inside, 9)
    norm = tl.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    floored = tl.maximum(norm, EPS)
    pw, px, py, pz = rw / floored, rx / floored, ry / floored, rz / floored
    qw = tl.load(quats + 4 * n, mask=inside, other=0.0)
    qx = tl.load(quats + 4 * n + 1, mask=inside, other=0.0)
    qy = tl.load(quats + 4 * n + 2, mask=inside, other=0.0)
    qz = tl.load(quats + 4 * n + 3, mask=inside, other=0.0)
    intensity = tl.load(intensities + n, mask=inside, other=0.0)
    intensity = intensity + _increment(now, reference, n, inside, 10)
    if not BACKWARD:
        for k in tl.static_range(3):
            mean = tl.load(means + 3 * n + k, mask=inside, other=0.0)
            mean = mean + _increment(now, reference, n, inside, k)
            tl.store(out_means + 3 * n + k, mean, mask=inside)
            scale = tl.load(scales + 3 * n + k, mask=inside, other=0.0)
            scale = scale + _increment(now, reference, n, inside, 3 + k)
            tl.store(out_scales + 3 * n + k, tl.maximum(scale, min_scale), mask=inside)
        tl.store(out_quats + 4 * n, pw * qw - px * qx - py * qy - pz * qz, mask=inside)
        tl.store(out_quats + 4 * n + 1, pw * qx + px * qw + py * qz - pz * qy, mask=inside)
        tl.store(out_quats + 4 * n + 2, pw * qy - px * qz + py * qw + pz * qx, mask=inside)
        tl.store(out_quats + 4 * n + 3, pw * qz + px * qy - py * qx + pz * qw, mask=inside)
        tl.store(out_intensities + n, tl.maximum(intensity, 0.0), mask=inside)
    else:
        for k in tl.static_range(3):
            grad = tl.load(out_means + 3 * n + k, mask=inside, other=0.0)
            _store_pair(grad_now, grad_reference, n, inside, k, grad)
            scale = tl.load(scales + 3 * n + k, mask=inside, other=0.0)
            scale = scale + _increment(now, reference, n, inside, 3 + k)
            grad = tl.load(out_scales + 3 * n + k, mask=inside, other=0.0)
            _store_pair(
                grad_now, grad_reference, n, inside, 3 + k, tl.where(scale >= min_scale, grad, 0.0)
            )
        gw = tl.load(out_quats + 4 * n, mask=inside, other=0.0)
        gx = tl.load(out_quats + 4 * n + 1, mask=inside, other=0.0)
        gy = tl.load(out_quats + 4 * n + 2, mask=inside, other=0.0)
        gz = tl.load(out_quats + 4 * n + 3, mask=inside, other=0.0)
        # dL/d(unit increment) through dr (x) r, then through r / max(|r|, EPS).
        dw = gw * qw + gx * qx + gy * qy + gz * qz
        dx = gx * qw - gw * qx - gy * qz + gz * qy
        dy = gx * qz - gw * qy + gy * qw - gz * qx
        dz = gy * qx - gw * qz - gx * qy + gz * qw
        radial = tl.where(norm > EPS, pw * dw + px * dx + py * dy + pz * dz, 0.0)
        _store_pair(grad_now, grad_reference, n, inside, 6, (dw - pw * radial) / floored)
        _store_pair(grad_now, grad_reference, n, inside, 7, (dx - px * radial) / floored)
        _store_pair(grad_now, grad_reference, n, inside, 8, (dy - py * radial) / floored)
        _store_pair(grad_now, grad_reference, n, inside, 9, (dz - pz * radial) / floored)
        grad = tl.load(out_intensities + n, mask=inside, other=0.0)
        _store_pair(grad_now, grad_reference, n, inside, 10, tl.where(intensity >= 0, grad, 0.0))


class _Deform(torch.autograd.Function):
    """``G_t`` from the head outputs at ``t`` and ``t_ref`` ``(N, 11)`` and the canonical
    Gaussians (constant), differentiable in the head outputs; one kernel each way."""

    @staticmethod
    def forward(ctx, now, reference, means, scales, quats, intensities, min_scale):
        inputs = [t.contiguous() for t in (now, reference, means, scales, quats, intensities)]
        outputs = [torch.empty_like(t) for t in inputs[2:]]
        _launch(outputs, (inputs[0],) * 2, inputs, min_scale, False)
        ctx.save_for_backward(*inputs)
        ctx.min_scale = min_scale
        return tuple(outputs)

    @staticmethod
    def backward(ctx, *grads):
        inputs = ctx.saved_tensors
        grads = [g.contiguous() for g in grads]
        head_grads = torch.empty_like(inputs[0]), torch.empty_like(inputs[1])
        _launch(grads, head_grads, inputs, ctx.min_scale, True)
        return *head_grads, None, None, None, None, None


def _launch(outputs, head_grads, inputs, min_scale: float, backward: bool) -> None:
    """Run :func:`_deform_kernel` over every Gaussian."""
    count = len(inputs[0])
    if count:
        _deform_kernel[(triton.cdiv(count, BLOCK),)](
            *outputs,
            *head_grads,
            *inputs,
            count,
            float(min_scale),
            BACKWARD=backward,
            EPS=QUATERNION_EPS,
            BLOCK=BLOCK,
        )


def deformed_gaussians(
    now: Tensor,
    reference: Tensor,
    means: Tensor,
    scales: Tensor,
    quats: Tensor,
    intensities: Tensor,
    min_scale: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``G_t`` (Eq. S22) with the anchored increments of Eq. S21, in float32.

    Parameters
    ----------
    now, reference : Tensor
        ``(N, 11)`` head outputs at ``t`` and at ``t_ref`` (``dmu``, ``ds``, ``dr``, ``di``).
    means, scales, quats, intensities : Tensor
        The canonical Gaussians ``(N, 3)``, ``(N, 3)``, ``(N, 4)``, ``(N,)`` (constant).
    min_scale : float
        Floor of the deformed scales, world units.

    Returns
    -------
    tuple of Tensor
        Deformed means, scales, quaternions and intensities, shaped as the inputs.
    """
    return _Deform.apply(now, reference, means, scales, quats, intensities, min_scale)
