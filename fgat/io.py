"""Reading and writing images and volumes: TIFF / OME-TIFF, MATLAB ``.mat``, NumPy ``.npy``.

Every reader validates what it returns and names the file and what was wrong; every writer
writes to a temporary name in the target folder and renames it into place, so an interrupted
write never leaves a half-written file under the user's name.
"""

from __future__ import annotations

import contextlib
import functools
import glob
import json
import logging
import math
import os
import re
import tempfile
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from fgat.zarr_series import (
    VOLUME_ATTRIBUTE,
    ZarrSeriesWriter,
    is_zarr,
    open_image,
    read_zarr,
    write_zarr,
)

__all__ = [
    "atomic_path",
    "check_fields",
    "check_truth_shape",
    "choose_view_size",
    "check_number",
    "check_output_file",
    "check_writable_folder",
    "load_yaml",
    "read_image",
    "read_mat",
    "read_series",
    "read_tiff",
    "read_text",
    "read_time_interval",
    "read_voxel_size",
    "read_yaml",
    "series_frames",
    "simulation_view_size",
    "remove_stale_temporaries",
    "tiff_shape",
    "unique_key_loader",
    "validate_array",
    "volume_entries",
    "volume_metadata",
    "write_tiff",
    "write_zarr",
    "ZarrSeriesWriter",
    "yaml_fields",
]


def _temporary_pattern(path: Path) -> re.Pattern:
    """Names of :func:`atomic_path`'s temporaries for ``path``: ``.<name>.<pid>.<random>.part``."""
    return re.compile(rf"\.{re.escape(path.name)}\.(\d+)\.[A-Za-z0-9_]+\.part")


