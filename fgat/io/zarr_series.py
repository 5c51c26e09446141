"""Volume series as OME-Zarr (NGFF 0.4): axes t, c, z, y, x, written one frame at a time.

A series of ``T`` volumes of ``C`` channels is one image of shape ``(T, C, Z, Y, X)`` chunked
per time point and channel (one chunk is one volume), with the physical scale of each axis
(micrometres, and seconds between frames when known) in its ``multiscales`` metadata, so that
napari (napari-ome-zarr), ome-zarr-py and Fiji read it as a 5-D image. A writer holds one frame
in memory, however long the series; the store is built under a temporary name beside the target
and renamed onto it when complete, so a failed or killed write leaves nothing under the target's
name. :func:`fgat.io.images.read_series` reads it back, as it reads OME-TIFF.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from fgat._core.resources import DISK_FULL_ERRNOS, disk_full_error

AXES = "tczyx"
VOLUME_ATTRIBUTE = "fgat.volume"  # the group attribute holding fgat.io.images.volume_entries
NGFF_VERSION = "0.4"
DATASET = "0"  # the single resolution level's array


def is_zarr(path: str | Path) -> bool:
    """Whether ``path`` is a Zarr store (a folder holding Zarr metadata) or, when nothing is
    there yet, is named like one (``*.zarr``)."""
    path = Path(path)
    if not path.exists():
        return path.suffix == ".zarr"
    return path.is_dir() and any((path / name).exists() for name in (".zgroup", "zarr.json"))


def channel_name(index: int) -> str:
    """The name of channel ``index`` of the data when nothing names it otherwise."""
    return f"channel {index}"


def ngff_metadata(
    voxel_size_um: Sequence[float],
    time_interval_s: float | None,
    name: str,
    channel_names: Sequence[str],
) -> dict[str, object]:
    """The ``multiscales`` attribute of a ``(T, C, Z, Y, X)`` image (axes with their types and
    units, and the scale of the one dataset: seconds per frame, 1 per channel, um per voxel) and
    its ``omero`` attribute naming the channels (``channels[c].label``, as NGFF viewers show
    them)."""
    units = {"t": "second", "z": "micrometer", "y": "micrometer", "x": "micrometer"}
    types = {"t": "time", "c": "channel"}
    if time_interval_s is None:
        del units["t"]  # frames, not seconds
    axes = [{"name": axis, "type": types.get(axis, "space")} for axis in AXES]
    for axis in axes:
        if axis["name"] in units:
            axis["unit"] = units[axis["name"]]
    scale = [1.0 if time_interval_s is None else float(time_interval_s), 1.0]
    scale += [float(size) for size in voxel_size_um]
    dataset = {"path": DATASET, "coordinateTransformations": [{"type": "scale", "scale": scale}]}
    return {
        "multiscales": [
            {"version": NGFF_VERSION, "name": name, "axes": axes, "datasets": [dataset]}
        ],
        "omero": {"name": name, "channels": [{"label": str(n)} for n in channel_names]},
    }


class ZarrSeriesWriter:
    """Write a ``(T, C, Z, Y, X)`` series to an OME-Zarr store one frame at a time.

    Use as a context manager: frames are appended with :meth:`append` and the store appears at
    ``path`` when the block ends without an error (otherwise the temporary is removed).

    Parameters
    ----------
    path : str or Path
        The store to create (a folder, conventionally named ``*.ome.zarr``).
    frame_shape : (C, Z, Y, X)
        Shape of every frame.
    voxel_size_um : (dz, dy, dx)
        Voxel size, micrometres.
    time_interval_s : float, optional
        Seconds between frames (the t axis is in frames without it).
    overwrite : bool
        Replace an existing store at ``path`` (refused otherwise, before anything is written).
    dtype : numpy dtype
        Stored type (default float32).
    metadata : mapping, optional
        A volume's :func:`fgat.io.images.volume_entries` (depth axis, depths, view order), stored as
        the group attribute ``fgat.volume``.
    channel_names : sequence of str, optional
        ``C`` names of the channels (NGFF ``omero.channels[c].label``); default ``"channel c"``.

    Raises
    ------
    ValueError
        ``path`` exists (without ``overwrite``) or is not a store, a shape or size is invalid.
    FileNotFoundError
        The folder of ``path`` does not exist.
    """

    def __init__(
        self,
        path: str | Path,
        frame_shape: Sequence[int],
        *,
        voxel_size_um: Sequence[float],
        time_interval_s: float | None = None,
        overwrite: bool = False,
        dtype=np.float32,
        metadata: Mapping[str, object] | None = None,
        channel_names: Sequence[str] | None = None,
    ) -> None:
        self.path = Path(path)
        self.frame_shape = tuple(int(n) for n in frame_shape)
        if len(self.frame_shape) != 4 or min(self.frame_shape) < 1:
            raise ValueError(f"{self.path}: frame_shape must be (C, Z, Y, X), got {frame_shape!r}")
        if channel_names is None:
            channel_names = [channel_name(c) for c in range(self.frame_shape[0])]
        if len(channel_names) != self.frame_shape[0]:
            raise ValueError(
                f"{self.path}: {len(channel_names)} channel names for {self.frame_shape[0]} "
                "channels"
            )
        if len(voxel_size_um) != 3 or not all(float(v) > 0 for v in voxel_size_um):
            raise ValueError(
                f"{self.path}: voxel_size_um must be three positive sizes (dz, dy, dx) in um, "
                f"got {voxel_size_um!r}"
            )
        if time_interval_s is not None and not float(time_interval_s) > 0:
            raise ValueError(
                f"{self.path}: time_interval_s must be positive, got {time_interval_s}"
            )
        if not self.path.parent.is_dir():
            raise FileNotFoundError(
                f"cannot write {self.path}: folder {self.path.parent} does not exist"
            )
        if self.path.exists() and not is_zarr(self.path):
            raise ValueError(f"{self.path}: exists and is not a Zarr store; it is not replaced")
        if self.path.exists() and not overwrite:
            raise ValueError(f"{self.path}: exists; choose another name or overwrite it")
        self.metadata = ngff_metadata(voxel_size_um, time_interval_s, self.path.name, channel_names)
        if metadata:
            self.metadata[VOLUME_ATTRIBUTE] = {k: v for k, v in metadata.items() if v is not None}
        self.dtype = np.dtype(dtype)
        self.count = 0
        self._temporary: Path | None = None
        self._array = None

    def __enter__(self) -> ZarrSeriesWriter:
        import zarr  # loaded when a file is read or written: keeps start-up fast

        self._temporary = Path(
            tempfile.mkdtemp(prefix=f".{self.path.name}.{os.getpid()}.", dir=self.path.parent)
        )
        group = zarr.open_group(self._temporary, mode="w", zarr_format=2)
        group.attrs.update(self.metadata)
        channels, *volume = self.frame_shape
        self._array = group.create_array(
            DATASET,
            shape=(0, *self.frame_shape),
            chunks=(1, 1, *volume),
            dtype=self.dtype,
            chunk_key_encoding={"name": "v2", "separator": "/"},  # NGFF 0.4: nested chunks
        )
        return self

    def append(self, frame) -> None:
        """Add the next time point: ``(C, Z, Y, X)`` (an array or a sequence of ``C`` volumes
        ``(Z, Y, X)``), or ``(Z, Y, X)`` for one channel. Channels are written one chunk at a
        time, so writing holds one channel's volume beside the frame."""
        channels = [frame] if np.ndim(frame[0]) == 2 else list(frame)
        shapes = [np.shape(channel) for channel in channels]
        if len(channels) != self.frame_shape[0] or set(shapes) != {self.frame_shape[1:]}:
            given = (len(channels), *shapes[0]) if len(set(shapes)) == 1 else shapes
            raise ValueError(
                f"{self.path}: frame {self.count} has shape {given}, expected "
                f"{self.frame_shape} (C, Z, Y, X)"
            )
        self._array.resize((self.count + 1, *self.frame_shape))
        for index, channel in enumerate(channels):
            self._array[self.count, index] = np.asarray(channel, dtype=self.dtype)
        self.count += 1

    def __exit__(self, kind, error, traceback) -> None:
        temporary, self._temporary, self._array = self._temporary, None, None
        if kind is not None or self.count == 0:
            shutil.rmtree(temporary, ignore_errors=True)
            if kind is None:
                raise ValueError(f"{self.path}: no frame was written")

            if isinstance(error, OSError) and error.errno in DISK_FULL_ERRNOS:
                frame = self.dtype.itemsize * int(np.prod(self.frame_shape))
                raise disk_full_error(self.path, error, (self.count + 1) * frame) from None
            return
        if self.path.exists():  # overwrite: the old store goes only once the new one is whole
            retired = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.old.", dir=self.path.parent))
            os.replace(self.path, retired / "store")
            os.replace(temporary, self.path)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            os.replace(temporary, self.path)


