"""napari's reader for what fgat writes (the ``fgat.get_reader`` command of ``napari.yaml``).

Every output opens as layers placed in the sample's coordinates: ``scale`` and ``translate`` in
micrometres (seconds for a series' time axis when the file records its interval, else frames),
with ``axis_labels`` and ``units``, so that the viewer's z coordinate is the depth in um relative
to the native focal plane (:func:`fgat.io.images.volume_entries`) and z grows the same way in
every layer: a volume recorded with ``depth_axis: down`` is shown flipped to ``up`` (a reversed
view, nothing is copied), as its metadata says.

============================  =============================================================
what                          layers
============================  =============================================================
volume / series OME-TIFF      one image ``(Z, Y, X)`` or ``(T, Z, Y, X)``; channels
                              ``(T, C, Z, Y, X)`` split into one additive layer each
PSF stack OME-TIFF            one image ``(view, z, y, x)``, the view order in its metadata
OME-Zarr store (fgat's)       as a series, opened lazily (dask over the zarr chunks), one
                              layer per channel named as the store names them
calibration folder            the image it was made from (when found), the lenslet centres as
                              points numbered in fgat's view order, the hexagonal lattice's
                              cells as shapes
results folder of a fit       the reconstruction, the SHB baseline and the truth (phantoms)
                              as aligned images
============================  =============================================================

Anything else (another tool's TIFF or OME-Zarr, a folder of other files, a damaged file) is
declined (``get_reader`` returns ``None``) from its header alone, so napari offers it to other
readers. The layers are built by pure functions that return napari's ``LayerData`` tuples
``(data, kwargs, layer_type)`` without importing napari.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from fgat._core.conventions import DEPTH_AXES
from fgat.io.images import read_time_interval, read_voxel_size, volume_metadata
from fgat.io.zarr_series import VOLUME_ATTRIBUTE, channel_name, is_zarr, open_image

LayerData = tuple[object, dict, str]
"""napari's ``(data, kwargs, layer_type)``."""

CALIBRATION_FILE = "calibration.yaml"  # fgat.instrument.calibration.CALIBRATION_FILE
RESIDUAL_FILE = "residual.json"  # fgat.app.report.RESIDUAL_FILE (a fit's results folder)
# Those modules load PyTorch; napari asks this reader about every file it opens.
RESULT_VOLUMES = (
    ("volume.ome.tif", "reconstruction", "green"),
    ("volumes.ome.tif", "reconstruction series", "green"),
    ("volumes.ome.zarr", "reconstruction series", "green"),
    ("shb.ome.tif", "SHB baseline", "magenta"),
    ("truth.ome.tif", "ground truth", "gray"),
)
"""A fit's results folder: file, what its layer is named, colormap."""
CHANNEL_COLORMAPS = ("green", "magenta", "cyan", "yellow", "red", "blue")
"""Colormaps of a store's channels, in channel order (repeated past six)."""
UNITS = {"um": "micrometer", "s": "second", None: "pixel"}
"""Units of the layers' axes as napari names them (a view axis, or frames, in ``pixel``)."""


def get_reader(path: str | Sequence[str]) -> Callable[[str | Sequence[str]], list] | None:
    """The reader of ``path`` (or of every path of a list) when fgat wrote it, else ``None``.

    Decided from headers and folder contents only: the OME-TIFF's fgat annotation
    (:func:`fgat.io.images.volume_metadata`), the OME-Zarr group's ``fgat.volume`` attribute,
    ``calibration.yaml``, or ``residual.json`` beside a fit's volume; never raises.
    """
    paths = [path] if isinstance(path, (str, Path)) else list(path)
    if not paths or any(identify(item) is None for item in paths):
        return None
    return read


def read(path: str | Sequence[str]) -> list[LayerData]:
    """The layers of one path or of each of a list (see the module's table)."""
    paths = [path] if isinstance(path, (str, Path)) else list(path)
    layers = []
    for item in paths:
        kind = identify(item)
        if kind is None:
            raise ValueError(f"{item}: not a file or folder fgat wrote")
        layers += READERS[kind](Path(item))
    return layers


def identify(path: str | Path) -> str | None:
    """What fgat output ``path`` is: ``"volume"`` or ``"psf"`` (an OME-TIFF), ``"zarr"``,
    ``"calibration"`` or ``"results"`` (folders); ``None`` for anything else, also a missing,
    unreadable or damaged path."""
    try:
        return _identify(Path(path))
    except Exception:  # noqa: BLE001 (a foreign or damaged file of any kind is declined)
        return None