def _process_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (one of another user counts as alive). On Windows, where
    signal 0 would terminate the process, every PID counts as alive."""
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporaries that killed writers of ``path`` left behind (see :func:`atomic_path`);
    those of a live process, and every other file, are kept. Returns the removed paths."""
    path = Path(path)
    pattern = _temporary_pattern(path)
    removed = []
    for candidate in path.parent.glob(f".{glob.escape(path.name)}.*.part"):
        match = pattern.fullmatch(candidate.name)
        if match and int(match[1]) != os.getpid() and not _process_alive(int(match[1])):
            candidate.unlink(missing_ok=True)
            removed.append(candidate)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | Path, nbytes: int | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary is ``.<name>.<pid>.<random>.part`` in the target's folder, removed when the block
    fails; one that a killed process left (its PID no longer running) is removed by the next
    writer of the same target. With ``nbytes`` (the size about to be written) a disk without
    that much room is refused before writing (:func:`fgat.resources.check_disk_space`); a write
    that still runs out of room (``ENOSPC``, ``EDQUOT``) ends in one
    :class:`~fgat.resources.DiskFullError` naming ``path`` and the bytes needed, the temporary
    removed.
    """
    from fgat.resources import DISK_FULL_ERRNOS, check_disk_space, disk_full_error

    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise ValueError(f"cannot write {path}: it is a folder")
    remove_stale_temporaries(path)
    if nbytes is not None:
        check_disk_space(path, nbytes, what=f"cannot write {path}")
    try:
        handle, temporary = tempfile.mkstemp(
            prefix=f".{path.name}.{os.getpid()}.", suffix=".part", dir=path.parent
        )
    except OSError as error:
        if error.errno in DISK_FULL_ERRNOS:
            raise disk_full_error(path, error, nbytes) from None
        raise ValueError(
            f"cannot write {path}: folder {path.parent} is not writable ({error.strerror})"
        ) from None
    os.close(handle)
    temporary = Path(temporary)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield temporary
        temporary.chmod(0o666 & ~umask)  # mkstemp creates 0600; give the file the usual mode
        os.replace(temporary, path)
    except OSError as error:
        if error.errno in DISK_FULL_ERRNOS:
            raise disk_full_error(path, error, nbytes) from None
        raise
    finally:
        temporary.unlink(missing_ok=True)


def check_output_file(
    path: str | Path, *, overwrite: bool = False, option: str | None = None
) -> Path:
    """Check, before any computation, that ``path`` can be written; return it as a Path.

    Refused with one line naming ``option`` (e.g. ``"--out"``) and the path: a missing folder
    (``FileNotFoundError``), a path that is a folder, an existing file unless ``overwrite``, a
    folder where no file can be created (probed by creating and removing a temporary file, so
    that read-only file systems and permissions count even for root) (``ValueError``).
    """
    path = Path(path)
    name = f"{option} {path}" if option else str(path)
    folder = path.resolve().parent
    if not folder.is_dir():
        raise FileNotFoundError(f"{name}: folder {folder} does not exist")
    store = is_zarr(path)
    if path.is_dir() and not store:
        raise ValueError(f"{name}: is a folder; expected a file name (or a *.zarr store)")
    if path.exists() and path.suffix == ".zarr" and not store:
        raise ValueError(f"{name}: exists and is not a Zarr store; it is not replaced")
    if path.exists() and not overwrite:
        raise ValueError(
            f"{name}: the {'store' if store else 'file'} exists; choose another name or pass "
            "--overwrite to replace it"
        )
    check_writable_folder(folder, name)
    return path


def check_writable_folder(folder: str | Path, name: str | None = None) -> None:
    """Raise ``ValueError`` naming ``name`` (default: the folder) unless a file can be created in
    the existing ``folder`` (a real probe: create and remove a temporary file)."""
    try:
        handle, probe = tempfile.mkstemp(prefix=".fgat-probe-", dir=folder)
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        raise ValueError(
            f"{name or folder}: cannot write in folder {folder} ({error.strerror})"
        ) from None


def validate_array(
    array: np.ndarray,
    *,
    source: str,
    ndim: int | Sequence[int] | None = None,
    axes: str | None = None,
    nonnegative: bool = False,
) -> np.ndarray:
    """Check an array read from ``source``: dimensionality, finiteness and sign.

    Parameters
    ----------
    array : numpy.ndarray
        The data.
    source : str
        What to name in errors (a file, or a file and a field).
    ndim : int or sequence of int, optional
        Allowed numbers of dimensions.
    axes : str, optional
        Axis names for the error message, e.g. ``"(Z, Y, X)"``.
    nonnegative : bool
        Reject negative values (photon counts, intensities).
    """
    array = np.asarray(array)
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if array.ndim not in allowed:
            expected = " or ".join(f"{n}D" for n in allowed) + (f" {axes}" if axes else "")
            raise ValueError(
                f"{source}: expected {expected}, got {array.ndim}D data of shape {array.shape}"
            )
    if array.size == 0:
        raise ValueError(f"{source}: the data is empty (shape {array.shape})")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise ValueError(f"{source}: expected real numbers, got dtype {array.dtype}")
    if np.issubdtype(array.dtype, np.floating):
        bad = ~np.isfinite(array)
        if bad.any():
            raise ValueError(
                f"{source}: {int(bad.sum())} NaN/Inf value(s), first at index "
                f"{tuple(int(i) for i in np.argwhere(bad)[0])}"
            )
    if nonnegative and array.min() < 0:
        raise ValueError(
            f"{source}: expected non-negative values (intensities), minimum is {array.min()}"
        )
    return array


def check_number(
    name: str,
    value,
    *,
    minimum: float | None = None,
    above: float | None = None,
    maximum: float | None = None,
    integer: bool = False,
) -> float | int:
    """``value`` as a finite number within bounds, or one ``ValueError`` naming ``name``.

    Parameters
    ----------
    name : str
        What to call the value in the error (an option or a field).
    value
        A number, or text that reads as one.
    minimum, maximum : float, optional
        Inclusive bounds.
    above : float, optional
        Exclusive lower bound.
    integer : bool
        Require a whole number (``1e8`` is accepted as ``100000000``) and return an ``int``.
    """
    words = ["an integer" if integer else "a finite number"]
    if above is not None:
        words.append(f"> {above:g}")
    if minimum is not None and maximum is not None:
        words.append(f"in [{minimum:g}, {maximum:g}]")
    elif minimum is not None:
        words.append(f">= {minimum:g}")
    elif maximum is not None:
        words.append(f"<= {maximum:g}")
    try:
        number = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        number = math.nan
    valid = (
        math.isfinite(number)
        and (not integer or number.is_integer())
        and (above is None or number > above)
        and (minimum is None or number >= minimum)
        and (maximum is None or number <= maximum)
    )
    if not valid:
        raise ValueError(f"{name} must be {' '.join(words)}, got {value!r}")
    return int(number) if integer else number


def _require_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: not a file")
    return path


class _Warnings(logging.Handler):
    """Collects the messages of the warnings a logger emits."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())

    def damage(self) -> str | None:
        """The first message that reports a structure cut or broken (an offset past the end of
        the file, truncated or corrupted data), without tifffile's object names; ``None`` if
        none does (other warnings, such as unusual metadata, are not damage)."""
        for message in self.messages:
            if any(word in message.lower() for word in ("offset", "truncat", "corrupt", "eof")):
                return message.rsplit("> ", 1)[-1].strip("')\" ")
        return None


@contextlib.contextmanager
def _open_tiff(path: str | Path):
    """A ``tifffile.TiffFile`` of ``path`` whose structure is whole, or one ``ValueError`` naming
    the file: not a TIFF, or truncated or corrupt. tifffile reads a cut file as far as it can
    (the first pages, without the OME-XML written at its end) and only logs the bad offsets, so
    a truncated volume would pass for a 2D image without voxel size; here its warnings while
    the header is read, and a page whose data runs past the end of the file, refuse it."""
    import tifffile

    path = _require_file(path)
    logger = logging.getLogger("tifffile")
    collect, propagate = _Warnings(), logger.propagate
    logger.addHandler(collect)
    logger.propagate = False  # reported below in one line, not on the console
    try:
        try:
            tif = tifffile.TiffFile(path)
        except Exception as error:  # tifffile raises many types for damaged files
            raise unreadable_tiff(path, error) from None
        with tif:
            try:
                size = path.stat().st_size
                tif.series[0]  # noqa: B018 (parses the pages and the OME-XML)
                past_end = any(
                    offset + count > size
                    for page in tif.pages
                    for offset, count in zip(page.dataoffsets, page.databytecounts)
                )
            except Exception as error:  # tifffile raises many types for damaged files
                collect.messages.append(f"corrupt: {error}")
                past_end = False
            reason = collect.damage() or ("data past the end" if past_end else None)
            if reason is not None:
                raise ValueError(
                    f"{path}: the TIFF file is truncated or corrupt ({reason}); write or copy "
                    "it again"
                )
            yield tif
    finally:
        logger.removeHandler(collect)
        logger.propagate = propagate


