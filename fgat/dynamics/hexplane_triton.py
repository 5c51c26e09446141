"""The HexPlane features (Eq. S18) as a Triton kernel: the GPU path of
:meth:`fgat.dynamics.HexPlane.at_times`.

The same bilinear samples (``grid_sample`` with ``align_corners=True`` and border padding) and
the same products in ``PLANES`` order as the PyTorch path, for the same points at ``K`` scalar
times (one or two: the deformation field asks for ``t`` and ``t_ref``). One program takes a
block of points and every channel of one level: it samples the three spatial planes once and
the three spatio-temporal planes at each time, and writes each time's product. The backward
walks the same blocks, recomputes the samples and adds ``dL/dplane`` at the four corners of
each sample with atomic adds, as ``grid_sample``'s backward does. As a chain of PyTorch
operations the features of one step are about ninety operations forward and two hundred
backward, each launched from the host; here they are one kernel per level each way. The points
are constant (the canonical Gaussians' positions): no gradient flows to them or to the times.
Float32 only (the PyTorch path serves other types). Triton's interpreter
(``TRITON_INTERPRET=1``) runs the same kernel on CPU tensors, which is how the tests compare it
with the PyTorch path on a machine without a GPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import triton
import triton.language as tl
from torch import Tensor

BLOCK = 32
"""Points per program."""


@triton.jit
def _corners(u, size):
    """Nodes and weight of a linear interpolation along an axis of ``size`` nodes at normalised
    coordinates ``u`` (``align_corners=True``, clamped to the border): lower node, upper node
    (the lower one again at the last node, with weight zero), and the upper node's weight."""
    x = (u + 1) / 2 * (size - 1)
    x = tl.minimum(tl.maximum(x, 0.0), size - 1.0)
    low = tl.floor(x)
    lower = low.to(tl.int32)
    return lower, tl.minimum(lower + 1, size - 1), x - low


@triton.jit
def _addresses(plane, channel, cols, plane_size, r0, r1, k0, k1):
    """The four corners' addresses ``(B, C)`` in a ``(C, rows, cols)`` plane: ``(r0, k0),
    (r0, k1), (r1, k0), (r1, k1)``."""
    base = plane + channel[None, :] * plane_size
    return (
        base + (r0 * cols + k0)[:, None],
        base + (r0 * cols + k1)[:, None],
        base + (r1 * cols + k0)[:, None],
        base + (r1 * cols + k1)[:, None],
    )


@triton.jit
def _weights(fr, fk):
    """Bilinear weights ``(B, 1)`` of the corners of :func:`_addresses`, in its order."""
    return (
        ((1 - fr) * (1 - fk))[:, None],
        ((1 - fr) * fk)[:, None],
        (fr * (1 - fk))[:, None],
        (fr * fk)[:, None],
    )


@triton.jit
def _sample(plane, channel, cols, plane_size, r0, r1, fr, k0, k1, fk, mask):
    """Bilinear samples ``(B, C)`` of a plane at rows ``r0, r1, fr`` and columns ``k0, k1, fk``
    (:func:`_corners` of each axis)."""
    a00, a01, a10, a11 = _addresses(plane, channel, cols, plane_size, r0, r1, k0, k1)
    w00, w01, w10, w11 = _weights(fr, fk)
    return (
        tl.load(a00, mask=mask, other=0.0) * w00
        + tl.load(a01, mask=mask, other=0.0) * w01
        + tl.load(a10, mask=mask, other=0.0) * w10
        + tl.load(a11, mask=mask, other=0.0) * w11
    )


@triton.jit
def _scatter(grad_plane, channel, cols, plane_size, r0, r1, fr, k0, k1, fk, mask, grad):
    """Add ``grad`` ``(B, C)`` (``dL/dsample``) into a plane's gradient at the sample's corners,
    weighted as in :func:`_sample`."""
    a00, a01, a10, a11 = _addresses(grad_plane, channel, cols, plane_size, r0, r1, k0, k1)
    w00, w01, w10, w11 = _weights(fr, fk)
    tl.atomic_add(a00, grad * w00, mask=mask)
    tl.atomic_add(a01, grad * w01, mask=mask)
    tl.atomic_add(a10, grad * w10, mask=mask)
    tl.atomic_add(a11, grad * w11, mask=mask)