def _identify(path: Path) -> str | None:
    if path.is_dir():
        if is_zarr(path):
            return "zarr" if VOLUME_ATTRIBUTE in open_image(path)[2] else None
        if (path / CALIBRATION_FILE).is_file():
            return "calibration"
        if (path / RESIDUAL_FILE).is_file() and any(
            identify(path / name) is not None for name, _, _ in RESULT_VOLUMES[:3]
        ):
            return "results"
        return None
    if path.is_file() and path.name.lower().endswith((".tif", ".tiff")):
        entries = volume_metadata(path)
        return entries["content"] if entries else None
    return None


# ---------------------------------------------------------------- layers of arrays (pure)
def image_layers(
    data,
    axes: str,
    entries: dict,
    *,
    voxel_size_um: Sequence[float | None],
    name: str,
    path: str,
    kind: str,
    time_interval_s: float | None = None,
    channel_names: Sequence[str] | None = None,
    colormap: str = "gray",
) -> list[LayerData]:
    """napari image layers of an array whose dimensions are ``axes`` (letters of ``"tcvzyx"``:
    time, channel, PSF view, depth, rows, columns), as fgat records them.

    Parameters
    ----------
    data : array-like
        NumPy, memory-mapped, zarr or dask array; a zarr array becomes a dask array (read chunk by
        chunk when shown).
    axes : str
        The dimensions of ``data``, e.g. ``"zyx"``, ``"tczyx"``, ``"vzyx"``.
    entries : dict
        fgat's :func:`~fgat.io.images.volume_metadata` of the file. With ``depth_axis: down``
        the z axis is reversed (lazily) and shown ``up``, its depths listed in that order.
    voxel_size_um : (dz, dy, dx)
        um per voxel; ``None`` for a size the file does not record (1, in pixels).
    name, path, kind : str
        Layer name, the file it came from and what it is (in the metadata).
    time_interval_s : float, optional
        Seconds between time points (the t axis in frames without it).
    channel_names : sequence of str, optional
        Names of the channels of a ``c`` axis (default ``"channel c"``); each channel becomes
        one additive layer (napari's ``channel_axis``) named ``"<name> <channel name>"``.
    colormap : str
        Colormap of a layer without channels.

    Returns
    -------
    list of LayerData
        One tuple ``(data, kwargs, "image")``; ``kwargs`` holds ``name``, ``scale``,
        ``translate`` (z: the depth of the first plane shown, um, so the z coordinate is the
        depth; 0 when the depths are not recorded), ``axis_labels``, ``units``, ``colormap``,
        ``blending`` and ``metadata`` (``fgat``: the entries as shown; ``recorded_depth_axis``,
        ``path``, ``kind``, ``voxel_size_um``, ``time_interval_s``), and ``channel_axis`` with
        per-channel lists for a ``c`` axis.
    """
    if len(axes) != np.ndim(data) or set(axes) - set("tcvzyx") or not axes.endswith("zyx"):
        raise ValueError(f"{path}: axes {axes!r} for data of shape {np.shape(data)}")
    if _is_zarr_array(data):
        import dask.array  # loaded when a store is opened: napari brings dask

        data = dask.array.from_zarr(data)
    entries = dict(entries)
    recorded = entries.get("depth_axis", "up")
    depths = entries.get("depths_um")
    if recorded == "down":
        data = data[(slice(None),) * (len(axes) - 3) + (slice(None, None, -1),)]
        depths = None if depths is None else depths[::-1]
        entries.update(
            depth_axis="up",
            depths_um=depths,
            depth_axis_convention=DEPTH_AXES["up"],
        )
    sizes = dict(zip("zyx", voxel_size_um))
    scale, translate, units, labels = [], [], [], []
    for axis in axes.replace("c", ""):
        if axis == "t":
            scale.append(1.0 if time_interval_s is None else float(time_interval_s))
            units.append(UNITS[None if time_interval_s is None else "s"])
        elif axis == "v":
            scale.append(1.0)
            units.append(UNITS[None])
        else:
            size = sizes[axis]
            scale.append(1.0 if size is None else float(size))
            units.append(UNITS[None if size is None else "um"])
        translate.append(float(depths[0]) if axis == "z" and depths else 0.0)
        labels.append({"v": "view"}.get(axis, axis))
    metadata = {
        "fgat": entries,
        "recorded_depth_axis": recorded,
        "path": path,
        "kind": kind,
        "voxel_size_um": tuple(voxel_size_um),
        "time_interval_s": time_interval_s,
    }
    if recorded == "down":
        metadata["shown"] = "the z axis reversed from the file's 'down' order to 'up'"
    kwargs = {
        "name": name,
        "scale": tuple(scale),
        "translate": tuple(translate),
        "axis_labels": tuple(labels),
        "units": tuple(units),
        "colormap": colormap,
        "blending": "additive",
        "metadata": metadata,
    }
    if "c" not in axes:
        return [(data, kwargs, "image")]
    count = np.shape(data)[axes.index("c")]
    channel_names = list(channel_names or [channel_name(c) for c in range(count)])
    per_channel = {
        "name": [f"{name} {channel}" for channel in channel_names],
        "colormap": [CHANNEL_COLORMAPS[c % len(CHANNEL_COLORMAPS)] for c in range(count)],
        "blending": ["additive"] * count,
        "metadata": [{**metadata, "channel": channel} for channel in channel_names],
    }
    for key in ("scale", "translate", "axis_labels", "units"):
        per_channel[key] = [kwargs[key]] * count
    return [(data, {**per_channel, "channel_axis": axes.index("c")}, "image")]