def unreadable_tiff(path: Path, error: Exception) -> ValueError:
    """The one-line error for a file tifffile cannot parse."""
    return ValueError(f"{path}: not a readable TIFF file (truncated or corrupt?): {error}")


def tiff_shape(path: str | Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of the data :func:`read_tiff` would return, from the file's header only
    (a truncated or corrupt file is refused, :func:`_open_tiff`)."""
    with _open_tiff(path) as tif:
        series = tif.series[0]
        return tuple(int(n) for n in series.shape), np.dtype(series.dtype)


def read_tiff(
    path: str | Path,
    *,
    ndim: int | Sequence[int] | None = None,
    axes: str | None = None,
    nonnegative: bool = False,
) -> np.ndarray:
    """Read a TIFF or OME-TIFF file as a NumPy array, validated (see :func:`validate_array`); data
    larger than the available memory is refused from the header, before reading."""
    import tifffile

    from fgat.resources import check_memory

    shape, dtype = tiff_shape(path)
    check_memory(f"the {shape} {dtype} values of {path}", int(np.prod(shape)) * dtype.itemsize)
    try:
        array = tifffile.imread(path)
    except Exception as error:  # tifffile raises many types for damaged files
        raise unreadable_tiff(path, error) from None
    return validate_array(array, source=str(path), ndim=ndim, axes=axes, nonnegative=nonnegative)


def simulation_view_size(measurement: str | Path) -> int | None:
    """The ``view_size`` of the ``params.yaml`` written by ``python -m fgat simulate`` in the
    measurement's folder; ``None`` without one (a ``params.yaml`` of another program is ignored)."""
    params = Path(measurement).parent / "params.yaml"
    if not params.is_file():
        return None
    try:
        content = read_yaml(params, str(params))
    except ValueError:
        return None
    config = content.get("config") if isinstance(content, dict) else None
    size = config.get("view_size") if isinstance(config, dict) else None
    return size if isinstance(size, int) and size >= 1 else None


def choose_view_size(
    view_size: int | None,
    option: str,
    measurement: str | Path,
    truth: tuple[str | Path, tuple[int, ...]] | None,
    centers: np.ndarray,
    sensor_shape: tuple[int, int],
) -> tuple[int, str]:
    """The lateral size ``Y = X`` of the views and of the volume, pixels, and where it came from.

    In order: ``view_size`` (given as ``option``), the ``view_size`` of the simulation that wrote
    the measurement (:func:`simulation_view_size`), the lateral size of the ground truth, the
    largest square between the lenslet centres. A truth thus never sets the size of a measurement
    whose size is known; :func:`check_truth_shape` then refuses a truth of another size.

    Parameters
    ----------
    view_size : int or None
        The size the user gave.
    option : str
        Its name, for the origin (``"data.view_size"``, ``"--view-size"``).
    measurement : str or Path
        The sensor image (its folder may hold the simulation's ``params.yaml``).
    truth : (path, shape) or None
        The ground truth's file and shape ``(..., Y, X)``.
    centers : ndarray
        Lenslet centres ``(V, 2)``, pixels.
    sensor_shape : (int, int)
        Sensor ``(H, W)``, pixels.

    Returns
    -------
    size : int
        Pixels.
    origin : str
        E.g. ``"the simulation's sim/params.yaml"``.
    """
    from fgat.optics.lenslets import largest_view_size

    if view_size is not None:
        return view_size, option
    simulated = simulation_view_size(measurement)
    if simulated is not None:
        return simulated, f"the simulation's {Path(measurement).parent / 'params.yaml'}"
    if truth is not None:
        return truth[1][-1], f"the lateral size of the truth {truth[0]}"
    return largest_view_size(
        centers, sensor_shape
    ), "the largest square between the lenslet centres"


def check_truth_shape(
    source: str, path: str | Path, shape: tuple[int, ...], expected: tuple[int, ...], origin: str
) -> None:
    """Refuse a ground truth whose shape is not the reconstruction's, before anything is computed
    (a truth of another lateral size would otherwise resize the views it is compared with).

    Parameters
    ----------
    source : str
        How the truth was given (``"data.truth"``, ``"--truth"``).
    path : str or Path
        Its file.
    shape : tuple of int
        Its shape ``((T,) Z, Y, X)``.
    expected : tuple of int
        The reconstruction's ``((T,) Z, Y, X)``: frames, PSF depths, view size.
    origin : str
        Where the view size came from (:func:`choose_view_size`).

    Raises
    ------
    ValueError
        ``"--truth t.tif: shape (3, 32, 32) does not match the reconstruction (3, 64, 64) ..."``.
    """
    if tuple(shape) == tuple(expected):
        return
    raise ValueError(
        f"{source} {path}: shape {tuple(shape)} does not match the reconstruction "
        f"{tuple(expected)} (({'T, ' if len(expected) == 4 else ''}Z, Y, X): PSF depths, view "
        f"size {expected[-1]} px from {origin}); give the truth of this measurement, or set the "
        "view size to the truth's if its views are meant to be that size"
    )


def read_series(path: str | Path, ndim: int = 4) -> np.ndarray:
    """A series written with a leading time axis (``ndim`` dimensions, e.g. ``(T, Z, Y, X)``), from
    an OME-TIFF or an OME-Zarr store (:func:`write_zarr`), also when it holds one time point: TIFF
    readers drop singleton axes, so ``ndim - 1`` dimensions read back as ``T = 1``. A Zarr image is
    ``(T, C, Z, Y, X)``; with ``ndim=4`` it must hold one channel."""
    if is_zarr(path):
        array, _ = read_zarr(path)
        if ndim == 5:
            return array
        if ndim != 4 or array.shape[1] != 1:
            raise ValueError(
                f"{path}: a (T, C, Z, Y, X) image of {array.shape[1]} channels read as {ndim} "
                "dimensions; read it with ndim=5"
            )
        return array[:, 0]
    array = read_tiff(path, ndim=(ndim - 1, ndim))
    return array if array.ndim == ndim else array[None]


def series_frames(path: str | Path) -> tuple[int, Iterator[np.ndarray]]:
    """The number of time points of a ``(T, Z, Y, X)`` series (OME-TIFF, or a one-channel
    OME-Zarr image) and an iterator over its ``(Z, Y, X)`` volumes, each read when it is
    reached: memory holds one volume."""
    if is_zarr(path):
        array, _, _ = open_image(path)
        if array.shape[1] != 1:
            raise ValueError(f"{path}: {array.shape[1]} channels; expected a one-channel series")
        return array.shape[0], (np.asarray(array[t, 0]) for t in range(array.shape[0]))
    import tifffile

    shape, _ = tiff_shape(path)
    if len(shape) not in (3, 4):
        raise ValueError(f"{path}: a series of shape {shape}; expected (T, Z, Y, X) or (Z, Y, X)")
    frames, depth = (1, shape[0]) if len(shape) == 3 else shape[:2]

    def read(t: int) -> np.ndarray:
        with tifffile.TiffFile(path) as tif:
            return tif.asarray(key=range(t * depth, (t + 1) * depth)).reshape(shape[-3:])

    return frames, (read(t) for t in range(frames))


OME_LENGTH_UM = {"pm": 1e-6, "Å": 1e-4, "nm": 1e-3, "µm": 1.0, "μm": 1.0, "um": 1.0}
OME_LENGTH_UM |= {"mm": 1e3, "cm": 1e4, "m": 1e6}
"""Micrometres per OME-TIFF length unit (``PhysicalSize{X,Y,Z}Unit``; OME's default is µm)."""
NGFF_LENGTH_UM = {
    "picometer": 1e-6,
    "angstrom": 1e-4,
    "nanometer": 1e-3,
    "micrometer": 1.0,
    "millimeter": 1e3,
    "centimeter": 1e4,
    "meter": 1e6,
}
"""Micrometres per OME-Zarr (NGFF) axis unit; an axis without a unit is taken in um."""


def _length_um(path, field: str, value, unit: str | None, units: dict[str, float]) -> float:
    """``value`` in ``unit`` as micrometres; an unknown unit is refused naming the file and
    field."""
    if unit is None:
        return float(value)
    if unit not in units:
        raise ValueError(f"{path}: {field} is in {unit!r}, expected one of {', '.join(units)}")
    return float(value) * units[unit]


def read_voxel_size(path: str | Path) -> dict[str, float]:
    """Physical sizes stored in an OME-TIFF or an OME-Zarr image, converted to micrometres from
    the units the file names (:data:`OME_LENGTH_UM`, :data:`NGFF_LENGTH_UM`), as ``{"Z": dz,
    "Y": dy, "X": dx}`` (those present).

    Raises
    ------
    ValueError
        A size in a unit that is not a length (or not known), naming the file and field.
    """
    if is_zarr(path):
        _, entry, _ = open_image(path)
        scale = entry["datasets"][0]["coordinateTransformations"][0]["scale"]
        units = [axis.get("unit") if isinstance(axis, dict) else None for axis in entry["axes"]]
        return {
            name: _length_um(path, f"axis {name.lower()} unit", size, unit, NGFF_LENGTH_UM)
            for name, size, unit in zip("ZYX", scale[-3:], units[-3:])
        }
    pixels = _ome_pixels(path)
    return {
        axis: _length_um(
            path,
            f"PhysicalSize{axis}Unit",
            pixels[f"PhysicalSize{axis}"],
            pixels.get(f"PhysicalSize{axis}Unit"),
            OME_LENGTH_UM,
        )
        for axis in "ZYX"
        if pixels.get(f"PhysicalSize{axis}") is not None
    }


TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "µs": 1e-6, "min": 60.0, "h": 3600.0}
"""Seconds per OME ``TimeIncrementUnit``."""


