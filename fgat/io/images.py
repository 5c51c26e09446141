"""Images and volumes on disk: OME-TIFF (with fgat's volume metadata, voxel sizes and
time intervals), MAT files and the dispatch to OME-Zarr series.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import uuid
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from fgat._core.conventions import DEPTH_AXES, VIEW_ORDER
from fgat._core.resources import check_memory
from fgat._core.validation import validate_array
from fgat.io.files import atomic_path, require_file
from fgat.io.zarr_series import VOLUME_ATTRIBUTE, is_zarr, open_image, read_zarr


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
    import tifffile  # loaded when a file is read or written: keeps start-up fast

    path = require_file(path)
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
    import tifffile  # loaded when a file is read or written: keeps start-up fast

    shape, dtype = tiff_shape(path)
    check_memory(f"the {shape} {dtype} values of {path}", int(np.prod(shape)) * dtype.itemsize)
    try:
        array = tifffile.imread(path)
    except Exception as error:  # tifffile raises many types for damaged files
        raise unreadable_tiff(path, error) from None
    return validate_array(array, source=str(path), ndim=ndim, axes=axes, nonnegative=nonnegative)


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
    import tifffile  # loaded when a file is read or written: keeps start-up fast

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
VOLUME_KEYS = ("content", "depth_axis", "depth_axis_convention", "depths_um", "view_order")
"""The entries of :func:`volume_entries` and :func:`volume_metadata`."""
CONTENTS = {
    "volume": "a volume (Z, Y, X) or a series of volumes (T, [C,] Z, Y, X)",
    "psf": "a PSF stack (V, Z, h, w): view v's image of a point on the axis at depths_um[k]",
}
"""What a file of fgat's holds (the ``content`` entry); a file without one holds a volume (fgat
wrote none before PSF stacks carried the annotation)."""


def volume_entries(
    depth_axis: str = "up", depths_um: Sequence[float] | None = None, content: str = "volume"
) -> dict[str, object]:
    """What a volume or PSF file tells another tool about its axes: what it holds, fgat's
    depth-axis convention and the lenslet view order (:data:`fgat._core.conventions.DEPTH_AXES`,
    ``VIEW_ORDER``).

    Parameters
    ----------
    depth_axis : {"up", "down"}
        Orientation of the volume's Z axis as written
        (:func:`fgat._core.conventions.orient_volume`).
    depths_um : sequence of float, optional
        ``(Z,)`` depth in um (relative to the native focal plane, positive away from the
        objective) of every Z index of the volume as written: for ``"down"`` the PSF planes'
        list reversed. ``None``: not known (a PSF file that does not record them).
    content : {"volume", "psf"}
        What the file holds (:data:`CONTENTS`).

    Returns
    -------
    dict
        ``content`` (str), ``depth_axis`` (str), ``depth_axis_convention`` (its sentence),
        ``depths_um`` (list of float, or ``None``) and ``view_order`` (the sentence); the
        ``metadata`` of :func:`write_tiff`, read back by :func:`volume_metadata`.
    """
    if content not in CONTENTS:
        raise ValueError(f"content must be one of {list(CONTENTS)}, got {content!r}")
    if depth_axis not in DEPTH_AXES:
        raise ValueError(f"depth_axis must be one of {list(DEPTH_AXES)}, got {depth_axis!r}")
    if depths_um is not None:
        depths_um = [float(depth) for depth in depths_um]
        if not depths_um or not all(math.isfinite(depth) for depth in depths_um):
            raise ValueError(f"depths_um must be finite numbers, one per Z index, got {depths_um}")
    return {
        "content": content,
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
        ``content`` (``"volume"`` when not recorded, :data:`CONTENTS`), ``depth_axis``,
        ``depth_axis_convention``, ``depths_um`` (list of float in the order of the Z index, um,
        or ``None`` when not recorded) and ``view_order``; ``{}`` for a file without fgat's
        annotation (another tool's, or written before fgat recorded it).

    Raises
    ------
    ValueError
        Not a readable file, or damaged entries; the message names ``path``.
    """
    if is_zarr(path):
        _, _, attributes = open_image(path)
        stored = attributes.get(VOLUME_ATTRIBUTE, {})
    else:
        stored = _tiff_entries(path)
    if not stored:
        return {}
    entries = {key: stored.get(key) for key in VOLUME_KEYS}
    entries["content"] = entries["content"] or "volume"
    if entries["content"] not in CONTENTS:
        raise ValueError(
            f"{path}: content must be one of {list(CONTENTS)}, got {entries['content']!r}"
        )
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
    import tifffile  # loaded when a file is read or written: keeps start-up fast

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
    (:mod:`fgat.app.fingerprint`) is not redone because its input was written again."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(json.dumps([data.shape, data.dtype.str, metadata], sort_keys=True).encode())
    digest.update(np.ascontiguousarray(data).data)
    return uuid.UUID(bytes=digest.digest(), version=4).urn


def read_mat(path: str | Path, key: str | None = None) -> np.ndarray:
    """Read one array from a MATLAB ``.mat`` file (v5; v7.3 needs ``h5py``).

    ``key`` names the variable; when omitted the file must hold exactly one.
    """
    import scipy.io  # SciPy loaded when used: keeps start-up fast

    path = require_file(path)
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
            array = np.load(require_file(path), allow_pickle=False)
        except (OSError, ValueError) as error:
            raise ValueError(f"{path}: not a readable .npy file: {error}") from None
    else:
        raise ValueError(
            f"{path}: unsupported file type {suffix!r}; expected .tif, .tiff, .mat or .npy"
        )
    return validate_array(array, source=str(path), ndim=ndim, axes=axes, nonnegative=nonnegative)