@triton.jit
def _level_kernel(
    features,
    positions,
    times,
    xy,
    xz,
    yz,
    xt,
    yt,
    zt,
    g_xy,
    g_xz,
    g_yz,
    g_xt,
    g_yt,
    g_zt,
    count,
    size_z,
    size_y,
    size_x,
    size_t,
    column,
    width,
    CHANNELS: tl.constexpr,
    TIMES: tl.constexpr,
    BACKWARD: tl.constexpr,
    CP: tl.constexpr,
    BLOCK: tl.constexpr,
):
    """One level, a block of points, every channel. Forward: ``features[k, n, column + c]``
    ``(K, N, width)`` at each time ``k`` from the planes ``xy`` ... ``zt`` (``(C, R_a, R_b)``
    each). Backward: ``features`` holds ``dL/dfeatures``, reduced into the planes' gradients
    ``g_xy`` ... ``g_zt`` (unused forward)."""
    n = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    inside = n < count
    channel = tl.arange(0, CP)
    mask = inside[:, None] & (channel < CHANNELS)[None, :]
    z0, z1, fz = _corners(tl.load(positions + 3 * n, mask=inside, other=0.0), size_z)
    y0, y1, fy = _corners(tl.load(positions + 3 * n + 1, mask=inside, other=0.0), size_y)
    x0, x1, fx = _corners(tl.load(positions + 3 * n + 2, mask=inside, other=0.0), size_x)
    area_xy, area_xz, area_yz = size_x * size_y, size_x * size_z, size_y * size_z
    area_xt, area_yt, area_zt = size_x * size_t, size_y * size_t, size_z * size_t
    s_xy = _sample(xy, channel, size_y, area_xy, x0, x1, fx, y0, y1, fy, mask)
    s_xz = _sample(xz, channel, size_z, area_xz, x0, x1, fx, z0, z1, fz, mask)
    s_yz = _sample(yz, channel, size_z, area_yz, y0, y1, fy, z0, z1, fz, mask)
    spatial = s_xy * s_xz * s_yz
    at = features + n[:, None] * width + column + channel[None, :]
    grad_spatial = tl.zeros([BLOCK, CP], tl.float32)
    for k in tl.static_range(TIMES):
        t0, t1, ft = _corners(tl.load(times + k) + tl.zeros([BLOCK], tl.float32), size_t)
        a_xt = _sample(xt, channel, size_t, area_xt, x0, x1, fx, t0, t1, ft, mask)
        a_yt = _sample(yt, channel, size_t, area_yt, y0, y1, fy, t0, t1, ft, mask)
        a_zt = _sample(zt, channel, size_t, area_zt, z0, z1, fz, t0, t1, ft, mask)
        if not BACKWARD:
            tl.store(at + k * count * width, spatial * a_xt * a_yt * a_zt, mask=mask)
        else:
            grad = tl.load(at + k * count * width, mask=mask, other=0.0)
            grad_spatial += grad * (a_xt * a_yt * a_zt)
            grad = grad * spatial
            _scatter(
                g_xt, channel, size_t, area_xt, x0, x1, fx, t0, t1, ft, mask, grad * (a_yt * a_zt)
            )
            _scatter(
                g_yt, channel, size_t, area_yt, y0, y1, fy, t0, t1, ft, mask, grad * (a_xt * a_zt)
            )
            _scatter(
                g_zt, channel, size_t, area_zt, z0, z1, fz, t0, t1, ft, mask, grad * (a_xt * a_yt)
            )
    if BACKWARD:
        _scatter(
            g_xy,
            channel,
            size_y,
            area_xy,
            x0,
            x1,
            fx,
            y0,
            y1,
            fy,
            mask,
            grad_spatial * (s_xz * s_yz),
        )
        _scatter(
            g_xz,
            channel,
            size_z,
            area_xz,
            x0,
            x1,
            fx,
            z0,
            z1,
            fz,
            mask,
            grad_spatial * (s_xy * s_yz),
        )
        _scatter(
            g_yz,
            channel,
            size_z,
            area_yz,
            y0,
            y1,
            fy,
            z0,
            z1,
            fz,
            mask,
            grad_spatial * (s_xy * s_xz),
        )


