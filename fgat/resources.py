"""Memory a computation will need, checked before anything is allocated.

A command estimates the memory of its largest step from the shapes involved and calls
:func:`check_memory`, which refuses a request that cannot fit with one line giving the estimate
and what the machine has, instead of an allocation failure minutes later. The estimates are
rough upper bounds (every large buffer counted as if alive at once); each lives beside the code
it describes (:meth:`fgat.optics.psf.JPGM.memory_bytes`, :func:`fgat.simulation.simulation_memory`),
and the FLFM operator's, shared by several commands, is here.
"""

from __future__ import annotations

import math
from pathlib import Path

from fgat.heap import release_freed_memory

__all__ = [
    "available_memory",
    "check_memory",
    "deconvolution_memory",
    "format_bytes",
    "operator_memory",
]


def format_bytes(nbytes: float) -> str:
    """``1.9e12`` -> ``"1.9 TB"`` (decimal units)."""
    units = ("B", "kB", "MB", "GB", "TB", "PB")
    power = 0
    while abs(nbytes) >= 1000 and power < len(units) - 1:
        nbytes /= 1000
        power += 1
    return f"{nbytes:.0f} B" if power == 0 else f"{nbytes:.1f} {units[power]}"


def _host_available() -> int | None:
    """Bytes the host can still allocate: ``MemAvailable`` of ``/proc/meminfo`` (psutil's
    ``available`` where there is no ``/proc``), lowered to the room left under a cgroup v2 memory
    limit; ``None`` if the platform does not say."""
    available = None
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    else:
        try:
            import psutil
        except ImportError:
            return None
        available = int(psutil.virtual_memory().available)
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            room = int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text())
            available = room if available is None else min(available, room)
    except (OSError, ValueError):
        pass
    return available


def available_memory(device=None) -> int | None:
    """Bytes that can be allocated now on ``device``: the free memory of a CUDA device, else the
    host's available memory once the freed heap this process keeps is handed back
    (:func:`fgat.heap.release_freed_memory`); ``None`` when the platform does not say."""
    if device is not None and str(device).startswith("cuda"):
        import torch

        free, _ = torch.cuda.mem_get_info(torch.device(device))
        return int(free)
    release_freed_memory()
    return _host_available()


def check_memory(what: str, nbytes: int, *, hint: str | None = None, device=None) -> None:
    """Refuse a computation whose estimated memory exceeds what ``device`` (default: the host) has.

    Parameters
    ----------
    what : str
        The subject of the message, e.g. ``"the phantom, PSF stack and forward model"``.
    nbytes : int
        Estimated peak memory in bytes.
    hint : str, optional
        What the user can reduce, appended in parentheses.
    device : str or torch.device, optional
        Where the memory is needed (``cuda`` devices are asked for their free memory).

    Raises
    ------
    ValueError
        ``"<what> need about 1.9 TB; this machine has 21.3 GB available (<hint>)"``.
    """
    available = available_memory(device)
    if available is None or nbytes <= available:
        return
    where = (
        f"{device} has"
        if device is not None and str(device).startswith("cuda")
        else "this machine has"
    )
    raise ValueError(
        f"{what} need about {format_bytes(nbytes)}; {where} {format_bytes(available)} available"
        + (f" ({hint})" if hint else "")
    )


def operator_memory(
    psf_shape: tuple[int, int, int, int],
    volume_shape: tuple[int, int, int],
    *,
    itemsize: int = 4,
    adjoint: bool = True,
    guard_px: int = 0,
) -> int:
    """Bytes of an :class:`~fgat.optics.operator.FLFMOperator` and one projection, upper bound.

    With ``guard_px = g > 0`` it is the :class:`~fgat.optics.acquisition.MeasuredOperator` of
    views ``volume_shape[1:]`` on the padded grid ``(Z, Y + 2g, X + 2g)``, and ``Y, X`` below
    are the padded sizes. With ``V, Z, h, w = psf_shape``, ``Y, X`` the volume's lateral size,
    the FFT grid ``fy x fx`` (:func:`~fgat.optics.operator.spectral_grid`),
    ``F = fy (fx // 2 + 1)`` complex bins and ``r = itemsize``: building the OTFs takes the
    zero-padded PSFs ``V Z fy fx r`` and the OTFs ``V Z F 2r``; the adjoint keeps their conjugate
    (another ``V Z F 2r``); a forward or adjoint projection holds the padded input and spectrum
    of the volume (``Z (fy fx r + F 2r)``) and of the views (``V (fy fx r + F 2r)``), counted
    twice for the inverse transforms.
    """
    from fgat.optics.operator import spectral_grid

    n_views, n_depths, h, w = (int(n) for n in psf_shape)
    _, y, x = (int(n) + 2 * guard_px * (axis > 0) for axis, n in enumerate(volume_shape))
    fy, fx = spectral_grid((y, x), (h, w))
    real, spectrum = fy * fx * itemsize, fy * (fx // 2 + 1) * 2 * itemsize
    otf = n_views * n_depths * (real + spectrum * (2 if adjoint else 1))
    return otf + 2 * (n_depths + n_views) * (real + spectrum)


def deconvolution_memory(
    psf_shape: tuple[int, int, int, int],
    volume_shape: tuple[int, int, int],
    *,
    itemsize: int = 4,
    guard_px: int = 0,
) -> int:
    """Bytes of an RL/SHB deconvolution (:func:`fgat.deconvolution.deconvolve`), upper bound:
    :func:`operator_memory` plus Algorithm S1's six volumes (estimate, previous, extrapolated
    point, update, ``A^T 1``, the callback's copy) on the grid padded by ``guard_px`` (see
    :func:`operator_memory`) and five view stacks (measurement, its normalised copy, prediction,
    ratio, ``A^T`` input, counted at the padded size; weights broadcast a given mask)."""
    n_views = int(psf_shape[0])
    z, y, x = (int(n) + 2 * guard_px * (axis > 0) for axis, n in enumerate(volume_shape))
    return (
        operator_memory(psf_shape, volume_shape, itemsize=itemsize, guard_px=guard_px)
        + (6 * z + 5 * n_views) * y * x * itemsize
    )


def window_voxels(scale: float, axial_ratio: float) -> int:
    """Voxels in the voxelizer's window around a Gaussian of ``scale`` lateral voxels (its 3-sigma
    box, at least the smallest window), the axial voxel being ``axial_ratio`` lateral voxels."""
    lateral = 2 * math.floor(3 * scale + 0.5) + 1
    axial = 2 * max(1, math.floor(3 * scale / axial_ratio + 0.5)) + 1
    return lateral * lateral * axial


def gaussian_bytes(count: int, window: int) -> int:
    """Memory of ``count`` Gaussians in a training step: 11 float32 parameters with their
    gradients and two Adam moments, and per window voxel what the voxelizer keeps for the
    backward pass (quadratic form, exponential, values, mask, int64 voxel index: about 32 bytes).
    A lower bound: windows grow when the Gaussians do."""
    return count * (11 * 4 * 4 + 32 * window)
