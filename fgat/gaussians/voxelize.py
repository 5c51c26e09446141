"""Differentiable voxelization of anisotropic 3D Gaussians (Eq. S16).

``V(x) = sum_n i_n exp(-1/2 (x - mu_n)^T Sigma_n^{-1} (x - mu_n))`` evaluated at voxel centres.
Cut-off rule: Gaussian ``n`` contributes only to voxels whose centre lies inside its 3-sigma box,
``|x_k - mu_{n,k}| <= 3 sqrt(Sigma_{n,kk})`` on every axis ``k``; Gaussians whose box misses the
grid are skipped. The exponent is written once per Gaussian as ten coefficients over the
monomials of a voxel's offset from the window's centre voxel (:func:`exponent_coefficients`).
Two paths evaluate it. The PyTorch path groups Gaussians by the size of their box (rounded up to
a few window sizes, the same in y and x), evaluates each group on a fixed window of voxel offsets
as one product and accumulates with ``index_add_``, in chunks that bound memory. The Triton path
(:mod:`fgat.gaussians.voxelize_triton`, float32 on a GPU) computes the coefficients from the
means, scales and orientations in one kernel and evaluates every box in tiles in another, and
differentiates each in one kernel; the boxes (whole voxels, no gradient) come from the same
PyTorch operations on both paths, so both evaluate the same voxels. Either way the cost grows
with the summed box volume, not with ``N x voxels``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from fgat._core.devices import constant, use_triton
from fgat.gaussians.rotation import quaternion_to_rotation

WINDOW_HALF_WIDTHS = (1, 2, 3, 4, 5, 6, 7, 8, 10, 12, 14, 16, 20, 24, 32, 40, 48, 64, 80, 96, 128)
"""Half-widths (voxels) of the evaluation windows Gaussians are grouped into."""


def _bucket(half_width: Tensor) -> Tensor:
    """Smallest listed window half-width >= each entry (entries beyond the list keep their
    value)."""
    sizes = constant(WINDOW_HALF_WIDTHS, half_width.device)
    index = torch.searchsorted(sizes, half_width.contiguous())
    return torch.where(index < len(sizes), sizes[index.clamp(max=len(sizes) - 1)], half_width)


def _window_groups(half_width: Tensor) -> tuple[Tensor, Tensor]:
    """Distinct ``(z, y, x)`` window half-widths ``(G, 3)`` (lateral ones equal), in
    lexicographic order, and each Gaussian's group: ``torch.unique(half_width, dim=0,
    return_inverse=True)`` computed over a 1-D integer key, which is many times faster."""
    lateral = half_width[:, 1]
    base = int(lateral.max()) + 1 if len(lateral) else 1
    keys, inverse = torch.unique(half_width[:, 0] * base + lateral, return_inverse=True)
    lateral = keys % base
    return torch.stack([keys // base, lateral, lateral], dim=1), inverse


PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
"""Index pairs ``(i, j)`` of a symmetric 3 x 3 matrix's distinct entries."""


def _window_features(world: list[Tensor]) -> Tensor:
    """Monomials ``[1, o_z, o_y, o_x, o_i o_j for (i, j) in PAIRS]`` ``(10, W)`` of a window's
    offsets ``o`` (the outer grid of the three axes' offsets ``world``, world units)."""
    o = torch.stack(torch.meshgrid(*world, indexing="ij"), dim=0).reshape(3, -1)
    rows, cols = zip(*PAIRS)
    return torch.cat([torch.ones_like(o[:1]), o, o[list(rows)] * o[list(cols)]])


def axis_std(rotation: Tensor, scales: Tensor) -> Tensor:
    """Per-axis standard deviation ``sqrt(Sigma_kk)`` ``(N, 3)`` of Gaussians with rotations
    ``(N, 3, 3)`` and scales ``(N, 3)``."""
    return torch.sqrt(((rotation * scales[..., None, :]) ** 2).sum(-1))