def _is_zarr_array(data) -> bool:
    return type(data).__module__.split(".")[0] == "zarr"


def points_layer(centers: np.ndarray, *, name: str, metadata: dict) -> LayerData:
    """A points layer of lenslet centres ``(V, 2)`` (row, col) in pixels, each labelled with its
    view index (fgat's view order)."""
    centers = np.asarray(centers, dtype=np.float64)
    views = np.arange(len(centers))
    kwargs = {
        "name": name,
        "features": {"view": views},
        "text": {"string": "{view}", "color": "yellow", "anchor": "upper_left"},
        "face_color": "yellow",
        "size": 3.0,
        "axis_labels": ("y", "x"),
        "units": (UNITS[None],) * 2,
        "metadata": metadata,
    }
    return (centers, kwargs, "points")


def lattice_layer(cells: np.ndarray, *, name: str, metadata: dict) -> LayerData:
    """A shapes layer of the lattice's hexagonal cells ``(V, 6, 2)`` (row, col), pixels: one
    polygon per view, in view order."""
    cells = np.asarray(cells, dtype=np.float64)
    kwargs = {
        "name": name,
        "shape_type": "polygon",
        "edge_color": "cyan",
        "face_color": "transparent",
        "edge_width": 0.5,
        "features": {"view": np.arange(len(cells))},
        "axis_labels": ("y", "x"),
        "units": (UNITS[None],) * 2,
        "metadata": metadata,
    }
    return (list(cells), kwargs, "shapes")


# ---------------------------------------------------------------- files and folders
def tiff_layers(path: Path, *, name: str | None = None, colormap: str = "gray") -> list[LayerData]:
    """The layer(s) of an OME-TIFF of fgat's: a volume or series (``content: volume``) or a PSF
    stack (``content: psf``, axes ``(view, z, y, x)``)."""
    entries = volume_metadata(path)
    data, letters = _tiff_data(path)
    axes = letters.lower()
    if entries["content"] == "psf":
        axes = axes.replace("c", "v")
    axes = axes.replace("q", "v")
    sizes = read_voxel_size(path)
    return image_layers(
        data,
        axes,
        entries,
        voxel_size_um=tuple(sizes.get(axis) for axis in "ZYX"),
        name=name or _stem(path),
        path=str(path),
        kind=entries["content"],
        time_interval_s=read_time_interval(path) if "t" in axes else None,
        colormap=colormap,
    )


def _tiff_data(path: Path):
    """The data of a TIFF (memory-mapped when its pages are stored contiguously, as fgat writes
    them: nothing is read until shown) and its axis letters."""
    import tifffile  # loaded when a file is read: keeps start-up fast

    with tifffile.TiffFile(path) as tif:
        series = tif.series[0]
        shape, letters = tuple(series.shape), series.axes
    try:
        data = tifffile.memmap(path, mode="r")
    except ValueError:  # compressed or scattered pages
        data = tifffile.imread(path)
    return data.reshape(shape), letters


def zarr_layers(path: Path, *, name: str | None = None, colormap: str = "gray") -> list[LayerData]:
    """The layer(s) of fgat's OME-Zarr image ``(T, C, Z, Y, X)``: lazy; one channel shown as a
    ``(T, Z, Y, X)`` layer, several as one layer per channel named by the store's
    ``omero.channels[c].label``."""
    array, entry, attributes = open_image(path)
    entries = volume_metadata(path)
    sizes = read_voxel_size(path)
    channels = [
        channel.get("label", channel_name(c))
        for c, channel in enumerate(attributes.get("omero", {}).get("channels", []))
    ]
    import dask.array  # loaded when a store is opened: napari brings dask

    data, axes = dask.array.from_zarr(array), "tczyx"
    if array.shape[1] == 1:
        data, axes = data[:, 0], "tzyx"
    return image_layers(
        data,
        axes,
        entries,
        voxel_size_um=tuple(sizes.get(axis) for axis in "ZYX"),
        name=name or _stem(path),
        path=str(path),
        kind="volume",
        time_interval_s=read_time_interval(path),
        channel_names=channels if len(channels) == array.shape[1] else None,
        colormap=colormap,
    )


