"""Skip empty space: the part of the grid an SHB pre-pass finds signal in, with the PSF's reach.

A scene whose objects fill a fraction of the field of view is reconstructed on the box around
them instead (:func:`signal_box`): the voxels at or above a fraction of the pre-pass maximum,
grown by the PSFs' lateral reach (:func:`psf_reach`: 99% of the light from the box lands
within that margin of it in every view) and by a number of planes axially. The crop's forward
model is exact for its views whatever the margin (all the light they receive comes from the
box); the margin keeps the light the box sends around it, which outer views shift sideways.
:func:`crop_scene` cuts the scene to the box (the views' pixels, the PSF's planes, truth and
mask), keeping every voxel's world position; :func:`pad_volume` puts a volume of the box back
into the full grid.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from fgat.recon.scene import Scene

Box = tuple[slice, slice, slice]
"""``(z, y, x)`` slices of the output grid ``scene.volume_shape``."""


def psf_reach(psf: np.ndarray, energy: float = 0.99) -> tuple[int, int]:
    """Half-widths ``(ry, rx)`` (pixels) of the smallest box centred on the crops' centre
    ``(h // 2, w // 2)`` that holds ``energy`` of every view's PSF at every depth.

    Parameters
    ----------
    psf : numpy.ndarray
        ``(V, Z, h, w)`` non-negative PSF stack.
    energy : float
        Fraction in (0, 1].
    """
    psf = np.asarray(psf, dtype=np.float64)
    _, _, h, w = psf.shape
    total = psf.sum(axis=(-2, -1))
    integral = np.pad(psf.cumsum(-2).cumsum(-1), ((0, 0), (0, 0), (1, 0), (1, 0)))
    cy, cx = h // 2, w // 2
    for radius in range(max(h, w)):
        y0, y1 = max(cy - radius, 0), min(cy + radius + 1, h)
        x0, x1 = max(cx - radius, 0), min(cx + radius + 1, w)
        inside = (
            integral[..., y1, x1]
            - integral[..., y0, x1]
            - integral[..., y1, x0]
            + integral[..., y0, x0]
        )
        if np.all(inside >= energy * total):
            return min(radius, cy), min(radius, cx)
    return cy, cx


def signal_box(volume: np.ndarray, threshold: float, margin: tuple[int, int, int]) -> Box:
    """The box around the voxels at or above ``threshold`` times the maximum of ``volume``
    ``(Z, Y, X)``, grown by ``margin`` voxels ``(z, y, x)`` on each side and clipped to the
    grid; the whole grid when nothing is above it."""
    volume = np.asarray(volume)
    peak = float(volume.max()) if volume.size else 0.0
    if not peak > 0:
        return tuple(slice(0, n) for n in volume.shape)
    lit = np.nonzero(volume >= threshold * peak)
    return tuple(
        slice(max(int(index.min()) - pad, 0), min(int(index.max()) + pad + 1, n))
        for index, pad, n in zip(lit, margin, volume.shape)
    )


def box_voxels(box: Box) -> int:
    """Voxels in ``box`` (the product of its ``(z, y, x)`` extents)."""
    return int(np.prod([s.stop - s.start for s in box]))


def crop_scene(scene: Scene, box: Box) -> Scene:
    """The scene of the box: views ``[:, y, x]``, PSF planes ``[:, z]``, their depths, truth
    and mask cut alike; ``offset_um`` keeps each voxel's world position. Optics to estimate
    (``scene.optics``) stay only when every plane stays (their depth normalisation spans the
    planes)."""
    z, y, x = box
    full_z = z == slice(0, scene.volume_shape[0])

    def views(array):
        return None if array is None else np.ascontiguousarray(array[..., y, x])

    def volumes(array):
        return None if array is None else np.ascontiguousarray(array[..., z, y, x])

    voxel = np.asarray(scene.voxel_size_um, dtype=np.float64)
    full = np.asarray(scene.volume_shape, dtype=np.float64)
    start = np.array([s.start for s in box], dtype=np.float64)
    size = np.array([s.stop - s.start for s in box], dtype=np.float64)
    centre = np.asarray(scene.offset_um) + (start + size / 2 - full / 2) * voxel
    return dataclasses.replace(
        scene,
        measurement=views(scene.measurement),
        psf=np.ascontiguousarray(scene.psf[:, z]),
        truth=volumes(scene.truth),
        frames=views(scene.frames),
        truth_frames=volumes(scene.truth_frames),
        truth_at=None,
        mask=views(scene.mask),
        depths_um=None if scene.depths_um is None else scene.depths_um[z],
        optics=scene.optics if full_z else None,
        truth_optics=scene.truth_optics if full_z else None,
        offset_um=tuple(float(c) for c in centre),
    )


def pad_volume(volume: torch.Tensor, box: Box, shape: tuple[int, int, int]) -> torch.Tensor:
    """``volume`` (the box's ``(Z', Y', X')``) in a zero ``shape`` grid at ``box``."""
    full = volume.new_zeros(shape)
    full[box] = volume
    return full
