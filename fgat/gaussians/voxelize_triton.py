"""Voxelization (Eq. S16) as a Triton kernel: the GPU path of :func:`fgat.gaussians.voxelize`.

The same Gaussians, 3-sigma cut-off and exponent as the PyTorch path, laid out for a GPU. Every
visible Gaussian's window (its 3-sigma box rounded out to whole voxels, clipped to the grid) is
cut into tiles of ``BLOCK`` voxels; one program evaluates one tile and adds it into the volume
with atomic adds, so the work is balanced whatever the Gaussians' sizes and there is no grouping,
no sort and one host synchronisation (the number of tiles). The backward (the same kernel,
compiled with ``BACKWARD``) walks the same tiles and reduces ``dL/dV`` against each Gaussian's
values into the gradients of its ten exponent coefficients and its intensity, carried on to
means, scales and orientations in one more kernel (:func:`gaussian_coefficients`,
which also computes the coefficients: rotation, precision and exponent per Gaussian, instead of
some thirty PyTorch operations forward and a hundred and fifty backward). Float32 only (the
PyTorch path serves other types).
Triton's interpreter (``TRITON_INTERPRET=1``) runs the same kernel on CPU tensors, which is how
the tests compare it with the PyTorch path on a machine without a GPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import triton
import triton.language as tl
from torch import Tensor

from fgat._core.devices import constant
from fgat.gaussians.rotation import QUATERNION_EPS

BLOCK = 128
"""Voxels per tile (one program)."""


@triton.jit
def _tile(
    pid,
    tile_gaussian,
    tile_index,
    low,
    width,
    center,
    offset,
    extent,
    rows,
    columns,
    voxel_z,
    voxel_y,
    voxel_x,
    BLOCK: tl.constexpr,
):
    """The Gaussian of tile ``pid``, its voxels' flat indices, which of them lie in its 3-sigma
    box, and their world offsets ``o`` from the window's centre voxel."""
    g = tl.load(tile_gaussian + pid)
    t = tl.load(tile_index + pid) * BLOCK + tl.arange(0, BLOCK)
    width_y = tl.load(width + 3 * g + 1)
    width_x = tl.load(width + 3 * g + 2)
    plane = width_y * width_x
    count = tl.load(width + 3 * g) * plane
    iz = t // plane
    rest = t - iz * plane
    iy = rest // width_x
    ix = rest - iy * width_x
    step_z = tl.load(low + 3 * g) + iz
    step_y = tl.load(low + 3 * g + 1) + iy
    step_x = tl.load(low + 3 * g + 2) + ix
    o_z = step_z.to(tl.float32) * voxel_z
    o_y = step_y.to(tl.float32) * voxel_y
    o_x = step_x.to(tl.float32) * voxel_x
    inside = (
        (t < count)
        & (tl.abs(tl.load(offset + 3 * g) + o_z) <= tl.load(extent + 3 * g))
        & (tl.abs(tl.load(offset + 3 * g + 1) + o_y) <= tl.load(extent + 3 * g + 1))
        & (tl.abs(tl.load(offset + 3 * g + 2) + o_x) <= tl.load(extent + 3 * g + 2))
    )
    z = (tl.load(center + 3 * g) + step_z).to(tl.int64)
    y = (tl.load(center + 3 * g + 1) + step_y).to(tl.int64)
    x = (tl.load(center + 3 * g + 2) + step_x).to(tl.int64)
    linear = (z * rows + y) * columns + x
    return g, linear, inside, o_z, o_y, o_x


@triton.jit
def _gaussian(coefficients, intensities, g, inside, o_z, o_y, o_x):
    """``exp(c . [1, o, o_i o_j])`` over the tile (zero outside the box) and the intensity."""
    c = coefficients + 10 * g
    exponent = (
        tl.load(c)
        + tl.load(c + 1) * o_z
        + tl.load(c + 2) * o_y
        + tl.load(c + 3) * o_x
        + tl.load(c + 4) * (o_z * o_z)
        + tl.load(c + 5) * (o_y * o_y)
        + tl.load(c + 6) * (o_x * o_x)
        + tl.load(c + 7) * (o_z * o_y)
        + tl.load(c + 8) * (o_z * o_x)
        + tl.load(c + 9) * (o_y * o_x)
    )
    return tl.where(inside, tl.exp(exponent), 0.0), tl.load(intensities + g)


