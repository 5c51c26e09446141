"""Placing and cropping patches: against NumPy loops, adjointness, derivatives in every mode."""

import numpy as np
import pytest
import torch
from torch.func import jacfwd, jvp, vmap

from fgat.optics.patches import crop_patches, place_patches

# Three 4 x 5 patches on a 13 x 14 grid, the first two overlapping; with step 2 they span 7 x 9.
ORIGINS = [(0, 0), (2, 3), (6, 5)]
SHAPE = (13, 14)
SIZE = (4, 5)


def numpy_place(patches: np.ndarray, origins, shape, step: int) -> np.ndarray:
    grid = np.zeros((*patches.shape[:-3], *shape), dtype=patches.dtype)
    for p, (r0, c0) in enumerate(origins):
        for i in range(patches.shape[-2]):
            for j in range(patches.shape[-1]):
                grid[..., r0 + step * i, c0 + step * j] += patches[..., p, i, j]
    return grid


def numpy_crop(grid: np.ndarray, origins, size, step: int) -> np.ndarray:
    out = np.zeros((*grid.shape[:-2], len(origins), *size), dtype=grid.dtype)
    for p, (r0, c0) in enumerate(origins):
        for i in range(size[0]):
            for j in range(size[1]):
                out[..., p, i, j] = grid[..., r0 + step * i, c0 + step * j]
    return out


def random(shape, dtype=torch.float64, seed=0):
    return torch.randn(shape, dtype=dtype, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("step", [1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.complex64])
def test_place_and_crop_equal_numpy_loops(step, dtype):
    patches = random((2, 3, *SIZE), dtype)
    grid = random((2, *SHAPE), dtype, seed=1)
    placed = place_patches(patches, ORIGINS, SHAPE, step)
    np.testing.assert_allclose(
        placed.numpy(), numpy_place(patches.numpy(), ORIGINS, SHAPE, step), rtol=1e-6, atol=1e-6
    )
    np.testing.assert_array_equal(
        crop_patches(grid, ORIGINS, SIZE, step).numpy(),
        numpy_crop(grid.numpy(), ORIGINS, SIZE, step),
    )


@pytest.mark.parametrize("step", [1, 2])
def test_place_is_the_adjoint_of_crop(step):
    patches = random((3, *SIZE), torch.complex128)
    grid = random(SHAPE, torch.complex128, seed=1)
    left = torch.vdot(place_patches(patches, ORIGINS, SHAPE, step).flatten(), grid.flatten())
    right = torch.vdot(patches.flatten(), crop_patches(grid, ORIGINS, SIZE, step).flatten())
    torch.testing.assert_close(left, right, rtol=1e-12, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.complex128])
@pytest.mark.slow
def test_gradients_and_second_derivatives(dtype):
    patches = random((2, 3, *SIZE), dtype).requires_grad_(True)
    grid = random((2, *SHAPE), dtype, seed=1).requires_grad_(True)
    for function, argument in (
        (lambda x: place_patches(x, ORIGINS, SHAPE, 2), patches),
        (lambda x: crop_patches(x, ORIGINS, SIZE, 2), grid),
    ):
        assert torch.autograd.gradcheck(function, (argument,))
        assert torch.autograd.gradgradcheck(function, (argument,))


def test_forward_mode_and_vmap_equal_the_reverse_mode_jacobian():
    patches = random((3, *SIZE))
    grid = random(SHAPE, seed=1)
    for function, argument in (
        (lambda x: place_patches(x, ORIGINS, SHAPE, 2), patches),
        (lambda x: crop_patches(x, ORIGINS, SIZE, 2), grid),
    ):
        reverse = torch.autograd.functional.jacobian(function, argument)
        torch.testing.assert_close(jacfwd(function)(argument), reverse, rtol=0, atol=0)
        tangents = random((4, *argument.shape), seed=2)
        pushed = vmap(lambda t: jvp(function, (argument,), (t,))[1])(tangents)
        expected = torch.stack([function(t) for t in tangents])
        torch.testing.assert_close(pushed, expected, rtol=0, atol=0)


def test_patches_outside_the_grid_and_wrong_counts_are_refused():
    with pytest.raises(ValueError, match=r"patch 2 at \(6, 5\) spans 7 x 9 samples, outside"):
        place_patches(random((3, *SIZE)), ORIGINS, (12, 14), step=2)
    with pytest.raises(ValueError, match="outside the 13 x 13 grid"):
        crop_patches(random((13, 13)), ORIGINS, SIZE, step=2)
    with pytest.raises(ValueError, match="2 patches but 3 origins"):
        place_patches(random((2, *SIZE)), ORIGINS, SHAPE)
    with pytest.raises(ValueError, match="step must be a positive"):
        crop_patches(random(SHAPE), ORIGINS, SIZE, step=0)
