"""Lenslet centres from the data: a hexagonal-lattice fit for any lenslet count.

An FLFM image repeats itself from lenslet to lenslet, whether it is a brightfield image of the
MLA (bright disks) or the fluorescence image itself (the same field of view behind every lens),
so the lattice shows in the image's autocorrelation: its six strongest peaks around the origin
give the pitch and the rotation. The lattice's position is where the ``V`` lattice points of
fgat's view order (:func:`~fgat.optics.lenslets.hexagonal_offsets`) collect the most light;
each lenslet is then refined to the centroid of its own disk and the lattice is refitted to the
refined centres by least squares. Centres come back in fgat's view order, with each lens's
distance from the fitted lattice. :func:`lattice_quality` says how far to trust a fit: the
contrast of every view over the background noise, the share of the views found and their RMS
distance from the lattice, with thresholds (:data:`MIN_VIEW_CONTRAST`,
:data:`MIN_VIEWS_FOUND`, :data:`MAX_RESIDUAL_RMS`) below which ``python -m fgat calibrate``
refuses the fit (an image of noise, a lenslet count the image does not show).

Per-view gains (vignetting, MLA transmission) come from a white-light image of the MLA
(:func:`gains_from_flat`) or from the fluorescence image itself (:func:`gains_from_image`). A
calibration folder (:func:`write_calibration`, :func:`read_calibration`) holds the centres,
the lattice, the gains, the camera model (:mod:`fgat.instrument.camera`), the depth-axis orientation
of reconstructed volumes (:data:`DEPTH_AXES`, :func:`orient_volume`) and fgat's view order
(:data:`VIEW_ORDER`) in ``calibration.yaml``.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgat._core.conventions import DEPTH_AXES, VIEW_ORDER
from fgat._core.validation import check_number
from fgat.instrument.camera import CameraModel, camera_from_image, read_camera, write_camera
from fgat.instrument.centres import read_centers, write_centers
from fgat.instrument.lattice import HexLattice
from fgat.io.files import atomic_path
from fgat.io.yaml_files import read_yaml

CALIBRATION_VERSION = 1
CALIBRATION_FILE = "calibration.yaml"
CALIBRATION_FIELDS = (
    "version",
    "source",
    "n_views",
    "centers",
    "lattice",
    "residuals_px",
    "gains",
    "gains_source",
    "camera",
    "depth_axis",
    "view_order",
    "depth_scale",
    "depth_scale_source",
)


@dataclass(eq=False)
class Calibration:
    """What fgat knows about an FLFM camera and its lenslets: a calibration folder's contents.

    Attributes
    ----------
    centers : numpy.ndarray
        ``(V, 2)`` lenslet centres (row, col), pixels, 0-based, in fgat's view order.
    lattice : HexLattice or None
        The hexagonal lattice fitted to the centres; ``None`` when they were not fitted.
    residuals : numpy.ndarray or None
        ``(V,)`` distance of each centre from its lattice point, pixels.
    gains : numpy.ndarray or None
        ``(V,)`` relative transmission of each view (vignetting, MLA transmission), max 1.
    camera : CameraModel or None
        Offset, read noise, hot pixels and pixel flat of the camera.
    depth_axis : {"up", "down"}
        Orientation of reconstructed volumes' Z axis (:data:`DEPTH_AXES`,
        :func:`orient_volume`).
    view_order : str
        Text describing fgat's view order (:data:`VIEW_ORDER`).
    source : str
        Image the calibration came from.
    gains_source, camera_source : str or None
        How the gains and the camera model were obtained (a flat or dark file, or estimated
        from the image).
    depth_scale : float or None
        Calibrated factor on the pupil phase per um of depth (:attr:`FLFMSystem.depth_scale
        <fgat.optics.systems.FLFMSystem>`), applied to the system by every command that reads
        this calibration; ``None``: not calibrated (the system's own).
    depth_scale_source : str or None
        Where ``depth_scale`` came from (the bead stack, positions, fit residual).
    """

    centers: np.ndarray
    lattice: HexLattice | None = None
    residuals: np.ndarray | None = None
    gains: np.ndarray | None = None
    camera: CameraModel | None = None
    depth_axis: str = "up"
    view_order: str = VIEW_ORDER
    source: str = ""
    gains_source: str | None = None
    camera_source: str | None = None
    depth_scale: float | None = None
    depth_scale_source: str | None = None

    def __post_init__(self) -> None:
        self.centers = np.asarray(self.centers, dtype=np.float64)
        if self.centers.ndim != 2 or self.centers.shape[1] != 2 or not len(self.centers):
            raise ValueError(f"centers must have shape (V, 2) (row, col), got {self.centers.shape}")
        for name in ("residuals", "gains"):
            value = getattr(self, name)
            if value is None:
                continue
            value = np.asarray(value, dtype=np.float64)
            if value.shape != (self.n_views,) or not np.isfinite(value).all() or value.min() < 0:
                raise ValueError(
                    f"{name} must be {self.n_views} finite non-negative values (one per view), "
                    f"got shape {value.shape}"
                )
            setattr(self, name, value)
        if self.depth_axis not in DEPTH_AXES:
            raise ValueError(
                f"depth_axis must be one of {list(DEPTH_AXES)}, got {self.depth_axis!r}"
            )
        if self.depth_scale is not None and not (
            isinstance(self.depth_scale, (int, float))
            and math.isfinite(self.depth_scale)
            and self.depth_scale > 0
        ):
            raise ValueError(f"depth_scale must be a positive number, got {self.depth_scale!r}")

    @property
    def n_views(self) -> int:
        """Number of views (lenslets) ``V``."""
        return len(self.centers)


def _view_windows(shape: tuple[int, int], centers: np.ndarray, size: int):
    """Slices of the ``size x size`` windows whose pixel ``(size // 2, size // 2)`` lies on
    ``round(centers)`` (the views of :meth:`fgat.optics.operator.FLFMOperator.views_from_sensor`);
    ``ValueError`` naming the view for a window off the sensor."""
    windows = []
    for view, (row, col) in enumerate(np.round(centers).astype(int) - size // 2):
        if row < 0 or col < 0 or row + size > shape[0] or col + size > shape[1]:
            raise ValueError(
                f"view {view}: a {size} x {size} window centred at {centers[view].tolist()} "
                f"does not fit on the {shape[0]} x {shape[1]} sensor"
            )
        windows.append((slice(row, row + size), slice(col, col + size)))
    return windows


def _offset_free(image, camera: CameraModel | None) -> tuple[np.ndarray, np.ndarray]:
    """The time-averaged image ``(H, W)`` corrected by ``camera`` (default: estimated from the
    image, :func:`~fgat.instrument.camera.camera_from_image`) and its valid-pixel mask ``(H,
    W)``."""
    frames = np.asarray(image, dtype=np.float64)
    if frames.ndim not in (2, 3) or not np.isfinite(frames).all():
        raise ValueError(f"expected a finite image (H, W) or frames (T, H, W), got {frames.shape}")
    camera = camera_from_image(frames) if camera is None else camera
    mean = camera.correct(frames.mean(axis=0) if frames.ndim == 3 else frames)
    return mean, camera.valid(mean.shape)


def _normalised(values: np.ndarray, what: str) -> np.ndarray:
    """``(V,)`` per-view values clipped at 0 and divided by their maximum."""
    values = np.clip(values, 0.0, None)
    if not values.max() > 0:
        raise ValueError(f"no view has light above the camera offset in the {what}")
    return values / values.max()


MIN_VIEW_GAIN = 0.05
"""Gain (relative to the brightest view) below which :func:`low_gain_warning` names a view: the
model then expects (almost) no light from it, right only for a blocked or missing lenslet;
vignetting the model does not know of dims an outer view by tens of per cent, not 20-fold."""


def low_gain_warning(gains: np.ndarray) -> str | None:
    """One line naming the views ``(V,)`` whose gain is below :data:`MIN_VIEW_GAIN`, or
    ``None``."""
    low = np.flatnonzero(np.asarray(gains) < MIN_VIEW_GAIN)
    if not len(low):
        return None
    values = ", ".join(f"view {int(v)}: {float(gains[v]):.3f}" for v in low)
    return (
        f"{len(low)} of {len(gains)} views get less than {MIN_VIEW_GAIN:g} of the brightest "
        f"view's light ({values}): the model expects (almost) no light from them; right for a "
        "blocked or missing lenslet, otherwise check the image and the lenslet count"
    )


def gains_from_flat(
    flat_image, centers, radius_px: float, camera: CameraModel | None = None
) -> np.ndarray:
    """Per-view gains ``(V,)`` (max 1) from a white-light image through the MLA.

    Each view's gain is its mean over a disk of ``radius_px`` around its centre, after offset
    removal (and flat-fielding) by ``camera`` (default: estimated from the image itself,
    :func:`~fgat.instrument.camera.camera_from_image`), hot pixels and pixels off the sensor left
    out. Choose the disk inside the lenslet's aperture image (e.g. 0.4 pitch for apertures filling
    the pitch), clear of its blurred border.

    Parameters
    ----------
    flat_image : array-like
        ``(H, W)`` or ``(T, H, W)`` (averaged) white-light image of the lenslet apertures,
        counts.
    centers : array-like
        ``(V, 2)`` lenslet centres (row, col), pixels, in view order.
    radius_px : float
        Radius of the averaging disk, pixels.
    camera : CameraModel, optional
        The camera (offset, hot pixels, pixel flat).
    """
    centers = np.asarray(centers, dtype=np.float64)
    if not radius_px > 0:
        raise ValueError(f"radius_px must be positive, got {radius_px!r}")
    image, valid = _offset_free(flat_image, camera)
    means = []
    for view, center in enumerate(centers):
        low = np.maximum(np.floor(center - radius_px).astype(int), 0)
        high = np.maximum(np.minimum(np.ceil(center + radius_px).astype(int) + 1, image.shape), low)
        rows, cols = np.mgrid[low[0] : high[0], low[1] : high[1]]
        disk = ((rows - center[0]) ** 2 + (cols - center[1]) ** 2 <= radius_px**2) * valid[
            low[0] : high[0], low[1] : high[1]
        ]
        if not disk.sum() > 0:
            raise ValueError(
                f"view {view}: no valid pixel within {radius_px:g} px of its centre "
                f"({center[0]:g}, {center[1]:g}) on the {image.shape[0]} x {image.shape[1]} sensor"
            )
        means.append((image[low[0] : high[0], low[1] : high[1]] * disk).sum() / disk.sum())
    return _normalised(np.array(means), "flat image")


def gains_from_image(
    image,
    centers,
    view_size: int,
    psf_energy=None,
    camera: CameraModel | None = None,
) -> np.ndarray:
    """Per-view gains ``(V,)`` (max 1) estimated from the fluorescence image itself.

    Every view sees the same sample, so its flux -- the sum over its ``view_size`` window
    after offset removal by ``camera`` (default: estimated from the image,
    :func:`~fgat.instrument.camera.camera_from_image`), hot pixels left out -- divided by the share
    of light the model gives it (``psf_energy``) is proportional to its gain. Valid when the
    sample lies inside every view's field (no light of a view falls outside its window, none
    of another view inside it).

    Parameters
    ----------
    image : array-like
        ``(H, W)`` or ``(T, H, W)`` (averaged) FLFM image, counts.
    centers : array-like
        ``(V, 2)`` lenslet centres (row, col), pixels, in view order.
    view_size : int
        Side of the square view windows, pixels (:func:`~fgat.optics.lenslets.largest_view_size`).
    psf_energy : array-like, optional
        ``(V,)`` fraction of a point's light that each view receives in the model with the
        lenslets on ``centers`` (:func:`view_psf_energy`; not the system's nominal lattice,
        which may put the outer lenses elsewhere in the pupil); default equal.
    camera : CameraModel, optional
        The camera (offset, hot pixels, pixel flat).
    """
    centers = np.asarray(centers, dtype=np.float64)
    if isinstance(view_size, bool) or not isinstance(view_size, (int, np.integer)) or view_size < 1:
        raise ValueError(f"view_size must be a positive integer, got {view_size!r}")
    image, valid = _offset_free(image, camera)
    flux = np.array(
        [
            (image[window] * valid[window]).sum()
            for window in _view_windows(image.shape, centers, view_size)
        ]
    )
    if psf_energy is not None:
        energy = np.asarray(psf_energy, dtype=np.float64)
        if energy.shape != (len(centers),) or not np.isfinite(energy).all() or energy.min() <= 0:
            raise ValueError(
                f"psf_energy must be {len(centers)} positive values (one per view), got "
                f"shape {energy.shape}"
            )
        flux = flux / energy
    return _normalised(flux, "image")


def save_calibration(calibration: Calibration, folder) -> dict[str, Path]:
    """Write ``centers.csv``, the camera's maps (:func:`~fgat.instrument.camera.write_camera`) and,
    last,
    ``calibration.yaml`` into the existing ``folder``, each atomically; returns the paths by
    name.

    ``calibration.yaml`` holds ``version`` (1), ``source``, ``n_views``, ``centers`` (the
    centres file), ``lattice`` (``center_px``, ``pitch_px``, ``rotation_deg``, or null),
    ``residuals_px`` and ``gains`` (``V`` values or null), ``gains_source``, ``camera``
    (``offset``, ``read_noise``, ``hot_pixels``, ``hot_pixel_count``, ``flat``, ``source``, or
    null), ``depth_axis``, ``view_order``, ``depth_scale`` (or null) and
    ``depth_scale_source``, after a comment block explaining them.
    """
    import yaml  # loaded when a file is read or written: keeps start-up fast

    folder = Path(folder)
    paths = {"centers.csv": folder / "centers.csv", CALIBRATION_FILE: folder / CALIBRATION_FILE}
    write_centers(paths["centers.csv"], calibration.centers)
    camera = None
    if calibration.camera is not None:
        camera = {**write_camera(calibration.camera, folder), "source": calibration.camera_source}
        for name in ("hot_pixels", "flat"):
            if camera[name] is not None:
                paths[camera[name]] = folder / camera[name]
    lattice = calibration.lattice
    record = {
        "version": CALIBRATION_VERSION,
        "source": calibration.source,
        "n_views": calibration.n_views,
        "centers": "centers.csv",
        "lattice": None
        if lattice is None
        else {
            "center_px": [float(v) for v in lattice.center],
            "pitch_px": float(lattice.pitch),
            "rotation_deg": float(lattice.rotation_deg),
        },
        "residuals_px": _listed(calibration.residuals),
        "gains": _listed(calibration.gains),
        "gains_source": calibration.gains_source,
        "camera": camera,
        "depth_axis": calibration.depth_axis,
        "view_order": calibration.view_order,
        "depth_scale": calibration.depth_scale,
        "depth_scale_source": calibration.depth_scale_source,
    }
    notes = [
        "fgat calibration (python -m fgat calibrate), read by "
        "fgat.instrument.calibration.read_calibration. centers: CSV of (row, col) pixels, 0-based, "
        "in fgat's view order (view_order). gains: relative transmission of each view (max 1). "
        "camera: offset and read_noise in counts; hot_pixels (uint8, 1 = defective) and flat "
        "(relative sensitivity) are (H, W) OME-TIFFs.",
        *(f"depth_axis {axis}: {text}." for axis, text in DEPTH_AXES.items()),
        "depth_scale: factor on the pupil phase per um of depth from a bead z-stack (python -m "
        "fgat calibrate-depth), null when not calibrated.",
    ]
    header = "".join(f"# {line}\n" for note in notes for line in textwrap.wrap(note, 96))
    with atomic_path(paths[CALIBRATION_FILE]) as temporary:
        temporary.write_text(header + yaml.safe_dump(record, sort_keys=False, width=100))
    return paths


def _listed(values: np.ndarray | None) -> list[float] | None:
    return None if values is None else [float(v) for v in values]


def _numbers(path: Path, name: str, values, count: int, what: str) -> np.ndarray:
    """``values`` as ``count`` finite non-negative floats; errors name the file and field."""
    if not isinstance(values, list) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in values
    ):
        raise ValueError(f"{path}: {name}: expected a list of {count} numbers, got {values!r}")
    array = np.asarray(values, dtype=np.float64)
    if len(array) != count:
        raise ValueError(
            f"{path}: {name}: {len(array)} values, but {what} has {count} lenslet centres"
        )
    if not np.isfinite(array).all() or array.min() < 0:
        raise ValueError(f"{path}: {name}: expected finite non-negative values, got {values}")
    return array


def _read_lattice(path: Path, record) -> HexLattice | None:
    if record is None:
        return None
    fields = ("center_px", "pitch_px", "rotation_deg")
    if not isinstance(record, dict) or set(record) != set(fields):
        raise ValueError(f"{path}: lattice: expected a mapping of {list(fields)} or null")
    center = record["center_px"]
    if not isinstance(center, list) or len(center) != 2:
        raise ValueError(f"{path}: lattice.center_px: expected [row, col], got {center!r}")
    return HexLattice(
        tuple(check_number(f"{path}: lattice.center_px", v) for v in center),
        check_number(f"{path}: lattice.pitch_px", record["pitch_px"], above=0),
        check_number(f"{path}: lattice.rotation_deg", record["rotation_deg"]),
    )


def read_calibration(folder) -> Calibration:
    """Read a calibration folder written by :func:`write_calibration` / ``python -m fgat
    calibrate``.

    Raises
    ------
    FileNotFoundError
        No folder, no ``calibration.yaml``, or a file it names is missing.
    ValueError
        A field is missing, unknown or invalid (the error names the file and the field), the
        centres file is invalid or not in fgat's view order, or ``gains`` / ``residuals_px``
        / ``n_views`` disagree with the number of centres.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"calibration folder {folder} does not exist")
    path = folder / CALIBRATION_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} does not exist: not a calibration folder of this fgat version (write one "
            "with 'python -m fgat calibrate', or pass its centers.csv)"
        )
    record = read_yaml(path, str(path))
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected a mapping of {list(CALIBRATION_FIELDS)}")
    unknown = sorted(set(record) - set(CALIBRATION_FIELDS))
    if unknown:
        raise ValueError(
            f"{path}: unknown field(s) {unknown}; expected some of {list(CALIBRATION_FIELDS)}"
        )
    missing = [name for name in ("version", "centers", "depth_axis") if name not in record]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing}")
    if record["version"] != CALIBRATION_VERSION:
        raise ValueError(
            f"{path}: version: expected {CALIBRATION_VERSION}, got {record['version']!r}"
        )
    if not isinstance(record["centers"], str):
        raise ValueError(f"{path}: centers: expected a file name, got {record['centers']!r}")
    centers_path = folder / record["centers"]
    if not centers_path.is_file():
        raise FileNotFoundError(f"{path}: centers: {centers_path} does not exist")
    centers = read_centers(centers_path)
    count = len(centers)
    n_views = record.get("n_views", count)
    if n_views != count:
        raise ValueError(
            f"{path}: n_views is {n_views!r}, but {centers_path.name} has {count} centres"
        )
    arrays = {
        name: None
        if record.get(key) is None
        else _numbers(path, key, record[key], count, centers_path.name)
        for name, key in (("residuals", "residuals_px"), ("gains", "gains"))
    }
    if arrays["gains"] is not None and not arrays["gains"].max() > 0:
        raise ValueError(f"{path}: gains: every view has gain 0")
    depth_axis = record["depth_axis"]
    if depth_axis not in DEPTH_AXES:
        raise ValueError(
            f"{path}: depth_axis: expected one of {list(DEPTH_AXES)}, got {depth_axis!r}"
        )
    depth_scale = record.get("depth_scale")
    if depth_scale is not None:
        depth_scale = check_number(f"{path}: depth_scale", depth_scale, above=0)
    texts = {}
    for name in ("source", "view_order", "gains_source", "depth_scale_source"):
        value = record.get(name)
        if value is not None and not isinstance(value, str):
            raise ValueError(f"{path}: {name}: expected text, got {value!r}")
        texts[name] = value
    camera_record = record.get("camera")
    camera_source = None
    if isinstance(camera_record, dict):
        camera_source = camera_record.get("source")
        if camera_source is not None and not isinstance(camera_source, str):
            raise ValueError(f"{path}: camera.source: expected text, got {camera_source!r}")
    camera = None if camera_record is None else read_camera(camera_record, folder, str(path))
    if camera is not None and camera.sensor_shape is not None:
        off = np.flatnonzero(
            (centers < 0).any(axis=1) | (centers >= np.array(camera.sensor_shape)).any(axis=1)
        )
        if len(off):
            raise ValueError(
                f"{path}: centre {int(off[0])} of {centers_path.name} lies outside the "
                f"{camera.sensor_shape[0]} x {camera.sensor_shape[1]} sensor of the camera maps"
            )
    return Calibration(
        centers=centers,
        lattice=_read_lattice(path, record.get("lattice")),
        residuals=arrays["residuals"],
        gains=arrays["gains"],
        camera=camera,
        depth_axis=depth_axis,
        view_order=VIEW_ORDER if texts["view_order"] is None else texts["view_order"],
        source=texts["source"] or "",
        gains_source=texts["gains_source"],
        camera_source=camera_source,
        depth_scale=depth_scale,
        depth_scale_source=texts["depth_scale_source"],
    )