def write_zarr(
    path: str | Path,
    series,
    *,
    axes: str = AXES,
    voxel_size_um: Sequence[float],
    time_interval_s: float | None = None,
    overwrite: bool = False,
    metadata: Mapping[str, object] | None = None,
    channel_names: Sequence[str] | None = None,
) -> Path:
    """Write a volume series as an OME-Zarr store (NGFF 0.4; see :class:`ZarrSeriesWriter`).

    Parameters
    ----------
    path : str or Path
        The store to create (``*.ome.zarr``).
    series : array or iterable of arrays
        An array whose dimensions are ``axes``, or an iterable of frames (each with the
        dimensions of ``axes`` without ``t``), written as they come: memory holds one frame.
    axes : str
        The dimensions of ``series`` in ``"tczyx"`` order, ``t`` first when present and ``z``,
        ``y``, ``x`` last: ``"tczyx"``, ``"tzyx"``, ``"czyx"`` or ``"zyx"``.
    voxel_size_um : (dz, dy, dx)
        Voxel size, micrometres.
    time_interval_s : float, optional
        Seconds between frames.
    overwrite : bool
        Replace an existing store.
    metadata : mapping, optional
        The volume's :func:`fgat.io.images.volume_entries` (group attribute ``fgat.volume``).
    channel_names : sequence of str, optional
        The channels' names (default ``"channel c"``).

    Returns
    -------
    Path
        ``path``.
    """
    if axes not in ("tczyx", "tzyx", "czyx", "zyx"):
        raise ValueError(f"{path}: axes must be 'tczyx', 'tzyx', 'czyx' or 'zyx', got {axes!r}")
    if isinstance(series, np.ndarray) or hasattr(series, "__array__"):
        array = np.asarray(series)
        if array.ndim != len(axes):
            raise ValueError(f"{path}: axes {axes!r} for an array of shape {array.shape}")
        frames: Iterable = array if axes.startswith("t") else [array]
    else:
        if not axes.startswith("t"):
            raise ValueError(f"{path}: an iterable of frames needs axes starting with 't'")
        frames = series
    iterator = iter(frames)
    first = next(iterator, None)
    if first is None:
        raise ValueError(f"{path}: the series has no frame")

    def with_channel(frame) -> np.ndarray:
        frame = np.asarray(frame)
        return frame if "c" in axes else frame[None]

    first = with_channel(first)
    with ZarrSeriesWriter(
        path,
        first.shape,
        voxel_size_um=voxel_size_um,
        time_interval_s=time_interval_s,
        overwrite=overwrite,
        metadata=metadata,
        channel_names=channel_names,
    ) as writer:
        writer.append(first)
        for frame in iterator:
            writer.append(with_channel(frame))
    return Path(path)


