"""What a reconstruction needs from its data: measurement, optics, grid (and truth on phantoms)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from fgat._core.validation import check_number
from fgat.io.images import read_tiff, volume_entries
from fgat.optics.acquisition import MeasuredOperator, padded_shape
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import parse_depths
from fgat.sim.simulation import SimulationConfig, make_phantom, simulate, true_optics


@dataclass
class Scene:
    """One reference-frame measurement (or a sequence) and the optics it is reconstructed with.

    Attributes
    ----------
    measurement : numpy.ndarray
        ``(V, Y, X)`` per-view images, background subtracted, clipped at zero and divided by
        ``scale`` (maximum 1).
    scale : float
        Counts per unit of ``measurement`` (to report results in counts).
    psf : numpy.ndarray
        ``(V, Z, h, w)`` PSF stack used by the forward model.
    voxel_size_um : (dz, dy, dx)
        Grid spacing of the reconstruction.
    truth : numpy.ndarray or None
        ``(Z, Y, X)`` ground truth on phantoms.
    name : str
        Label for logs and figures.
    optics : OpticsSpec or None
        How ``psf`` was made, when a JPGM made it: the starting point of self-estimation.
    truth_optics : OpticsSpec or None
        On phantoms, the optics the measurement was simulated with.
    frames : numpy.ndarray or None
        A sequence's per-view images ``(T, V, Y, X)``, normalised with the reference frame's
        ``scale``; ``measurement`` is ``frames[reference]``. ``None`` for a single frame.
    times : numpy.ndarray or None
        Normalised acquisition times ``(T,)`` in [0, 1] (first frame 0, last frame 1).
    reference : int
        Index of the reference frame (``t_ref``, the static stage's frame).
    truth_frames : numpy.ndarray or None
        On dynamic phantoms, the truth ``(T, Z, Y, X)`` of every frame.
    truth_at : callable or None
        On dynamic phantoms, ``truth_at(times) -> (T', Z, Y, X)``: the truth at any normalised
        times (e.g. between frames).
    gains : numpy.ndarray or None
        ``(V,)`` known relative per-view gains (vignetting, MLA transmission), positive and
        dimensionless, applied in the forward model: measured view ``v`` = ``g_v`` x ideal view.
        ``None``: all 1.
    mask : numpy.ndarray or None
        ``(V, Y, X)`` float pixel mask, 1 = use, 0 = ignore (hot pixels), honoured by every
        loss and by SHB. ``None``: every pixel.
    guard_px : int
        Lateral guard band in voxels: the reconstruction grid is :attr:`grid_shape`
        ``(Z, Y + 2g, X + 2g)`` (objects just outside the field of view land in the band, not
        in the border voxels), the output :attr:`volume_shape` ``(Z, Y, X)`` its centre.
    depth_axis : {"up", "down"}
        Orientation of the volume's Z axis (:data:`fgat._core.conventions.DEPTH_AXES`): the
        order of ``psf``'s planes.
    depths_um : tuple of float or None
        ``(Z,)`` depth in um of every Z index of the volume (of every plane of ``psf``), in the
        order of ``depth_axis``; ``None`` when not known.
    offset_um : (z, y, x)
        Where the volume's centre lies in the full scene's coordinates, um (a cropped scene's
        box, :mod:`fgat.recon.crop`; 0 otherwise).
    frame_interval_s : float or None
        Seconds between consecutive frames of a sequence (the time axis of the series written);
        ``None`` when not known (the axis is then in frames).

    Raises
    ------
    ValueError
        ``gains``, ``mask``, ``guard_px``, ``depth_axis``, ``depths_um`` or ``frame_interval_s``
        of the wrong shape or out of range.
    """

    measurement: np.ndarray
    scale: float
    psf: np.ndarray
    voxel_size_um: tuple[float, float, float]
    truth: np.ndarray | None = None
    name: str = "scene"
    optics: OpticsSpec | None = None
    truth_optics: OpticsSpec | None = None
    frames: np.ndarray | None = None
    times: np.ndarray | None = None
    reference: int = 0
    truth_frames: np.ndarray | None = None
    truth_at: Callable[[np.ndarray], np.ndarray] | None = None
    gains: np.ndarray | None = None
    mask: np.ndarray | None = None
    guard_px: int = 0
    depth_axis: str = "up"
    depths_um: tuple[float, ...] | None = None
    offset_um: tuple[float, float, float] = (0.0, 0.0, 0.0)
    frame_interval_s: float | None = None

    def __post_init__(self) -> None:
        n_views = self.measurement.shape[0]
        if self.frame_interval_s is not None:
            self.frame_interval_s = check_number(
                "frame_interval_s", self.frame_interval_s, above=0.0
            )
        if self.gains is not None:
            self.gains = np.asarray(self.gains, dtype=np.float64)
            if self.gains.shape != (n_views,) or not (
                np.isfinite(self.gains).all() and (self.gains > 0).all()
            ):
                raise ValueError(
                    f"gains must be {n_views} finite positive numbers (one per view), got "
                    f"shape {self.gains.shape}"
                )
        if self.mask is not None:
            self.mask = np.asarray(self.mask, dtype=np.float32)
            if self.mask.shape != self.measurement.shape or not np.isin(self.mask, (0, 1)).all():
                raise ValueError(
                    f"mask must be 0/1 of the measurement's shape {self.measurement.shape}, got "
                    f"shape {self.mask.shape}"
                )
            if not self.mask.any():
                raise ValueError("mask ignores every pixel")
        guard = self.guard_px
        if isinstance(guard, bool) or not isinstance(guard, (int, np.integer)) or guard < 0:
            raise ValueError(f"guard_px must be a non-negative integer, got {guard!r}")
        self.guard_px = int(guard)
        depths = volume_entries(self.depth_axis, self.depths_um)["depths_um"]  # checks both
        if depths is not None:
            self.depths_um = tuple(depths)
            if len(self.depths_um) != self.psf.shape[1]:
                raise ValueError(
                    f"depths_um: {len(self.depths_um)} depths for the {self.psf.shape[1]} planes "
                    "of the PSF stack"
                )

    def volume_entries(self) -> dict[str, object]:
        """What the volume files of this scene record about their Z axis and the view order
        (:func:`fgat.io.images.volume_entries`)."""
        return volume_entries(self.depth_axis, self.depths_um)

    @property
    def volume_shape(self) -> tuple[int, int, int]:
        """The output grid ``(Z, Y, X)``: the views' lateral size (the truth's shape)."""
        return (self.psf.shape[1], *self.measurement.shape[1:])

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """The reconstruction grid ``(Z, Y + 2g, X + 2g)`` with the guard band ``g``."""
        return padded_shape(self.volume_shape, self.guard_px)

    @property
    def grid_origin(self) -> tuple[float, float, float]:
        """World position (um, ``(z, y, x)``) of the reconstruction grid's corner: the output grid
        is centred on ``offset_um`` (0: a :class:`~fgat.gaussians.cloud.GaussianCloud`'s default
        origin, in its float32 arithmetic) and the guard band lies outside it, so every output
        voxel has the same centre with and without a guard band."""
        voxel = torch.tensor(self.voxel_size_um, dtype=torch.float32)
        extent = torch.tensor(self.volume_shape, dtype=torch.float32) * voxel
        guard = torch.tensor([0.0, self.guard_px, self.guard_px]) * voxel
        offset = torch.tensor(self.offset_um, dtype=torch.float32)
        return tuple((-extent / 2 - guard + offset).tolist())

    @property
    def view_shape(self) -> tuple[int, int]:
        """``(Y, X)`` of each view, pixels."""
        return tuple(self.measurement.shape[1:])

    def operator(self, psf, gains=None) -> MeasuredOperator:
        """The scene's forward model for a PSF stack tensor ``(V, Z, h, w)``: its views, guard
        band and gains (``gains`` ``(V,)``, e.g. estimated ones, instead of the scene's)."""
        return MeasuredOperator(
            psf, self.view_shape, self.guard_px, self.gains if gains is None else gains
        )

    @property
    def n_frames(self) -> int:
        return 1 if self.frames is None else len(self.frames)

    def sequence(self) -> tuple[np.ndarray, np.ndarray]:
        """``(frames (T, V, Y, X), times (T,))``; a single frame is a sequence of one at t = 0."""
        if self.frames is None:
            return self.measurement[None], np.zeros(1)
        return self.frames, self.times


def normalized_measurement(
    views: np.ndarray,
    background: float,
    reference: int | None = None,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Subtract the camera offset, clip at zero and divide by the maximum of the views
    ``(V, Y, X)``, or of frame ``reference`` of a sequence ``(T, V, Y, X)`` (every frame by the
    same scale): ``(views, scale)``, float32 views and the scale in the input's units. With a
    pixel ``mask`` ``(V, Y, X)`` (1 = use) the maximum is taken over the unmasked pixels (a hot
    pixel does not set the scale).

    The arithmetic is float64, one frame at a time (memory of one frame), rounded to float32 once
    at the end: a measurement and any multiple of it (offset included) give the same float32
    views, and counts that float32 holds exactly give what float32 arithmetic gives.
    """
    views = np.asarray(views)
    frame = views if reference is None else views[reference]
    offset = _above_offset(frame, background)
    scale = float((offset if mask is None else offset * (np.asarray(mask) > 0)).max())
    if scale <= 0:
        raise ValueError(
            f"the measurement is zero everywhere after subtracting the background ({background})"
        )
    normalized = np.empty(views.shape, dtype=np.float32)
    for index in np.ndindex(views.shape[:-3]):
        normalized[index] = _above_offset(views[index], background) / scale
    return normalized, scale


def _above_offset(views: np.ndarray, background: float) -> np.ndarray:
    """``max(views - background, 0)`` in float64."""
    return np.clip(views.astype(np.float64) - float(background), 0, None)


def reference_index(frame: int | None, n_frames: int, source: str) -> int:
    """The reference frame: ``frame`` (checked) or the middle one, ``T // 2`` (Note S3)."""
    index = n_frames // 2 if frame is None else int(frame)
    if not 0 <= index < n_frames:
        raise ValueError(f"{source}: reference frame {index} is outside the {n_frames} frames")
    return index


def phantom_scene(
    config: SimulationConfig, psf: str = "true", reference: int | None = None
) -> Scene:
    """Simulate ``config`` and return its :class:`Scene`, truth and true optics included.

    Parameters
    ----------
    config : SimulationConfig
        The acquisition (a dynamic phantom with ``frames > 1`` gives a sequence).
    psf : str
        PSF of the reconstruction: ``"true"`` (the simulation's), ``"ideal"`` (aberration-free
        JPGM of the same system, as 3DGAT assumes) or a PSF OME-TIFF path ``(V, Z, h, w)``.
    reference : int, optional
        Reference frame of a sequence; default the middle one.
    """
    result = simulate(config)
    reference = (
        reference_index(reference, config.frames, "reference frame") if result.is_sequence else None
    )
    views, scale = normalized_measurement(result.views, config.background, reference)
    truth_optics = OpticsSpec(
        result.system,
        tuple(parse_depths(config.depths_um)),
        result.centers,
        **true_optics(config, result.system.n_lenslets),
    )
    optics = None
    if psf == "true":
        stack, optics = result.psf, truth_optics
    elif psf == "ideal":
        optics = truth_optics.ideal()
        stack = optics.psf()
    else:
        stack = read_tiff(psf, ndim=4, axes="(V, Z, h, w)", nonnegative=True)
        if stack.shape[:2] != result.psf.shape[:2]:
            raise ValueError(
                f"{psf}: {stack.shape[:2]} (views, depths), expected {result.psf.shape[:2]}"
            )
    measurement, truth, sequence = views, result.truth, {}
    if result.is_sequence:
        measurement, truth = views[reference], result.truth[reference]
        sequence = {
            "frames": views,
            "times": result.times,
            "reference": reference,
            "truth_frames": result.truth,
            "truth_at": lambda times: make_phantom(config, truth.shape, times),
        }
    return Scene(
        measurement=measurement,
        scale=scale,
        psf=stack,
        voxel_size_um=result.voxel_size_um,
        truth=truth,
        name=f"{config.phantom['kind']} phantom",
        optics=optics,
        truth_optics=truth_optics,
        depths_um=truth_optics.depths_um,
        **sequence,
    )
