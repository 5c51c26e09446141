"""Patches on a grid: placing them (overlaps add) and cropping them, an exact adjoint pair.

Both act on the last two axes of any ``(..., H, W)`` grid with ``(..., P, h, w)`` patches, the
patch's sample ``(i, j)`` at grid index ``(r0 + step i, c0 + step j)`` for its origin
``(r0, c0)``. Their gradients are each other, taken patch by patch: autograd through in-place
slice additions instead copies the whole grid's gradient once per patch (a third of a
small-system JPGM update). Forward-mode derivatives and ``vmap`` apply the same maps, so the
cross-information's Jacobians see them too.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

Origins = tuple[tuple[int, int], ...]


def place_patches(
    patches: Tensor, origins: Sequence[Sequence[int]], shape: Sequence[int], step: int = 1
) -> Tensor:
    """The grid ``(..., H, W)`` that holds ``patches`` ``(..., P, h, w)`` at ``origins`` (P of
    ``(r0, c0)``, grid samples), zero elsewhere; overlapping patches add. The adjoint of
    :func:`crop_patches`."""
    size = tuple(patches.shape[-2:])
    origins, shape = _checked(origins, patches.shape[-3], size, shape, step)
    return _Patches.apply(patches, origins, shape, size, step, True)


def crop_patches(
    grid: Tensor, origins: Sequence[Sequence[int]], size: Sequence[int], step: int = 1
) -> Tensor:
    """Patches ``(..., P, h, w)`` of ``size`` ``(h, w)`` cut from ``grid`` ``(..., H, W)`` at
    ``origins`` (P of ``(r0, c0)``, grid samples), every ``step``-th sample. The adjoint of
    :func:`place_patches`."""
    origins, shape = _checked(origins, len(origins), size, grid.shape[-2:], step)
    return _Patches.apply(grid, origins, shape, tuple(int(n) for n in size), step, False)


def _checked(
    origins: Sequence[Sequence[int]],
    count: int,
    size: Sequence[int],
    shape: Sequence[int],
    step: int,
) -> tuple[Origins, tuple[int, int]]:
    """``origins`` and ``shape`` as tuples of ints, after checking that every patch fits."""
    origins = tuple((int(r0), int(c0)) for r0, c0 in origins)
    shape = (int(shape[0]), int(shape[1]))
    if len(origins) != count:
        raise ValueError(f"{count} patches but {len(origins)} origins")
    if int(step) < 1:
        raise ValueError(f"step must be a positive number of samples, got {step}")
    span = [step * (int(n) - 1) + 1 for n in size]
    for p, (r0, c0) in enumerate(origins):
        if r0 < 0 or c0 < 0 or r0 + span[0] > shape[0] or c0 + span[1] > shape[1]:
            raise ValueError(
                f"patch {p} at {(r0, c0)} spans {span[0]} x {span[1]} samples, outside the "
                f"{shape[0]} x {shape[1]} grid"
            )
    return origins, shape


def _windows(origins: Origins, size: Sequence[int], step: int) -> list[tuple[slice, slice]]:
    h, w = (step * (int(n) - 1) + 1 for n in size)
    return [(slice(r0, r0 + h, step), slice(c0, c0 + w, step)) for r0, c0 in origins]


def _place(patches: Tensor, origins: Origins, shape: tuple[int, int], step: int) -> Tensor:
    grid = patches.new_zeros((*patches.shape[:-3], *shape))
    for p, (rows, cols) in enumerate(_windows(origins, patches.shape[-2:], step)):
        grid[..., rows, cols] += patches[..., p, :, :]
    return grid


def _crop(grid: Tensor, origins: Origins, size: tuple[int, int], step: int) -> Tensor:
    return torch.stack([grid[..., r, c] for r, c in _windows(origins, size, step)], dim=-3)


class _Patches(torch.autograd.Function):
    """:func:`place_patches` (``place``) or :func:`crop_patches`, with the other as its
    backward; being linear, each is its own forward-mode derivative, and under ``vmap`` the
    batch is one more leading dimension."""

    @staticmethod
    def forward(
        tensor: Tensor,
        origins: Origins,
        shape: tuple[int, int],
        size: tuple[int, int],
        step: int,
        place: bool,
    ) -> Tensor:
        if place:
            return _place(tensor, origins, shape, step)
        return _crop(tensor, origins, size, step)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.arguments = inputs[1:]

    @staticmethod
    def backward(ctx, grad: Tensor):
        *arguments, place = ctx.arguments
        return _Patches.apply(grad, *arguments, not place), None, None, None, None, None

    @staticmethod
    def jvp(ctx, tangent: Tensor, *_):
        return _Patches.apply(tangent, *ctx.arguments)

    @staticmethod
    def vmap(info, in_dims, tensor: Tensor, *arguments):
        if in_dims[0] is None:
            return _Patches.apply(tensor, *arguments), None
        return _Patches.apply(tensor.movedim(in_dims[0], 0), *arguments), 0