def _launch(features, positions, times, levels, grads, channels, backward) -> None:
    """Run :func:`_level_kernel` for each level's six planes (``levels``, ``(1, C, R_a, R_b)``
    in ``PLANES`` order) and, backward, their gradients ``grads``."""
    count, width = positions.shape[0], features.shape[-1]
    for level, planes in enumerate(levels):
        xy, _, _, xt, _, _ = planes
        size_x, size_y, size_t = xy.shape[2], xy.shape[3], xt.shape[3]
        size_z = planes[1].shape[3]
        _level_kernel[(triton.cdiv(count, BLOCK),)](
            features,
            positions,
            times,
            *planes,
            *(grads[level] if backward else planes),  # unused forward
            count,
            size_z,
            size_y,
            size_x,
            size_t,
            level * channels,
            width,
            CHANNELS=channels,
            TIMES=len(times),
            BACKWARD=backward,
            CP=triton.next_power_of_2(channels),
            BLOCK=BLOCK,
        )


class _Features(torch.autograd.Function):
    """Features ``(K, N, L C)`` of points ``(N, 3)`` at ``K`` times ``(K,)`` from the planes
    (``L`` levels of six, flat), differentiable in the planes."""

    @staticmethod
    def forward(ctx, positions, times, *planes):
        levels = _levels(planes)
        channels = planes[0].shape[1]
        features = torch.empty(
            len(times), len(positions), len(levels) * channels, device=positions.device
        )
        if len(positions):
            _launch(features, positions, times, levels, None, channels, False)
        ctx.save_for_backward(positions, times, *planes)
        return features

    @staticmethod
    def backward(ctx, grad):
        positions, times, *planes = ctx.saved_tensors
        flat = torch.zeros(sum(p.numel() for p in planes), device=grad.device)
        grads = [g.view(p.shape) for g, p in zip(flat.split([p.numel() for p in planes]), planes)]
        if len(positions):
            levels, channels = _levels(planes), planes[0].shape[1]
            _launch(grad.contiguous(), positions, times, levels, _levels(grads), channels, True)
        return None, None, *grads


def _levels(planes: Sequence[Tensor]) -> list[tuple[Tensor, ...]]:
    """Flat planes grouped six by six (one level each)."""
    return [tuple(planes[i : i + 6]) for i in range(0, len(planes), 6)]


def hexplane_features(positions: Tensor, times: Tensor, planes: Sequence[Tensor]) -> Tensor:
    """HexPlane features (Eq. S18) of points at scalar times, in float32.

    Parameters
    ----------
    positions : Tensor
        ``(N, 3)`` normalised positions (z, y, x) in [-1, 1] (no gradient flows to them).
    times : Tensor
        ``(K,)`` normalised times in [-1, 1], ``K`` one or two.
    planes : sequence of Tensor
        ``L`` levels of six ``(1, C, R_a, R_b)`` planes in ``PLANES`` order, flat.

    Returns
    -------
    Tensor
        ``(K, N, L C)``: each time's features, level after level.
    """
    planes = [p.contiguous() for p in planes]
    for tensor in (positions, times, *planes):
        if tensor.dtype != torch.float32:
            raise TypeError(f"the Triton HexPlane takes float32, got {tensor.dtype}")
    return _Features.apply(positions.detach().contiguous(), times.detach().contiguous(), *planes)