def read_time_interval(path: str | Path) -> float | None:
    """Seconds between the time points of an OME-TIFF (``TimeIncrement``) or OME-Zarr image
    (the t axis' scale when its unit is seconds); ``None`` when the file does not say."""
    if is_zarr(path):
        _, entry, _ = open_image(path)
        if (entry["axes"][0] or {}).get("unit") != "second":
            return None
        return float(entry["datasets"][0]["coordinateTransformations"][0]["scale"][0])
    pixels = _ome_pixels(path)
    increment, unit = pixels.get("TimeIncrement"), pixels.get("TimeIncrementUnit", "s")
    if increment is None or unit not in TIME_UNITS_S:
        return None
    return float(increment) * TIME_UNITS_S[unit]


def _ome_pixels(path: str | Path) -> dict[str, str]:
    """The attributes of the first OME ``Pixels`` element of a TIFF (empty without OME-XML)."""
    with _open_tiff(path) as tif:
        xml = tif.ome_metadata
    if not xml:
        return {}
    for element in ElementTree.fromstring(xml).iter():
        if element.tag.endswith("Pixels"):
            return dict(element.attrib)
    return {}


VOLUME_NAMESPACE = "fgat.volume"
"""Namespace of the OME ``MapAnnotation`` that holds :func:`volume_entries` in fgat's files."""
VOLUME_KEYS = ("depth_axis", "depth_axis_convention", "depths_um", "view_order")
"""The entries of :func:`volume_entries` and :func:`volume_metadata`."""


