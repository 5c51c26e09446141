"""Reading and writing images and volumes: TIFF / OME-TIFF, MATLAB ``.mat``, NumPy ``.npy``.

Every reader validates what it returns and names the file and what was wrong; every writer
writes to a temporary name in the target folder and renames it into place, so an interrupted
write never leaves a half-written file under the user's name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

__all__ = ["atomic_path", "read_image", "read_mat", "read_tiff", "read_voxel_size", "validate_array",
           "write_tiff", "yaml_fields"]


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds."""
    path = Path(path)
    if not path.parent.exists():
        raise FileNotFoundError(f"cannot write {path}: folder {path.parent} does not exist")
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(handle)
    temporary = Path(temporary)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield temporary
        temporary.chmod(0o666 & ~umask)  # mkstemp creates 0600; give the file the usual mode
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def validate_array(array: np.ndarray, *, source: str, ndim: int | Sequence[int] | None = None,
                   axes: str | None = None, nonnegative: bool = False) -> np.ndarray:
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
            raise ValueError(f"{source}: expected {expected}, got {array.ndim}D data of shape {array.shape}")
    if array.size == 0:
        raise ValueError(f"{source}: the data is empty (shape {array.shape})")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise ValueError(f"{source}: expected real numbers, got dtype {array.dtype}")
    if np.issubdtype(array.dtype, np.floating):
        bad = ~np.isfinite(array)
        if bad.any():
            raise ValueError(f"{source}: {int(bad.sum())} NaN/Inf value(s), first at index "
                             f"{tuple(int(i) for i in np.argwhere(bad)[0])}")
    if nonnegative and array.min() < 0:
        raise ValueError(f"{source}: expected non-negative values (intensities), minimum is {array.min()}")
    return array


def _require_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: not a file")
    return path


def read_tiff(path: str | Path, *, ndim: int | Sequence[int] | None = None, axes: str | None = None,
              nonnegative: bool = False) -> np.ndarray:
    """Read a TIFF or OME-TIFF file as a NumPy array, validated (see :func:`validate_array`)."""
    import tifffile

    path = _require_file(path)
    try:
        array = tifffile.imread(path)
    except Exception as error:  # tifffile raises many types for damaged files
        raise ValueError(f"{path}: not a readable TIFF file (truncated or damaged?): {error}") from None
    return validate_array(array, source=str(path), ndim=ndim, axes=axes, nonnegative=nonnegative)


def read_series(path: str | Path, ndim: int = 4) -> np.ndarray:
    """A series written with a leading time axis (``ndim`` dimensions, e.g. ``(T, Z, Y, X)``), also
    when it holds one time point: TIFF readers drop singleton axes, so ``ndim - 1`` dimensions read
    back as ``T = 1``."""
    array = read_tiff(path, ndim=(ndim - 1, ndim))
    return array if array.ndim == ndim else array[None]


def read_voxel_size(path: str | Path) -> dict[str, float]:
    """Physical sizes (um) stored in an OME-TIFF, as ``{"Z": dz, "Y": dy, "X": dx}`` (those present)."""
    import tifffile

    path = _require_file(path)
    with tifffile.TiffFile(path) as tif:
        xml = tif.ome_metadata
    if not xml:
        return {}
    sizes = {}
    for element in ElementTree.fromstring(xml).iter():
        if element.tag.endswith("Pixels"):
            for axis in "ZYX":
                value = element.get(f"PhysicalSize{axis}")
                if value is not None:
                    sizes[axis] = float(value)
            break
    return sizes