@triton.jit
def _tiles_kernel(
    values,
    grad_coefficients,
    grad_intensities,
    coefficients,
    intensities,
    tile_gaussian,
    tile_index,
    low,
    width,
    center,
    offset,
    extent,
    rows,
    columns,
    voxel_z,
    voxel_y,
    voxel_x,
    BACKWARD: tl.constexpr,
    BLOCK: tl.constexpr,
):
    """One tile: forward, its Gaussian's values added into the volume ``values``; backward,
    ``dL/dV`` (``values``) reduced against them into the Gaussian's gradients."""
    g, linear, inside, o_z, o_y, o_x = _tile(
        tl.program_id(0),
        tile_gaussian,
        tile_index,
        low,
        width,
        center,
        offset,
        extent,
        rows,
        columns,
        voxel_z,
        voxel_y,
        voxel_x,
        BLOCK,
    )
    value, intensity = _gaussian(coefficients, intensities, g, inside, o_z, o_y, o_x)
    if not BACKWARD:
        tl.atomic_add(values + linear, value * intensity, mask=inside)
    else:
        weighted = tl.load(values + linear, mask=inside, other=0.0) * value
        tl.atomic_add(grad_intensities + g, tl.sum(weighted, 0))
        d = weighted * intensity  # dL/d(exponent) at each voxel
        c = grad_coefficients + 10 * g
        tl.atomic_add(c, tl.sum(d, 0))
        tl.atomic_add(c + 1, tl.sum(d * o_z, 0))
        tl.atomic_add(c + 2, tl.sum(d * o_y, 0))
        tl.atomic_add(c + 3, tl.sum(d * o_x, 0))
        tl.atomic_add(c + 4, tl.sum(d * (o_z * o_z), 0))
        tl.atomic_add(c + 5, tl.sum(d * (o_y * o_y), 0))
        tl.atomic_add(c + 6, tl.sum(d * (o_x * o_x), 0))
        tl.atomic_add(c + 7, tl.sum(d * (o_z * o_y), 0))
        tl.atomic_add(c + 8, tl.sum(d * (o_z * o_x), 0))
        tl.atomic_add(c + 9, tl.sum(d * (o_y * o_x), 0))


COEFFICIENT_BLOCK = 128
"""Gaussians per program of the exponent coefficients' kernels."""


@triton.jit
def _rotation(quats, n, inside, EPS: tl.constexpr):
    """Gaussians ``n``'s unit quaternions ``(w, x, y, z)``, their norms (before the ``EPS``
    floor) and rotations ``R`` on (z, y, x) vectors, row by row (the (x, y, z) matrix with its
    rows and columns reversed, as :func:`~fgat.gaussians.rotation.quaternion_to_rotation`)."""
    w = tl.load(quats + 4 * n, mask=inside, other=1.0)
    x = tl.load(quats + 4 * n + 1, mask=inside, other=0.0)
    y = tl.load(quats + 4 * n + 2, mask=inside, other=0.0)
    z = tl.load(quats + 4 * n + 3, mask=inside, other=0.0)
    norm = tl.sqrt(w * w + x * x + y * y + z * z)
    floored = tl.maximum(norm, EPS)
    w, x, y, z = w / floored, x / floored, y / floored, z / floored
    return (
        w,
        x,
        y,
        z,
        norm,
        1 - 2 * (x * x + y * y),
        2 * (y * z + w * x),
        2 * (x * z - w * y),
        2 * (y * z - w * x),
        1 - 2 * (x * x + z * z),
        2 * (x * y + w * z),
        2 * (x * z + w * y),
        2 * (x * y - w * z),
        1 - 2 * (y * y + z * z),
    )


@triton.jit
def _precision(r00, r01, r02, r10, r11, r12, r20, r21, r22, d0, d1, d2):
    """``P = R diag(d) R^T``: its entries ``P_00, P_11, P_22, P_01, P_02, P_12``."""
    return (
        r00 * r00 * d0 + r01 * r01 * d1 + r02 * r02 * d2,
        r10 * r10 * d0 + r11 * r11 * d1 + r12 * r12 * d2,
        r20 * r20 * d0 + r21 * r21 * d1 + r22 * r22 * d2,
        r00 * r10 * d0 + r01 * r11 * d1 + r02 * r12 * d2,
        r00 * r20 * d0 + r01 * r21 * d1 + r02 * r22 * d2,
        r10 * r20 * d0 + r11 * r21 * d1 + r12 * r22 * d2,
    )