def volume_entries(
    depth_axis: str = "up", depths_um: Sequence[float] | None = None
) -> dict[str, object]:
    """What a volume file tells another tool about its axes: fgat's depth-axis convention and the
    lenslet view order (:data:`fgat.optics.calibration.DEPTH_AXES`, ``VIEW_ORDER``).

    Parameters
    ----------
    depth_axis : {"up", "down"}
        Orientation of the volume's Z axis as written
        (:func:`fgat.optics.calibration.orient_volume`).
    depths_um : sequence of float, optional
        ``(Z,)`` depth in um (relative to the native focal plane, positive away from the
        objective) of every Z index of the volume as written: for ``"down"`` the PSF planes'
        list reversed. ``None``: not known (a PSF file that does not record them).

    Returns
    -------
    dict
        ``depth_axis`` (str), ``depth_axis_convention`` (its sentence), ``depths_um`` (list of
        float, or ``None``) and ``view_order`` (the sentence); the ``metadata`` of
        :func:`write_tiff`, read back by :func:`volume_metadata`.
    """
    from fgat.optics.calibration import DEPTH_AXES, VIEW_ORDER

    if depth_axis not in DEPTH_AXES:
        raise ValueError(f"depth_axis must be one of {list(DEPTH_AXES)}, got {depth_axis!r}")
    if depths_um is not None:
        depths_um = [float(depth) for depth in depths_um]
        if not depths_um or not all(math.isfinite(depth) for depth in depths_um):
            raise ValueError(f"depths_um must be finite numbers, one per Z index, got {depths_um}")
    return {
        "depth_axis": depth_axis,
        "depth_axis_convention": DEPTH_AXES[depth_axis],
        "depths_um": depths_um,
        "view_order": VIEW_ORDER,
    }


def volume_metadata(path: str | Path) -> dict[str, object]:
    """The :func:`volume_entries` an OME-TIFF (see :func:`write_tiff`) or OME-Zarr image (see
    :func:`write_zarr`) written by fgat records.

    Returns
    -------
    dict
        ``depth_axis``, ``depth_axis_convention``, ``depths_um`` (list of float in the order of
        the Z index, um, or ``None`` when not recorded) and ``view_order``; ``{}`` for a file
        without fgat's annotation (another tool's, or written before fgat recorded it).

    Raises
    ------
    ValueError
        Not a readable file, or damaged entries; the message names ``path``.
    """
    from fgat.optics.calibration import DEPTH_AXES

    if is_zarr(path):
        _, _, attributes = open_image(path)
        stored = attributes.get(VOLUME_ATTRIBUTE, {})
    else:
        stored = _tiff_entries(path)
    if not stored:
        return {}
    entries = {key: stored.get(key) for key in VOLUME_KEYS}
    depths = entries["depths_um"]
    try:
        if depths is not None:
            listed = json.loads(depths) if isinstance(depths, str) else depths
            entries["depths_um"] = [float(depth) for depth in listed]
    except (TypeError, ValueError):
        raise ValueError(f"{path}: depths_um {depths!r} is not a list of numbers") from None
    if entries["depth_axis"] not in DEPTH_AXES:
        raise ValueError(
            f"{path}: depth_axis must be one of {list(DEPTH_AXES)}, got {entries['depth_axis']!r}"
        )
    return entries


def _tiff_entries(path: str | Path) -> dict[str, str]:
    """The text entries of fgat's OME ``MapAnnotation`` in a TIFF (``{}`` without one)."""
    with _open_tiff(path) as tif:
        xml = tif.ome_metadata
    if not xml:
        return {}
    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError as error:
        raise ValueError(f"{path}: damaged OME-XML metadata: {error}") from None
    for element in root.iter():
        if element.tag.endswith("MapAnnotation") and element.get("Namespace") == VOLUME_NAMESPACE:
            return {
                pair.get("K"): pair.text or ""
                for pair in element.iter()
                if pair.tag.rsplit("}", 1)[-1] == "M"
            }
    return {}