def write_tiff(path: str | Path, array, *, axes: str | None = None,
               voxel_size_um: Sequence[float] | None = None) -> Path:
    """Write an array as OME-TIFF, atomically.

    Parameters
    ----------
    path : str or Path
        Target file (``.ome.tif`` recommended).
    array : array-like
        Data; float64 is stored as float32.
    axes : str, optional
        OME axis letters, e.g. ``"ZYX"`` or ``"VZYX"`` (non-OME letters are stored as ``Q``);
        defaults to the last ``ndim`` letters of ``"TCZYX"``.
    voxel_size_um : sequence of float, optional
        Physical sizes of the last axes in micrometres: ``(dz, dy, dx)`` or ``(dy, dx)``.
    """
    import tifffile

    data = np.asarray(array)
    if data.dtype == np.float64:
        data = data.astype(np.float32)
    axes = axes or "TCZYX"[-data.ndim:]
    if len(axes) != data.ndim:
        raise ValueError(f"axes {axes!r} do not match the {data.ndim}D array of shape {data.shape}")
    metadata: dict[str, object] = {"axes": "".join(a if a in "TCZYXS" else "Q" for a in axes)}
    if voxel_size_um is not None:
        for axis, size in zip(reversed(axes), reversed(tuple(voxel_size_um))):
            metadata[f"PhysicalSize{axis}"] = float(size)
            metadata[f"PhysicalSize{axis}Unit"] = "µm"
    path = Path(path)
    with atomic_path(path) as temporary:
        tifffile.imwrite(temporary, data, ome=True, metadata=metadata)
    return path


def write_csv(path: str | Path, columns: Sequence[str], rows) -> Path:
    """Write a table as CSV, atomically: a header of ``columns``, then one line per row (a
    mapping, read at ``columns``, or a sequence in that order)."""
    import csv
    from collections.abc import Mapping

    path = Path(path)
    with atomic_path(path) as temporary, temporary.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        writer.writerows([row[c] for c in columns] if isinstance(row, Mapping) else row for row in rows)
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
        raise ValueError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7") from None
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


def read_image(path: str | Path, *, ndim: int | Sequence[int] | None = None, axes: str | None = None,
               nonnegative: bool = False, key: str | None = None) -> np.ndarray:
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
        raise ValueError(f"{path}: unsupported file type {suffix!r}; expected .tif, .tiff, .mat or .npy")
    return validate_array(array, source=str(path), ndim=ndim, axes=axes, nonnegative=nonnegative)


def yaml_fields(text: str, source: str, schema) -> dict:
    """Parse YAML ``text`` into a dict of the fields of dataclass ``schema``, naming ``source``
    (a file, a preset) in every error: invalid YAML, not a mapping, unknown fields."""
    import dataclasses

    import yaml

    try:
        fields = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ValueError(f"{source}: not valid YAML ({error})") from None
    fields = {} if fields is None else fields
    if not isinstance(fields, dict):
        raise ValueError(f"{source}: expected a mapping of {schema.__name__} fields")
    known = {f.name for f in dataclasses.fields(schema)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ValueError(f"{source}: unknown field(s) {unknown}; expected some of {sorted(known)}")
    return fields


def parse_values(spec, what: str = "value") -> list[float]:
    """Numbers from a list, ``"-30,0,30"``, or ``"start:stop:count"`` (inclusive, evenly spaced)."""
    if isinstance(spec, str):
        parts = spec.split(":")
        if len(parts) == 3:
            start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
            if count < 1:
                raise ValueError(f"{what} count must be positive in {spec!r}")
            return np.linspace(start, stop, count).tolist() if count > 1 else [start]
        return [float(v) for v in spec.split(",") if v.strip()]
    return [float(v) for v in spec]


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
        return {parse_overrides(key) if isinstance(key, str) and key.isdigit() else key: parse_overrides(item)
                for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(parse_overrides(item) for item in value)
    return value


def coerce_fields(instance) -> None:
    """Give a dataclass's fields the type of their defaults when set from text.

    Command-line overrides of a config dict arrive as strings (``"50"``, ``"false"``); they are
    read with :func:`parse_scalar` and cast to the default's type (int, float, bool). A value that
    does not convert raises ``ValueError`` naming the field. ``None`` is left alone.
    """
    import dataclasses

    for field in dataclasses.fields(instance):
        default = field.default
        value = getattr(instance, field.name)
        if not field.init or default is dataclasses.MISSING or not isinstance(default, (bool, int, float)):
            continue
        if isinstance(value, str):
            value = parse_scalar(value)
        if value is None:
            setattr(instance, field.name, None)
            continue
        expected = {bool: "true or false", int: "an integer", float: "a number"}[type(default)]
        if isinstance(default, bool) and not isinstance(value, bool):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        try:
            converted = type(default)(value)
        except (TypeError, ValueError):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}") from None
        setattr(instance, field.name, converted)
