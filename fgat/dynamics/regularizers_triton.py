"""The HexPlane regularisers (Eqs. S30-S32) as a Triton kernel: the GPU path of
:func:`fgat.dynamics.plane_regularisers`.

One launch per plane each way, whatever terms it enters: forward, a program sums a block of the
plane's terms (squared first differences along both plane axes for Eq. S30, squared second
differences along time for Eq. S31, ``|1 - P|`` for Eq. S32), each divided by the plane's size,
and adds them into the three totals with atomic adds; backward, each element's gradient is the
stencil of the terms it enters, weighted by the totals' incoming gradients. As PyTorch
operations the three terms of a HexPlane are about ninety operations forward and a hundred and
sixty backward, each launched from the host. The totals' last bits depend on the order of the
atomic adds; the gradients do not. Float32 only (the PyTorch path serves other types). Triton's
interpreter (``TRITON_INTERPRET=1``) runs the same kernel on CPU tensors, which is how the tests
compare it with the PyTorch path on a machine without a GPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import triton
import triton.language as tl
from torch import Tensor

BLOCK = 1024
"""Plane elements per program."""


@triton.jit
def _at(plane, e, ok):
    """``plane[e]`` where ``ok``, else zero."""
    return tl.load(plane + e, mask=ok, other=0.0)


@triton.jit
def _second_difference(plane, e, b, ok, cols):
    """``P[b + 1] + P[b - 1] - 2 P[b]`` along the last axis where ``1 <= b <= cols - 2`` (and
    ``ok``), else zero."""
    inner = ok & (b >= 1) & (b <= cols - 2)
    outer = _at(plane, e + 1, inner) + _at(plane, e - 1, inner)
    return tl.where(inner, outer - 2 * _at(plane, e, inner), 0.0)


@triton.jit
def _terms_kernel(
    plane,
    totals,
    grad,
    grad_totals,
    size,
    rows,
    cols,
    scale,
    TV: tl.constexpr,
    SM: tl.constexpr,
    L1: tl.constexpr,
    BACKWARD: tl.constexpr,
    BLOCK: tl.constexpr,
):
    """A block of one ``(..., rows, cols)`` plane of ``size`` elements. Forward: its share of
    each term (times ``scale``) into ``totals`` ``(3,)``. Backward: ``dL/dP`` into ``grad``
    from the totals' gradients ``grad_totals`` ``(3,)``."""
    e = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = e < size
    b = e % cols
    a = (e // cols) % rows
    p = _at(plane, e, ok)
    down = ok & (a + 1 < rows)  # a first difference along rows starts here
    right = ok & (b + 1 < cols)  # and along columns
    d_rows = tl.where(down, _at(plane, e + cols, down) - p, 0.0)
    d_cols = tl.where(right, _at(plane, e + 1, right) - p, 0.0)
    if not BACKWARD:
        if TV:
            tl.atomic_add(totals, tl.sum(d_rows * d_rows + d_cols * d_cols, 0) * scale)
        if SM:
            s = _second_difference(plane, e, b, ok, cols)
            tl.atomic_add(totals + 1, tl.sum(s * s, 0) * scale)
        if L1:
            tl.atomic_add(totals + 2, tl.sum(tl.where(ok, tl.abs(1 - p), 0.0), 0) * scale)
    else:
        g = tl.zeros([BLOCK], tl.float32)
        if TV:
            up = ok & (a >= 1)
            left = ok & (b >= 1)
            d_up = tl.where(up, p - _at(plane, e - cols, up), 0.0)
            d_left = tl.where(left, p - _at(plane, e - 1, left), 0.0)
            g += tl.load(grad_totals) * 2 * (d_up - d_rows + d_left - d_cols)
        if SM:
            centre = _second_difference(plane, e, b, ok, cols)
            before = _second_difference(plane, e - 1, b - 1, ok, cols)
            after = _second_difference(plane, e + 1, b + 1, ok, cols)
            g += tl.load(grad_totals + 1) * 2 * (before + after - 2 * centre)
        if L1:
            one_minus = 1 - p
            sign = tl.where(one_minus > 0, 1.0, tl.where(one_minus < 0, -1.0, 0.0))
            g -= tl.load(grad_totals + 2) * sign
        tl.store(grad + e, g * scale, mask=ok)


def _launch(plane, totals, grad, grad_totals, terms, backward) -> None:
    """Run :func:`_terms_kernel` over one plane for its ``terms`` (``(tv, sm, l1)`` flags)."""
    if plane.numel() and any(terms):
        _terms_kernel[(triton.cdiv(plane.numel(), BLOCK),)](
            plane,
            totals,
            grad,
            grad_totals,
            plane.numel(),
            plane.shape[-2],
            plane.shape[-1],
            1.0 / plane.numel(),
            TV=terms[0],
            SM=terms[1],
            L1=terms[2],
            BACKWARD=backward,
            BLOCK=BLOCK,
        )


class _PlaneTerms(torch.autograd.Function):
    """The three totals ``(3,)`` (Eq. S30, S31, S32) of planes each entering the terms its flags
    say (``memberships``: one ``(tv, sm, l1)`` per plane)."""

    @staticmethod
    def forward(ctx, memberships, *planes):
        planes = [p.contiguous() for p in planes]
        totals = torch.zeros(3, device=planes[0].device)
        for plane, terms in zip(planes, memberships):
            _launch(plane, totals, plane, totals, terms, False)
        ctx.memberships = memberships
        ctx.save_for_backward(*planes)
        return totals

    @staticmethod
    def backward(ctx, grad_totals):
        grad_totals = grad_totals.contiguous()
        grads = []
        for plane, terms in zip(ctx.saved_tensors, ctx.memberships):
            grad = torch.zeros_like(plane) if not any(terms) else torch.empty_like(plane)
            _launch(plane, grad_totals, grad, grad_totals, terms, True)
            grads.append(grad)
        return None, *grads


def plane_terms(planes: Sequence[Tensor], memberships: Sequence[tuple[bool, bool, bool]]) -> Tensor:
    """Totals ``(3,)`` of Eqs. S30, S31 and S32 over float32 planes ``(..., R_a, R_b)``, each
    plane entering the terms its ``(tv, sm, l1)`` flags in ``memberships`` name, each term
    divided by the plane's number of elements (Eq. S31 only where ``R_b > 2``)."""
    for plane in planes:
        if plane.dtype != torch.float32:
            raise TypeError(f"the Triton plane regularisers take float32, got {plane.dtype}")
    flags = tuple(
        (bool(tv), bool(sm) and plane.shape[-1] > 2, bool(l1))
        for plane, (tv, sm, l1) in zip(planes, memberships)
    )
    return _PlaneTerms.apply(flags, *planes)