def calibration_layers(folder: Path) -> list[LayerData]:
    """A calibration folder: the image it was made from (``source``, found as given, relative
    to the working folder, to the calibration folder or to its parent; no layer when none is
    there, as the points' metadata says), its centres (points, numbered in view order) and its
    lattice's hexagonal cells (shapes; none when the centres were not fitted), in pixels."""
    from fgat.instrument.calibration import (  # loaded when used: it loads PyTorch
        read_calibration,
    )
    from fgat.io.images import read_tiff  # loaded when used: keeps start-up fast

    calibration = read_calibration(folder)
    source = find_source(folder, calibration.source)
    metadata = {
        "kind": "calibration",
        "path": str(folder),
        "source": calibration.source,
        "source_found": None if source is None else str(source),
        "view_order": calibration.view_order,
        "depth_axis": calibration.depth_axis,
    }
    layers = []
    if source is not None:
        image = read_tiff(source, ndim=(2, 3))
        axes = ("t", "y", "x")[-image.ndim :]
        kwargs = {
            "name": f"{folder.name}: {source.name}",
            "colormap": "gray",
            "axis_labels": axes,
            "units": (UNITS[None],) * image.ndim,
            "metadata": {**metadata, "kind": "calibration image"},
        }
        layers.append((image, kwargs, "image"))
    else:
        metadata["note"] = (
            f"the calibration's image {calibration.source!r} was not found (as given, or "
            f"relative to {Path.cwd()}, {folder} or {folder.parent}): no image layer"
        )
    lattice = calibration.lattice
    centres = {**metadata, "kind": "lenslet centres", "lattice": _lattice_record(lattice)}
    layers.append(
        points_layer(calibration.centers, name=f"{folder.name}: lenslet centres", metadata=centres)
    )
    if lattice is not None:
        layers.append(
            lattice_layer(
                lattice.cells(calibration.n_views),
                name=f"{folder.name}: lenslet lattice",
                metadata={**metadata, "kind": "lenslet lattice", "lattice": centres["lattice"]},
            )
        )
    return layers


def _lattice_record(lattice) -> dict | None:
    if lattice is None:
        return None
    return {
        "center_px": [float(v) for v in lattice.center],
        "pitch_px": float(lattice.pitch),
        "rotation_deg": float(lattice.rotation_deg),
    }


def find_source(folder: Path, source: str) -> Path | None:
    """The calibration image ``source`` (as the user typed it): as given (absolute, or relative
    to the working folder), else relative to the calibration ``folder`` or to its parent, else
    by its name in either; ``None`` when none of them is a file."""
    if not source:
        return None
    given = Path(source)
    candidates = [given, folder / given, folder.parent / given]
    candidates += [folder / given.name, folder.parent / given.name]
    return next((path for path in candidates if path.is_file()), None)


def results_layers(folder: Path) -> list[LayerData]:
    """A fit's results folder: the reconstruction (``volume.ome.tif``, or the dynamic stage's
    ``volumes.ome.tif`` / ``.ome.zarr``), the SHB baseline and the truth, each written on the
    scene's grid (so with the same scale and translate), named ``"<what> (<run>)"`` with the
    first 8 characters of the folder's name (the MLflow run id)."""
    layers = []
    for file, label, colormap in RESULT_VOLUMES:
        path = folder / file
        kind = identify(path)
        if kind is None:
            continue
        name = f"{label} ({folder.name[:8]})"
        read_layers = zarr_layers if kind == "zarr" else tiff_layers
        for data, kwargs, layer_type in read_layers(path, name=name, colormap=colormap):
            kwargs["metadata"] = {**kwargs["metadata"], "results": str(folder), "role": label}
            layers.append((data, kwargs, layer_type))
    return layers


def _stem(path: Path) -> str:
    """``path``'s name without ``.ome.tif`` / ``.ome.zarr`` (and the like)."""
    name = path.name
    for suffix in (".ome.tiff", ".ome.tif", ".ome.zarr", ".tiff", ".tif", ".zarr"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


READERS = {
    "volume": tiff_layers,
    "psf": tiff_layers,
    "zarr": zarr_layers,
    "calibration": calibration_layers,
    "results": results_layers,
}
"""The layers of each kind of :func:`identify`."""