def precision_and_extent(scales: Tensor, quaternions: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse covariance ``R S^-2 R^T`` ``(N, 3, 3)`` and per-axis std ``sqrt(Sigma_kk)``
    ``(N, 3)``."""
    rotation = quaternion_to_rotation(quaternions)
    precision = (rotation / scales[..., None, :] ** 2) @ rotation.transpose(-1, -2)
    return precision, axis_std(rotation, scales)


def _use_triton(backend: str, means: Tensor) -> bool:
    return use_triton(backend, means, "Gaussians")


def exponent_coefficients(precision: Tensor, offset: Tensor) -> Tensor:
    """Coefficients ``(N, 10)`` of the exponent over the monomials ``[1, o, o_i o_j for (i, j)
    in PAIRS]`` of a voxel's world offset ``o`` from the window's centre voxel: with ``d = b +
    o`` (``b`` = ``offset``, centre voxel minus mean), ``-1/2 d^T P d = [-1/2 b^T P b, -P b,
    -1/2 P_ii, -P_ij] . [1, o, o_i o_j]``."""
    pb = (precision @ offset[:, :, None]).squeeze(-1)
    rows, cols = constant(PAIRS, precision.device).T
    symmetric = constant((-0.5, -0.5, -0.5, -1.0, -1.0, -1.0), precision.device, precision.dtype)
    return torch.cat(
        [-0.5 * (offset * pb).sum(1, keepdim=True), -pb, precision[:, rows, cols] * symmetric], 1
    )


def voxelize(
    means: Tensor,
    scales: Tensor,
    quats: Tensor,
    intensities: Tensor,
    shape: Sequence[int],
    voxel_size: Sequence[float],
    origin: Sequence[float],
    *,
    max_elements: int = 2**22,
    backend: str = "auto",
) -> Tensor:
    """Render Gaussians into a dense volume (Eq. S16), differentiable in all four inputs.

    Parameters
    ----------
    means : Tensor
        ``(N, 3)`` centres (z, y, x), world units (um).
    scales : Tensor
        ``(N, 3)`` standard deviations along the Gaussian's own axes, world units.
    quats : Tensor
        ``(N, 4)`` orientations (w, x, y, z); normalised here.
    intensities : Tensor
        ``(N,)`` peak values ``i_n``.
    shape : (Z, Y, X)
        Grid size in voxels.
    voxel_size : (dz, dy, dx)
        Voxel size, world units.
    origin : (z0, y0, x0)
        World position of the grid's corner: voxel ``i`` is centred at
        ``origin + (i + 0.5) voxel_size``.
    max_elements : int
        Gaussian-voxel pairs evaluated at once by the PyTorch path (bounds memory).
    backend : {"auto", "torch", "triton"}
        ``torch``: windows grouped by size, evaluated as batched products (any device, any
        floating type). ``triton``: two fused kernels, no grouping (float32, a GPU or Triton's
        interpreter). ``auto``: ``triton`` for float32 on a GPU where Triton is installed. The
        two agree to float32 rounding (tested).

    Returns
    -------
    Tensor
        ``(Z, Y, X)`` volume, dtype and device of ``means``.
    """
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    for name, tensor, tail in (
        ("scales", scales, (3,)),
        ("quats", quats, (4,)),
        ("intensities", intensities, ()),
    ):
        if tuple(tensor.shape) != (n, *tail):
            raise ValueError(f"{name} must have shape {(n, *tail)}, got {tuple(tensor.shape)}")
    shape = tuple(int(s) for s in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"shape must be three positive sizes (Z, Y, X), got {shape!r}")
    triton_path = _use_triton(backend, means)
    device, dtype = means.device, means.dtype
    size = constant(tuple(float(v) for v in voxel_size), device, dtype)
    corner = constant(tuple(float(v) for v in origin), device, dtype)
    grid = constant(shape, device)
    if n == 0:
        return torch.zeros(shape, dtype=dtype, device=device)

    if triton_path:  # the exponent's coefficients come from a kernel: here only the boxes
        with torch.no_grad():
            sigma_axes = axis_std(quaternion_to_rotation(quats), scales)
    else:
        precision, sigma_axes = precision_and_extent(scales, quats)
    half_extent = 3.0 * sigma_axes  # world units, per axis
    with torch.no_grad():
        position = (means - corner) / size - 0.5  # continuous voxel index of each mean
        reach = half_extent / size
        low = torch.ceil(position - reach)
        high = torch.floor(position + reach)
        visible = ((high >= 0) & (low <= grid - 1) & (high >= low)).all(dim=1)
        center = torch.round(position).long()
        half_width = torch.floor(reach + 0.5).long()  # |round(position) - position| <= 1/2
    offset = corner + (center.to(dtype) + 0.5) * size - means  # (N, 3): centre voxel - mean
    if triton_path:
        from fgat.gaussians.voxelize_triton import (  # Triton: only on the GPU path
            WindowTiles,
            gaussian_coefficients,
            voxelize_tiles,
        )

        offset = offset.detach()  # the kernel's backward gives the means' gradient
        coefficients = gaussian_coefficients(means, scales, quats, offset)
        tiles = WindowTiles(center, half_width, visible, offset, half_extent, shape, voxel_size)
        return voxelize_tiles(coefficients, intensities, tiles)
    coefficients = exponent_coefficients(precision, offset)
    return _voxelize_groups(
        coefficients,
        intensities,
        offset,
        half_extent,
        center,
        half_width,
        visible,
        shape,
        size,
        max_elements,
    )


def _voxelize_groups(
    coefficients: Tensor,
    intensities: Tensor,
    offset: Tensor,
    half_extent: Tensor,
    center: Tensor,
    half_width: Tensor,
    visible: Tensor,
    shape: tuple[int, int, int],
    size: Tensor,
    max_elements: int,
) -> Tensor:
    """The PyTorch path: Gaussians grouped by window size, each group's window evaluated as one
    product ``coefficients @ features`` and accumulated with ``index_add_``, in chunks of at
    most ``max_elements`` Gaussian-voxel pairs."""
    device, dtype = coefficients.device, coefficients.dtype
    volume = torch.zeros(math.prod(shape), dtype=dtype, device=device)
    with torch.no_grad():
        half_width = _bucket(half_width)
        # Square lateral windows: a few times fewer groups (kernel launches) for some padding.
        half_width[:, 1:] = half_width[:, 1:].amax(dim=1, keepdim=True)
        visible_index = torch.nonzero(visible).squeeze(1)
        groups, inverse = _window_groups(half_width[visible_index])
        counts = torch.bincount(inverse, minlength=len(groups)).tolist()
        members_of = torch.split(visible_index[torch.argsort(inverse)], counts)
    strides = (shape[1] * shape[2], shape[2], 1)
    for key, members in zip(groups.tolist(), members_of):
        steps = [torch.arange(-h, h + 1, device=device) for h in key]
        world = [step.to(dtype) * size[k] for k, step in enumerate(steps)]
        features = _window_features(world)  # (10, W)
        chunk = max(1, max_elements // features.shape[1])
        for begin in range(0, len(members), chunk):
            index = members[begin : begin + chunk]
            mask, linear = None, None
            for k in range(3):  # separable box, grid and index terms, one axis at a time
                voxel = center[index, k, None] + steps[k]  # (n, W_k)
                ok = (
                    (voxel >= 0)
                    & (voxel < shape[k])
                    & ((offset[index, k, None] + world[k]).abs() <= half_extent[index, k, None])
                )
                term = voxel.clamp(0, shape[k] - 1) * strides[k]
                view = [-1, 1, 1, 1]
                view[k + 1] = steps[k].numel()
                ok, term = ok.view(view), term.view(view)
                mask = ok if mask is None else mask & ok
                linear = term if linear is None else linear + term
            gaussian = torch.exp(coefficients[index] @ features) * intensities[index, None]
            values = torch.where(mask.reshape(len(index), -1), gaussian, 0.0)
            volume.index_add_(0, linear.reshape(-1), values.reshape(-1))
    return volume.reshape(shape)


def voxelize_dense(
    means: Tensor,
    scales: Tensor,
    quats: Tensor,
    intensities: Tensor,
    shape: Sequence[int],
    voxel_size: Sequence[float],
    origin: Sequence[float],
) -> Tensor:
    """Every Gaussian at every voxel with the same 3-sigma box rule: the reference for tests and
    benchmarks (memory ``N x voxels``)."""
    device, dtype = means.device, means.dtype
    axes = [
        torch.as_tensor(o, dtype=dtype)
        + (torch.arange(n, dtype=dtype, device=device) + 0.5) * torch.as_tensor(s, dtype=dtype)
        for n, s, o in zip(shape, voxel_size, origin)
    ]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    precision, sigma_axes = precision_and_extent(scales, quats)
    delta = points[None] - means[:, None]
    in_box = (delta.abs() <= 3.0 * sigma_axes[:, None]).all(-1)
    quadratic = ((delta @ precision) * delta).sum(-1)
    return (
        (intensities[:, None] * torch.exp(-0.5 * quadratic) * in_box).sum(0).reshape(tuple(shape))
    )
