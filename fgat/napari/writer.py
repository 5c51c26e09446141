"""napari's writer of an image layer as an OME-TIFF with fgat's metadata (the
``fgat.write_volume`` command of ``napari.yaml``).

A layer that :mod:`fgat.napari.reader` opened is written back as the file it came from was: the
same voxel sizes (the layer's ``scale``), seconds between time points, fgat's entries (depths,
view order, what it holds) and depth-axis order (a ``down`` file read as ``up`` is flipped back),
so that reading the written file gives the same data, scale, translate and metadata. Any other
layer is written with the sizes of its axes in micrometres (none when they are in pixels) and, in
micrometres, the depths of its z axis from its ``translate``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from fgat._core.conventions import orient_volume
from fgat.io.images import volume_entries, write_tiff

LENGTHS_UM = {"micrometer": 1.0, "um": 1.0, "µm": 1.0, "nanometer": 1e-3, "millimeter": 1e3}
"""Micrometres per unit of a layer's spatial axis (napari's unit names and their short forms)."""
SECONDS = {"second": 1.0, "s": 1.0, "millisecond": 1e-3, "ms": 1e-3, "minute": 60.0}
"""Seconds per unit of a layer's time axis."""


def write_volume(path: str, data, meta: Mapping) -> list[str]:
    """Write one image layer (napari's single-layer writer: ``data`` and the layer's state
    ``meta``) as an OME-TIFF at ``path``.

    Parameters
    ----------
    path : str
        Target file (``.ome.tif``).
    data : array-like
        ``(Z, Y, X)``, ``(T, Z, Y, X)`` or, for a PSF stack (``content: psf`` in the layer's fgat
        metadata), ``(V, Z, h, w)``.
    meta : mapping
        The layer's ``scale``, ``translate``, ``units``, ``axis_labels`` and ``metadata`` (as
        :mod:`fgat.napari.reader` sets it: ``fgat`` entries, ``recorded_depth_axis``).

    Returns
    -------
    list of str
        ``[path]``.

    Raises
    ------
    ValueError
        Data that is not a 3-D or 4-D grey-level image, or a 4-D layer whose first axis is
        neither time nor a PSF view; one line naming the layer.
    """
    layer = meta.get("name", "the layer")
    if meta.get("rgb"):
        raise ValueError(f"cannot write {layer!r} as a volume: it is an RGB image")
    array = np.asarray(data)
    if array.ndim not in (3, 4) or not np.issubdtype(array.dtype, np.number):
        raise ValueError(
            f"cannot write {layer!r} as a volume: {array.ndim}-D {array.dtype} data of shape "
            f"{array.shape}; expected (Z, Y, X), (T, Z, Y, X) or a PSF stack (V, Z, h, w)"
        )
    metadata = dict(meta.get("metadata") or {})
    fgat = dict(metadata.get("fgat") or {})
    content = fgat.get("content", "volume")
    labels = tuple(meta.get("axis_labels") or ())
    if array.ndim == 4 and content != "psf" and labels and labels[0] not in ("t", "time"):
        raise ValueError(
            f"cannot write {layer!r} as a volume: its first axis {labels[0]!r} is neither time "
            "(t) nor a PSF stack's view"
        )
    scale = _floats(meta.get("scale"), array.ndim)
    translate = _floats(meta.get("translate"), array.ndim, 0.0)
    units = [str(unit) for unit in (meta.get("units") or ["pixel"] * array.ndim)]
    voxel = [
        None if unit not in LENGTHS_UM else size * LENGTHS_UM[unit]
        for size, unit in zip(scale[-3:], units[-3:])
    ]
    shown = fgat.get("depths_um")
    if shown is None or len(shown) != array.shape[-3]:
        shown = (
            None
            if voxel[0] is None
            else [
                translate[-3] * LENGTHS_UM[units[-3]] + k * voxel[0] for k in range(array.shape[-3])
            ]
        )
    recorded = metadata.get("recorded_depth_axis", "up")
    if fgat.get("depth_axis", "up") != "up":  # a layer not shown up: written as it is
        recorded = fgat["depth_axis"]
    elif recorded == "down":  # shown flipped to up: back to the file's order
        array = orient_volume(array, "down")
        shown = None if shown is None else list(shown)[::-1]
    interval = None
    if array.ndim == 4 and content != "psf" and units[0] in SECONDS:
        interval = scale[0] * SECONDS[units[0]]
    axes = ("CZYX" if content == "psf" else "TZYX") if array.ndim == 4 else "ZYX"
    write_tiff(
        path,
        array,
        axes=axes,
        voxel_size_um=None if None in voxel else voxel,
        metadata=volume_entries(recorded, shown, content=content),
        time_interval_s=interval,
    )
    return [str(Path(path))]


def _floats(values, ndim: int, default: float = 1.0) -> list[float]:
    """The last ``ndim`` of ``values`` as floats (``default`` for each when absent)."""
    if values is None:
        return [default] * ndim
    values = [float(value) for value in values]
    return ([default] * ndim + values)[-ndim:]