@triton.jit
def _coefficients_kernel(
    coefficients,
    grad_means,
    grad_scales,
    grad_quats,
    scales,
    quats,
    offset,
    count,
    BACKWARD: tl.constexpr,
    EPS: tl.constexpr,
    BLOCK: tl.constexpr,
):
    """Forward: each Gaussian's exponent coefficients ``c`` (ten, into ``coefficients``) from
    its scales ``s``, quaternion ``q`` and offset ``b`` (see :func:`exponent_coefficients`).
    Backward (``coefficients`` holding ``dL/dc``): ``dL/dmu = -dL/db``, ``dL/ds`` and ``dL/dq``,
    with ``G`` = ``dL/dP`` and ``Gs = G + G^T``: ``dL/db = -P (g_0 b + g_1..3)``, ``dL/dR = Gs R
    D`` and ``dL/ds_k = -2 (R^T G R)_kk / s_k^3`` for ``P = R D R^T``, ``D = diag(s^-2)``."""
    n = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    inside = n < count
    w, x, y, z, norm, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(quats, n, inside, EPS)
    s0 = tl.load(scales + 3 * n, mask=inside, other=1.0)
    s1 = tl.load(scales + 3 * n + 1, mask=inside, other=1.0)
    s2 = tl.load(scales + 3 * n + 2, mask=inside, other=1.0)
    d0, d1, d2 = 1.0 / (s0 * s0), 1.0 / (s1 * s1), 1.0 / (s2 * s2)
    p00, p11, p22, p01, p02, p12 = _precision(
        r00, r01, r02, r10, r11, r12, r20, r21, r22, d0, d1, d2
    )
    b0 = tl.load(offset + 3 * n, mask=inside, other=0.0)
    b1 = tl.load(offset + 3 * n + 1, mask=inside, other=0.0)
    b2 = tl.load(offset + 3 * n + 2, mask=inside, other=0.0)
    c = coefficients + 10 * n
    if not BACKWARD:
        u0 = p00 * b0 + p01 * b1 + p02 * b2
        u1 = p01 * b0 + p11 * b1 + p12 * b2
        u2 = p02 * b0 + p12 * b1 + p22 * b2
        tl.store(c, -0.5 * (b0 * u0 + b1 * u1 + b2 * u2), mask=inside)
        tl.store(c + 1, -u0, mask=inside)
        tl.store(c + 2, -u1, mask=inside)
        tl.store(c + 3, -u2, mask=inside)
        tl.store(c + 4, -0.5 * p00, mask=inside)
        tl.store(c + 5, -0.5 * p11, mask=inside)
        tl.store(c + 6, -0.5 * p22, mask=inside)
        tl.store(c + 7, -p01, mask=inside)
        tl.store(c + 8, -p02, mask=inside)
        tl.store(c + 9, -p12, mask=inside)
    else:
        g0 = tl.load(c, mask=inside, other=0.0)
        g1 = tl.load(c + 1, mask=inside, other=0.0)
        g2 = tl.load(c + 2, mask=inside, other=0.0)
        g3 = tl.load(c + 3, mask=inside, other=0.0)
        v0, v1, v2 = g0 * b0 + g1, g0 * b1 + g2, g0 * b2 + g3
        tl.store(grad_means + 3 * n, p00 * v0 + p01 * v1 + p02 * v2, mask=inside)
        tl.store(grad_means + 3 * n + 1, p01 * v0 + p11 * v1 + p12 * v2, mask=inside)
        tl.store(grad_means + 3 * n + 2, p02 * v0 + p12 * v1 + p22 * v2, mask=inside)
        # Gs_ij = -g0 b_i b_j - g_(1+i) b_j - g_(1+j) b_i, less g_(4+i) on the diagonal and
        # g_7, g_8, g_9 at (0, 1), (0, 2), (1, 2).
        e00 = -(g0 * b0 + 2 * g1) * b0 - tl.load(c + 4, mask=inside, other=0.0)
        e11 = -(g0 * b1 + 2 * g2) * b1 - tl.load(c + 5, mask=inside, other=0.0)
        e22 = -(g0 * b2 + 2 * g3) * b2 - tl.load(c + 6, mask=inside, other=0.0)
        e01 = -v0 * b1 - g2 * b0 - tl.load(c + 7, mask=inside, other=0.0)
        e02 = -v0 * b2 - g3 * b0 - tl.load(c + 8, mask=inside, other=0.0)
        e12 = -v1 * b2 - g3 * b1 - tl.load(c + 9, mask=inside, other=0.0)
        # M = Gs R, column by column; dL/dR_ik = M_ik d_k; (R^T Gs R)_kk = sum_i R_ik M_ik.
        m00 = e00 * r00 + e01 * r10 + e02 * r20
        m10 = e01 * r00 + e11 * r10 + e12 * r20
        m20 = e02 * r00 + e12 * r10 + e22 * r20
        m01 = e00 * r01 + e01 * r11 + e02 * r21
        m11 = e01 * r01 + e11 * r11 + e12 * r21
        m21 = e02 * r01 + e12 * r11 + e22 * r21
        m02 = e00 * r02 + e01 * r12 + e02 * r22
        m12 = e01 * r02 + e11 * r12 + e12 * r22
        m22 = e02 * r02 + e12 * r12 + e22 * r22
        tl.store(grad_scales + 3 * n, -(r00 * m00 + r10 * m10 + r20 * m20) * d0 / s0, inside)
        tl.store(grad_scales + 3 * n + 1, -(r01 * m01 + r11 * m11 + r21 * m21) * d1 / s1, inside)
        tl.store(grad_scales + 3 * n + 2, -(r02 * m02 + r12 * m12 + r22 * m22) * d2 / s2, inside)
        # dL/d(standard matrix): h_ab = dL/dR_(2-a)(2-b).
        h00, h01, h02 = m22 * d2, m21 * d1, m20 * d0
        h10, h11, h12 = m12 * d2, m11 * d1, m10 * d0
        h20, h21, h22 = m02 * d2, m01 * d1, m00 * d0
        dw = 2 * (z * (h10 - h01) + y * (h02 - h20) + x * (h21 - h12))
        dx = 2 * (y * (h01 + h10) + z * (h02 + h20) + w * (h21 - h12) - 2 * x * (h11 + h22))
        dy = 2 * (x * (h01 + h10) + z * (h12 + h21) + w * (h02 - h20) - 2 * y * (h00 + h22))
        dz = 2 * (x * (h02 + h20) + y * (h12 + h21) + w * (h10 - h01) - 2 * z * (h00 + h11))
        # Through q / max(|q|, EPS): the tangent part over |q|, or 1 / EPS where floored.
        unit = norm > EPS
        radial = tl.where(unit, w * dw + x * dx + y * dy + z * dz, 0.0)
        scale = 1.0 / tl.maximum(norm, EPS)
        tl.store(grad_quats + 4 * n, (dw - w * radial) * scale, mask=inside)
        tl.store(grad_quats + 4 * n + 1, (dx - x * radial) * scale, mask=inside)
        tl.store(grad_quats + 4 * n + 2, (dy - y * radial) * scale, mask=inside)
        tl.store(grad_quats + 4 * n + 3, (dz - z * radial) * scale, mask=inside)