def open_image(path: str | Path):
    """An OME-Zarr image with axes ``tczyx`` (fgat's, or any NGFF image with those axes),
    opened without reading its data: ``(array, entry, attributes)``, the ``(T, C, Z, Y, X)``
    zarr array, its ``multiscales`` entry and the group's attributes.

    Raises
    ------
    FileNotFoundError
        Nothing at ``path``.
    ValueError
        No ``multiscales`` metadata, or other axes; the message names ``path``.
    """
    import zarr  # loaded when a file is read or written: keeps start-up fast

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    group = zarr.open_group(path, mode="r")
    attributes = dict(group.attrs)
    multiscales = attributes.get("multiscales")
    if not multiscales:
        raise ValueError(f"{path}: not an OME-Zarr image (no 'multiscales' metadata)")
    entry = multiscales[0]
    names = "".join(axis["name"] if isinstance(axis, dict) else axis for axis in entry["axes"])
    if names != AXES:
        raise ValueError(f"{path}: axes {names!r}; fgat reads 'tczyx' images")
    return group[entry["datasets"][0]["path"]], entry, attributes


def read_zarr(path: str | Path) -> tuple[np.ndarray, dict[str, object]]:
    """The ``(T, C, Z, Y, X)`` data of an OME-Zarr image (:func:`open_image`) and its
    ``multiscales`` entry."""
    array, entry, _ = open_image(path)
    return np.asarray(array[...]), entry