def write_tiff(
    path: str | Path,
    array,
    *,
    axes: str | None = None,
    voxel_size_um: Sequence[float] | None = None,
    metadata: Mapping[str, object] | None = None,
    time_interval_s: float | None = None,
) -> Path:
    """Write an array as OME-TIFF, atomically.

    Parameters
    ----------
    path : str or Path
        Target file (``.ome.tif`` recommended).
    array : array-like
        Data; float64 is stored as float32. Always grey levels: a last axis of 3 or 4 is an axis
        of the data, never RGB(A) samples.
    axes : str, optional
        OME axis letters, e.g. ``"ZYX"`` or ``"VZYX"`` (non-OME letters are stored as ``Q``);
        defaults to the last ``ndim`` letters of ``"TCZYX"``.
    voxel_size_um : sequence of float, optional
        Physical sizes of the last axes in micrometres: ``(dz, dy, dx)`` or ``(dy, dx)``.
    metadata : mapping, optional
        A volume's :func:`volume_entries`, stored as an OME ``MapAnnotation`` (namespace
        :data:`VOLUME_NAMESPACE`, text values, lists as JSON, ``None`` left out) that
        :func:`volume_metadata` reads back; ``depths_um`` must hold one depth per Z index.
    time_interval_s : float, optional
        Seconds between time points (OME ``TimeIncrement``; :func:`read_time_interval`).
    """
    import tifffile

    data = np.asarray(array)
    if data.dtype == np.float64:
        data = data.astype(np.float32)
    axes = axes or "TCZYX"[-data.ndim :]
    if len(axes) != data.ndim:
        raise ValueError(f"axes {axes!r} do not match the {data.ndim}D array of shape {data.shape}")
    ome: dict[str, object] = {"axes": "".join(a if a in "TCZYXS" else "Q" for a in axes)}
    if voxel_size_um is not None:
        for axis, size in zip(reversed(axes), reversed(tuple(voxel_size_um))):
            ome[f"PhysicalSize{axis}"] = float(size)
            ome[f"PhysicalSize{axis}Unit"] = "µm"
    if time_interval_s is not None:
        ome["TimeIncrement"], ome["TimeIncrementUnit"] = float(time_interval_s), "s"
    if metadata:
        depths = metadata.get("depths_um")
        if depths is not None and ("Z" not in axes or len(depths) != data.shape[axes.index("Z")]):
            raise ValueError(
                f"cannot write {path}: {len(depths)} depths_um for the Z axis of the "
                f"{axes} array of shape {data.shape}"
            )
        ome["MapAnnotation"] = {
            "Namespace": VOLUME_NAMESPACE,
            "Value": {
                key: value if isinstance(value, str) else json.dumps(value)
                for key, value in metadata.items()
                if value is not None
            },
        }
    ome["UUID"] = content_uuid(data, ome)
    path = Path(path)
    with atomic_path(path, data.nbytes) as temporary:
        tifffile.imwrite(temporary, data, ome=True, metadata=ome, photometric="minisblack")
    return path


def content_uuid(data: np.ndarray, metadata: Mapping[str, object]) -> str:
    """An OME ``urn:uuid`` drawn from the data (values, shape, dtype) and the metadata, so that
    writing the same volume twice gives the same file: a run keyed on its input files' contents
    (:mod:`fgat.fingerprint`) is not redone because its input was written again."""
    import hashlib
    import uuid

    digest = hashlib.blake2b(digest_size=16)
    digest.update(json.dumps([data.shape, data.dtype.str, metadata], sort_keys=True).encode())
    digest.update(np.ascontiguousarray(data).data)
    return uuid.UUID(bytes=digest.digest(), version=4).urn


def write_csv(path: str | Path, columns: Sequence[str], rows) -> Path:
    """Write a table as CSV, atomically: a header of ``columns``, then one line per row (a
    mapping, read at ``columns``, or a sequence in that order)."""
    import csv
    from collections.abc import Mapping

    path = Path(path)
    with atomic_path(path) as temporary, temporary.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        writer.writerows(
            [row[c] for c in columns] if isinstance(row, Mapping) else row for row in rows
        )
    return path


def write_json(path: str | Path, data: Mapping[str, object]) -> Path:
    """Write ``data`` as indented JSON, atomically; NaN and infinite floats (at any depth of
    its lists) as ``null``, which strict JSON readers accept."""

    def plain(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, (list, tuple)):
            return [plain(item) for item in value]
        return value

    path = Path(path)
    text = json.dumps({k: plain(v) for k, v in data.items()}, indent=2) + "\n"
    with atomic_path(path, len(text.encode())) as temporary:
        temporary.write_text(text)
    return path


def read_mat(path: str | Path, key: str | None = None) -> np.ndarray:
    """Read one array from a MATLAB ``.mat`` file (v5; v7.3 needs ``h5py``).

    ``key`` names the variable; when omitted the file must hold exactly one.
    """
    import scipy.io

    path = _require_file(path)
    try:
        contents = scipy.io.loadmat(path)
    except NotImplementedError:
        raise ValueError(
            f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7"
        ) from None
    except Exception as error:
        raise ValueError(f"{path}: not a readable MATLAB file: {error}") from None
    names = [name for name in contents if not name.startswith("__")]
    if key is None:
        if len(names) != 1:
            raise ValueError(f"{path}: holds variables {names}; name the one to read")
        key = names[0]
    if key not in contents:
        raise ValueError(f"{path}: no variable {key!r}; it holds {names}")
    return validate_array(contents[key], source=f"{path}:{key}")


