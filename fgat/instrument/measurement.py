"""A measured acquisition as fgat reconstructs it: from camera frames to per-view images.

A real FLFM camera is not fgat's phantom: the frames carry an offset and hot pixels, the outer
views are dimmer than the centre one, the lenslet centres sit where the MLA put them and the
depth planes may be listed in another code's order. :class:`MeasurementModel` holds what a
reconstruction needs to undo that (the camera model, the lenslet centres, the PSF stack, the
per-view gains and the depth order), and :func:`measurement_model` builds it from the files a
user has: a calibration folder (``python -m fgat calibrate``), a centres file or a brightfield
image, a PSF file or a system with depths, a dark frame. The data module of ``fit`` and
``python -m fgat deconvolve`` both use it, so a measurement means the same thing to both.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from fgat.instrument.calibration import Calibration
from fgat.instrument.camera import CameraModel, camera_from_dark
from fgat.instrument.centres import read_centers
from fgat.io.images import read_tiff, read_voxel_size, volume_metadata
from fgat.optics.acquisition import guard_band
from fgat.optics.depth_scale import calibrated_system
from fgat.optics.lenslets import detect_lenslet_centers
from fgat.optics.operator import crop_views
from fgat.optics.sampling import depth_spacing_warning
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import FLFMSystem


@dataclass(frozen=True)
class MeasurementModel:
    """Camera, lenslet centres, PSF and per-view gains of a measured acquisition.

    Attributes
    ----------
    camera : CameraModel
        Offset, read noise, hot pixels and flat field of the camera.
    centers : numpy.ndarray
        ``(V, 2)`` lenslet centres (row, col) pixels, in fgat's view order.
    psf : numpy.ndarray
        ``(V, Z, h, w)`` PSF stack, planes in the order of ``depth_axis``.
    voxel_size_um : (dz, dy, dx)
        Grid spacing of the reconstruction, um.
    optics : OpticsSpec or None
        How ``psf`` was made when a system made it (the start of self-estimation).
    gains : numpy.ndarray or None
        ``(V,)`` relative per-view gains applied in the forward model.
    depth_axis : {"up", "down"}
        ``"up"``: volume index 0 is the first (most negative) depth; ``"down"``: the last.
    depths_um : tuple of float or None
        ``(Z,)`` depth in um of every plane of ``psf`` (and Z index of the volume), in the order
        of ``depth_axis``; ``None`` when a PSF file does not record them.
    """

    camera: CameraModel
    centers: np.ndarray
    psf: np.ndarray
    voxel_size_um: tuple[float, float, float]
    optics: OpticsSpec | None = None
    gains: np.ndarray | None = None
    depth_axis: str = "up"
    depths_um: tuple[float, ...] | None = None

    def views(self, frames: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-view images of camera frames ``(T, H, W)``: ``(views (T, V, size, size), mask)``.

        The frames are corrected (:meth:`CameraModel.correct`: offset, flat field) and cropped
        around the centres; ``mask`` ``(V, size, size)`` is 0 at hot pixels (left in the views
        for every consumer to ignore), or ``None`` without hot pixels.
        """
        corrected = torch.from_numpy(self.camera.correct(frames).astype(np.float32))
        views = crop_views(corrected, self.centers, size).numpy()
        hot = self.camera.hot_pixels
        if hot is None or not hot.any():
            return views, None
        valid = self.camera.valid(frames.shape[-2:]).astype(np.float32)
        mask = crop_views(torch.from_numpy(valid), self.centers, size).numpy()
        return views, mask

    def guard(self, guard_px: int | str, size: int) -> int:
        """The guard band in pixels: ``guard_px``, or for ``"auto"`` the PSF stack's
        :func:`~fgat.optics.acquisition.guard_band` (its ``GUARD_ENERGY`` radius), at most
        ``size // 2``."""
        return guard_band(guard_px, self.psf, max_px=size // 2)


def measurement_model(
    *,
    calibration: Calibration | None = None,
    centers: str | None = None,
    brightfield: str | None = None,
    n_lenslets: int | None = None,
    psf: str | None = None,
    system: FLFMSystem | None = None,
    depths_um: list[float] | None = None,
    optics: dict | None = None,
    background: float | None = None,
    dark: str | None = None,
    gains=None,
    depth_axis: str | None = None,
) -> MeasurementModel:
    """Build a :class:`MeasurementModel` from a user's files.

    Parameters
    ----------
    calibration : Calibration, optional
        What ``python -m fgat calibrate`` wrote
        (:func:`fgat.instrument.calibration.read_calibration`): centres and, where present, gains,
        camera, depth axis and depth scale (applied to
        ``system``'s JPGM; a ``psf`` file is used as it is). The explicit arguments below take
        precedence over its entries.
    centers, brightfield : str, optional
        A centres file (``row,col`` CSV or ``.mat``), or a brightfield image of the MLA to detect
        ``n_lenslets`` centres in (:func:`~fgat.optics.lenslets.detect_lenslet_centers`).
    psf : str, optional
        A PSF stack ``(V, Z, h, w)`` OME-TIFF (its planes' depths and order those it records,
        :func:`~fgat.io.images.volume_metadata`; ``up`` when it records none); otherwise the
        JPGM of ``system`` on ``depths_um`` at the centres, with ``optics`` (``zernike``,
        ``intercepts``, ``slopes`` tables).
    background : float, optional
        Camera offset in counts; default the camera model's (``dark`` or the calibration's),
        else 0.
    dark : str, optional
        Dark frame(s) TIFF for the camera model (:func:`fgat.instrument.camera.camera_from_dark`).
    gains : sequence of float, optional
        ``(V,)`` per-view gains; default the calibration's, else none.
    depth_axis : {"up", "down"}, optional
        Plane order; default the calibration's, else ``"up"``.
    """
    camera = _camera(calibration, dark, background)
    if centers is not None:
        lenslets = read_centers(centers)
    elif calibration is not None:
        lenslets = calibration.centers
    else:
        lenslets = detect_lenslet_centers(read_tiff(brightfield, ndim=2), n_lenslets)
    axis = depth_axis or getattr(calibration, "depth_axis", None) or "up"
    step = -1 if axis == "down" else 1
    spec = None
    if psf is not None:
        if getattr(calibration, "depth_scale", None) is not None:
            warnings.warn(
                f"{psf}: a PSF file is used as it is, without the calibration's depth_scale "
                f"{calibration.depth_scale:g} (fgat psf --centers CALIBRATION applies it)",
                stacklevel=2,
            )
        stack = read_tiff(psf, ndim=4, axes="(V, Z, h, w) PSF stack", nonnegative=True)
        entries = volume_metadata(psf)
        if entries.get("depth_axis", "up") != "up":  # e.g. a fit's psf.ome.tif in "down" order
            step = -step
        stack = np.ascontiguousarray(stack.astype(np.float32)[:, ::step])
        sizes = read_voxel_size(psf)
        voxel = tuple(sizes.get(name, 1.0) for name in "ZYX")
        recorded = entries.get("depths_um")
        depths = None if recorded is None else recorded[::step]
        source = psf
    else:
        depths = list(depths_um)[::step]
        system = calibrated_system(system, calibration)
        spec = OpticsSpec(system, tuple(depths), lenslets, **(optics or {}))
        stack = spec.psf()
        voxel = system.grid_voxel_size_um(depths)
        source = f"system {system.name!r}"
        warning = depth_spacing_warning(stack, depths)
        if warning is not None:
            warnings.warn(f"depths_um: {warning}", stacklevel=2)
    if len(lenslets) != stack.shape[0]:
        raise ValueError(
            f"{len(lenslets)} lenslet centres but the PSF stack of {source} has "
            f"{stack.shape[0]} views"
        )
    if gains is None and calibration is not None:
        gains = calibration.gains
    if gains is not None:
        gains = np.asarray(gains, dtype=np.float64)
        if gains.shape != (len(lenslets),):
            raise ValueError(f"gains: {gains.size} per-view gains for {len(lenslets)} views")
    return MeasurementModel(
        camera, lenslets, stack, voxel, spec, gains, axis, None if depths is None else tuple(depths)
    )


def _camera(
    calibration: Calibration | None, dark: str | None, background: float | None
) -> CameraModel:
    """``dark``'s camera, else the calibration's, else an offset only; ``background`` replaces
    the offset."""
    if dark is not None:
        camera = camera_from_dark(read_tiff(dark, ndim=(2, 3)))
    else:
        camera = getattr(calibration, "camera", None) or CameraModel(0.0, 0.0)
    if background is not None:
        camera = dataclasses.replace(camera, offset=float(background))
    return camera