class _Coefficients(torch.autograd.Function):
    """Exponent coefficients ``(N, 10)`` from means, scales, quaternions and the offsets ``b``
    of the window centres from the means (constant here: the centre voxels move with the mean
    only in whole voxels), differentiable in the first three; one kernel each way."""

    @staticmethod
    def forward(ctx, means, scales, quats, offset):
        scales, quats, offset = (t.contiguous() for t in (scales, quats, offset))
        coefficients = torch.empty(len(scales), 10, dtype=torch.float32, device=scales.device)
        _launch_coefficients(coefficients, None, scales, quats, offset)
        ctx.save_for_backward(scales, quats, offset)
        return coefficients

    @staticmethod
    def backward(ctx, grad):
        scales, quats, offset = ctx.saved_tensors
        grads = torch.empty_like(scales), torch.empty_like(scales), torch.empty_like(quats)
        _launch_coefficients(grad.contiguous(), grads, scales, quats, offset)
        return *grads, None


def _launch_coefficients(coefficients, grads, scales, quats, offset) -> None:
    """Run :func:`_coefficients_kernel` forward (``grads`` None) or backward."""
    if not len(scales):
        return
    backward = grads is not None
    _coefficients_kernel[(triton.cdiv(len(scales), COEFFICIENT_BLOCK),)](
        coefficients,
        *(grads if backward else (coefficients,) * 3),  # unused forward
        scales,
        quats,
        offset,
        len(scales),
        BACKWARD=backward,
        EPS=QUATERNION_EPS,
        BLOCK=COEFFICIENT_BLOCK,
    )


def gaussian_coefficients(means: Tensor, scales: Tensor, quats: Tensor, offset: Tensor) -> Tensor:
    """The ten exponent coefficients ``(N, 10)`` of
    :func:`fgat.gaussians.voxelize.exponent_coefficients` computed from float32 means, scales
    ``(N, 3)`` and quaternions ``(N, 4)`` (normalised here) in one kernel, and their gradients
    in one: ``offset`` ``(N, 3)`` (window centre voxel minus mean, world units) is taken as
    given, ``dL/d means = -dL/d offset``."""
    return _Coefficients.apply(means, scales, quats, offset.detach())