def read_image(
    path: str | Path,
    *,
    ndim: int | Sequence[int] | None = None,
    axes: str | None = None,
    nonnegative: bool = False,
    key: str | None = None,
) -> np.ndarray:
    """Read a TIFF/OME-TIFF, ``.mat`` or ``.npy`` file by its extension, validated."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        return read_tiff(path, ndim=ndim, axes=axes, nonnegative=nonnegative)
    if suffix == ".mat":
        array = read_mat(path, key)
    elif suffix == ".npy":
        try:
            array = np.load(_require_file(path), allow_pickle=False)
        except (OSError, ValueError) as error:
            raise ValueError(f"{path}: not a readable .npy file: {error}") from None
    else:
        raise ValueError(
            f"{path}: unsupported file type {suffix!r}; expected .tif, .tiff, .mat or .npy"
        )
    return validate_array(array, source=str(path), ndim=ndim, axes=axes, nonnegative=nonnegative)


@functools.cache
def unique_key_loader() -> type:
    """The :class:`yaml.SafeLoader` subclass every YAML read of fgat uses: a mapping that gives a
    key twice is refused (a ``yaml.constructor.ConstructorError`` naming the key and both lines)
    instead of keeping the last value silently. Built on first use, so importing :mod:`fgat.io`
    does not import PyYAML."""
    import yaml
    from yaml.constructor import ConstructorError

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                first: dict = {}  # key -> its first line (0-based); merged keys (<<) may be
                for key_node, _ in node.value:  # overridden, as YAML allows: not checked
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    try:
                        seen = key in first
                    except TypeError:
                        continue  # an unhashable key: SafeLoader's own error follows
                    if seen:
                        raise ConstructorError(
                            None,
                            None,
                            f"duplicate key {key!r} at line {key_node.start_mark.line + 1} "
                            f"(first given at line {first[key] + 1}); give each key once",
                            key_node.start_mark,
                        )
                    first[key] = key_node.start_mark.line
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def load_yaml(text: str, source: str) -> object:
    """The YAML document of ``text``, read by :func:`unique_key_loader` (safe
    tags only; a key given twice in a mapping is an error); invalid YAML is one ``ValueError``
    naming ``source`` with the line and column (:func:`describe_yaml_error`)."""
    import yaml

    try:
        return yaml.load(text, Loader=unique_key_loader())  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as error:
        raise ValueError(f"{source}: {describe_yaml_error(error)}") from None


def read_text(path: str | Path, source: str | None = None) -> str:
    """The UTF-8 text of the file ``path``; a file that is not UTF-8 text (binary, or another
    encoding) is one ``ValueError`` naming ``source`` (default the path) and the first bad
    byte."""
    path = Path(path)
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise ValueError(
            f"{source or path}: not a UTF-8 text file (byte 0x{data[error.start]:02x} at offset "
            f"{error.start}); expected YAML text"
        ) from None


def yaml_fields(text: str, source: str, schema, *, extra: tuple[str, ...] = ()) -> dict:
    """Parse YAML ``text`` into a dict of the fields of dataclass ``schema`` (and the keys
    ``extra``), naming ``source`` (a file, a preset) in every error: invalid YAML, a key given
    twice, not a mapping, unknown fields."""
    fields = load_yaml(text, source)
    fields = {} if fields is None else fields
    if not isinstance(fields, dict):
        raise ValueError(f"{source}: expected a mapping of {schema.__name__} fields")
    check_fields(source, schema, fields, extra=extra)
    return fields


def check_fields(source: str, schema, fields: dict | None, *, extra: tuple[str, ...] = ()) -> None:
    """Raise ``ValueError`` naming ``source`` and the valid keys when ``fields`` has a key that is
    neither a constructor field of dataclass ``schema`` nor one of ``extra``."""
    import dataclasses

    known = {f.name for f in dataclasses.fields(schema) if f.init} | set(extra)
    unknown = sorted(set(fields or {}) - known)
    if unknown:
        raise ValueError(f"{source}: unknown field(s) {unknown}; expected some of {sorted(known)}")


def read_yaml(path: str | Path, source: str) -> object:
    """The YAML document of the file ``path``; a missing file, one that is not UTF-8 text, invalid
    YAML or a key given twice is one error naming ``source`` (e.g. ``"config runs.yaml"``) with
    the line and column (:func:`describe_yaml_error`, :func:`load_yaml`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{source} does not exist")
    return load_yaml(read_text(path, source), source)


def check_config_files(words: Sequence[str]) -> None:
    """Every ``--config`` (``-c``) of command-line ``words`` must be a readable YAML file, or a
    YAML mapping given inline: a missing file or a syntax error is one error naming the file,
    the line and the column (:func:`read_yaml`; a key given twice names both lines), raised
    before any heavy import or computation, and before jsonargparse, which would keep the
    last value of a repeated key silently.
    """
    for index, word in enumerate(words):
        if word in ("--config", "-c") and index + 1 < len(words):
            path = words[index + 1]
        elif word.startswith("--config="):
            path = word.split("=", 1)[1]
        else:
            continue
        if not Path(path).is_file():
            try:
                if isinstance(load_yaml(path, "--config"), dict):
                    continue  # the options themselves, as jsonargparse accepts them
            except ValueError:
                pass
        read_yaml(path, f"--config {path}")


def describe_yaml_error(error) -> str:
    """One line for a PyYAML error: where (line and column, 1-based) and what, e.g. ``"invalid YAML
    at line 3, column 1: expected ',' or '}', but got '<scalar>' (while parsing a flow mapping
    started at line 2, column 10)"``."""
    mark = getattr(error, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    context = getattr(error, "context", None)
    context_mark = getattr(error, "context_mark", None)
    if context and context_mark is not None:
        context += f" started at line {context_mark.line + 1}, column {context_mark.column + 1}"
    return f"invalid YAML{where}: {problem}" + (f" ({context})" if context else "")


def parse_values(spec, what: str = "value", *, distinct: bool = False) -> list[float]:
    """Finite numbers from a list, ``"-30,0,30"``, or ``"start:stop:count"`` (inclusive, evenly
    spaced); ``distinct`` also refuses a value given twice. Errors name ``what`` and ``spec``."""
    ranged = isinstance(spec, str) and len(spec.split(":")) == 3
    try:
        if ranged:
            start, stop, count = spec.split(":")
            start, stop, count = float(start), float(stop), int(count)
        else:
            values = [
                float(v)
                for v in (spec.split(",") if isinstance(spec, str) else spec)
                if not isinstance(v, str) or v.strip()
            ]
    except (TypeError, ValueError):
        raise ValueError(
            f"{what}s {spec!r}: expected numbers (a,b,c) or start:stop:count"
        ) from None
    if ranged:
        if count < 1:
            raise ValueError(f"{what} count must be positive in {spec!r}")
        values = np.linspace(start, stop, count).tolist() if count > 1 else [start]
    if not all(np.isfinite(values)):
        raise ValueError(f"{what}s {spec!r}: every {what} must be a finite number")
    if distinct and len(set(values)) != len(values):
        repeated = sorted({v for v in values if values.count(v) > 1})
        raise ValueError(f"{what}s {spec!r}: {what} {repeated[0]:g} is given more than once")
    return values


def parse_scalar(text: str):
    """A command-line scalar: ``"50"`` -> 50, ``"1e-3"`` -> 0.001, ``"false"`` -> False,
    ``"null"`` -> None; anything else stays text."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    if lowered in ("null", "none", "~"):
        return None
    for convert in (int, float):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


def parse_overrides(value):
    """Apply :func:`parse_scalar` to every string inside nested dicts and lists (config dicts
    whose entries were overridden on the command line arrive as text)."""
    if isinstance(value, str):
        return parse_scalar(value)
    if isinstance(value, dict):
        return {
            parse_overrides(key)
            if isinstance(key, str) and key.isdigit()
            else key: parse_overrides(item)
            for key, item in value.items()
        }
    if isinstance(value, (list, tuple)):
        return type(value)(parse_overrides(item) for item in value)
    return value


def coerce_fields(instance) -> None:
    """Give a dataclass's fields the type of their defaults when set from text.

    Command-line overrides of a config dict arrive as strings (``"50"``, ``"false"``); they are
    read with :func:`parse_scalar` and cast to the default's type (int, float, bool). A value that
    does not convert (text, a boolean for a number or a number for a boolean, a fraction for an
    integer, NaN or infinity) raises ``ValueError`` naming the field. ``None`` is left alone.
    """
    import dataclasses

    for field in dataclasses.fields(instance):
        default = field.default
        value = getattr(instance, field.name)
        if (
            not field.init
            or default is dataclasses.MISSING
            or not isinstance(default, (bool, int, float))
        ):
            continue
        if isinstance(value, str):
            value = parse_scalar(value)
        if value is None:
            setattr(instance, field.name, None)
            continue
        expected = {bool: "true or false", int: "an integer", float: "a finite number"}[
            type(default)
        ]
        if isinstance(default, bool) != isinstance(value, bool):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        if isinstance(default, int) and isinstance(value, float) and not value.is_integer():
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        try:
            converted = type(default)(value)
        except (TypeError, ValueError):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}") from None
        setattr(instance, field.name, converted)


def require(ok: bool, field: str, value, expected: str) -> None:
    """Raise ``ValueError("<field> must be <expected>, got <value>")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"{field} must be {expected}, got {value!r}")


def require_positive(prefix: str, **values: float) -> None:
    """Every value finite and > 0 (learning rates, scales)."""
    for name, value in values.items():
        require(
            math.isfinite(value) and value > 0,
            f"{prefix}.{name}".lstrip("."),
            value,
            "a positive number",
        )


def require_non_negative(prefix: str, **values: float) -> None:
    """Every value finite and >= 0 (loss weights, iteration counts)."""
    for name, value in values.items():
        require(
            math.isfinite(value) and value >= 0,
            f"{prefix}.{name}".lstrip("."),
            value,
            "a non-negative number",
        )
