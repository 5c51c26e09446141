"""Voxelization (Eq. S16) as a Triton kernel: the GPU path of :func:`fgat.gaussians.voxelize`.

The same Gaussians, 3-sigma cut-off and exponent as the PyTorch path, laid out for a GPU. Every
visible Gaussian's window (its 3-sigma box rounded out to whole voxels, clipped to the grid) is
cut into tiles of ``BLOCK`` voxels; one program evaluates one tile and adds it into the volume
with atomic adds, so the work is balanced whatever the Gaussians' sizes and there is no grouping,
no sort and one host synchronisation (the number of tiles). The backward (the same kernel,
compiled with ``BACKWARD``) walks the same tiles and reduces ``dL/dV`` against each Gaussian's
values into the gradients of its ten exponent coefficients and its intensity; PyTorch carries
them on to means, scales and orientations. Float32 only (the PyTorch path serves other types).
Triton's interpreter (``TRITON_INTERPRET=1``) runs the same kernel on CPU tensors, which is how
the tests compare it with the PyTorch path on a machine without a GPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import triton
import triton.language as tl
from torch import Tensor

from fgat.devices import constant

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