class WindowTiles:
    """The tiles of the visible Gaussians' windows on a ``(Z, Y, X)`` grid of voxel size
    ``(dz, dy, dx)`` (world units): per Gaussian the window's first step and width per axis
    ``(N, 3)`` (int32), window centre voxel ``(N, 3)``, offset ``b`` of the centre voxel from
    the mean and 3-sigma half-extent ``(N, 3)`` (world units), and per tile its Gaussian and its
    index within that Gaussian's window ``(T,)``."""

    def __init__(
        self,
        center: Tensor,
        half_width: Tensor,
        visible: Tensor,
        offset: Tensor,
        extent: Tensor,
        shape: Sequence[int],
        voxel_size: Sequence[float],
    ) -> None:
        self.shape = tuple(int(s) for s in shape)
        self.voxel_size = tuple(float(v) for v in voxel_size)
        grid = constant(self.shape, center.device)
        low = torch.maximum(-half_width, -center)  # clipped to the grid: no step leaves it
        high = torch.minimum(half_width, grid - 1 - center)
        width = (high - low + 1).clamp(min=0) * visible[:, None]
        tiles = (width.prod(dim=1) + BLOCK - 1) // BLOCK
        total = int(tiles.sum())  # the one host synchronisation
        gaussians = torch.arange(len(tiles), device=center.device)
        tile_gaussian = torch.repeat_interleave(gaussians, tiles, output_size=total)
        first = torch.cumsum(tiles, 0) - tiles
        tile_index = torch.arange(total, device=center.device) - first[tile_gaussian]
        self.tensors = tuple(
            t.contiguous()
            for t in (
                tile_gaussian.int(),
                tile_index.int(),
                low.int(),
                width.int(),
                center.int(),
                offset,
                extent,
            )
        )

    def launch(self, values: Tensor, coefficients: Tensor, intensities: Tensor, grads=None):
        """Run the kernel over every tile: add the volume into ``values`` (forward), or with
        ``grads`` (coefficients', intensities') reduce ``dL/dV`` = ``values`` into them."""
        if not len(self):
            return
        backward = grads is not None
        _tiles_kernel[(len(self),)](
            values,
            *(grads if backward else (coefficients, intensities)),  # unused forward
            coefficients,
            intensities,
            *self.tensors,
            self.shape[1],
            self.shape[2],
            *self.voxel_size,
            BACKWARD=backward,
            BLOCK=BLOCK,
        )

    def __len__(self) -> int:
        return len(self.tensors[0])


class _Voxelize(torch.autograd.Function):
    """``V = sum_n i_n exp(c_n . [1, o, o_i o_j])`` over the tiles; differentiable in the
    coefficients ``c`` ``(N, 10)`` and intensities ``i`` ``(N,)``."""

    @staticmethod
    def forward(ctx, coefficients, intensities, tiles):
        coefficients, intensities = coefficients.contiguous(), intensities.contiguous()
        volume = torch.zeros(tiles.shape, dtype=torch.float32, device=coefficients.device)
        tiles.launch(volume, coefficients, intensities)
        ctx.save_for_backward(coefficients, intensities)
        ctx.tiles = tiles
        return volume

    @staticmethod
    def backward(ctx, grad_volume):
        coefficients, intensities = ctx.saved_tensors
        grads = torch.zeros_like(coefficients), torch.zeros_like(intensities)
        ctx.tiles.launch(grad_volume.contiguous(), coefficients, intensities, grads)
        return *grads, None


def voxelize_tiles(coefficients: Tensor, intensities: Tensor, tiles: WindowTiles) -> Tensor:
    """Render ``(Z, Y, X)`` from each Gaussian's exponent coefficients ``(N, 10)`` (over the
    monomials ``[1, o_z, o_y, o_x, o_z^2, o_y^2, o_x^2, o_z o_y, o_z o_x, o_y o_x]`` of the
    world offset ``o`` from its window's centre voxel) and intensities ``(N,)``, float32."""
    if coefficients.dtype != torch.float32 or intensities.dtype != torch.float32:
        raise TypeError(
            f"the Triton voxelizer takes float32, got {coefficients.dtype}/{intensities.dtype}"
        )
    return _Voxelize.apply(coefficients, intensities, tiles)
