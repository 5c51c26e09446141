"""Machine resources: free host and device memory, free disk space (and the disk-full
error), process memory, and formatting of byte counts and durations; timing helpers.
"""

from __future__ import annotations

import errno
import os
import resource
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from fgat._core.heap import release_freed_memory


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
            import psutil  # optional: used only when installed
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
    (:func:`fgat._core.heap.release_freed_memory`); ``None`` when the platform does not say."""
    if device is not None and str(device).startswith("cuda"):
        import torch  # torch loaded when used: keeps start-up fast

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


DISK_FULL_ERRNOS = frozenset(
    code for code in (errno.ENOSPC, getattr(errno, "EDQUOT", None)) if code is not None
)
"""``errno`` values of a write that failed for want of room: no space left on the device, or
the user's disk quota exceeded."""


class DiskFullError(ValueError):
    """A file could not be written for want of room on its disk (or under the user's quota); the
    message names the file, the bytes it needs and the bytes free."""


def _free_bytes(path: str | Path) -> tuple[Path, int | None]:
    """The nearest existing folder of ``path`` and the bytes free to this user on its file
    system (``None`` if the platform does not say)."""
    folder = Path(path).absolute()
    while not folder.is_dir() and folder != folder.parent:
        folder = folder.parent
    try:
        return folder, int(shutil.disk_usage(folder).free)
    except OSError:
        return folder, None


def disk_full_error(path: str | Path, error: OSError, nbytes: int | None = None) -> DiskFullError:
    """The one-line :class:`DiskFullError` for an ``OSError`` ``error`` (``ENOSPC``, ``EDQUOT``)
    raised while writing ``path`` of about ``nbytes`` bytes (``None``: not known)."""
    _, free = _free_bytes(path)
    reason = "the disk quota is exceeded" if error.errno != errno.ENOSPC else "the disk is full"
    need = f" needs about {format_bytes(nbytes)};" if nbytes else ""
    room = f" {format_bytes(free)} free there" if free is not None else ""
    return DiskFullError(
        f"cannot write {path}: {reason} ({os.strerror(error.errno)});{need}{room}; free some "
        "space or write elsewhere (nothing was left under that name)"
    )


def check_disk_space(path: str | Path, nbytes: int, *, what: str | None = None) -> None:
    """Refuse, before a computation, to write ``nbytes`` bytes at ``path`` (a file or a folder,
    existing or not) when its file system has less free room.

    Raises
    ------
    DiskFullError
        ``"<what>: needs about 1.2 GB of disk space; only 300.0 MB free in <folder>; ..."``.
    """
    folder, free = _free_bytes(path)
    if free is None or nbytes <= free:
        return
    raise DiskFullError(
        f"{what or path}: needs about {format_bytes(nbytes)} of disk space; only "
        f"{format_bytes(free)} free in {folder}; free some space or write elsewhere"
    )


# ---------------------------------------------------------------------- time and peak memory
def format_seconds(seconds: float) -> str:
    """``8280`` -> ``"2.3 h"``, ``95`` -> ``"1.6 min"``, ``4.2`` -> ``"4.2 s"``, ``0.031`` ->
    ``"31 ms"``, ``0.25`` -> ``"250 ms"``."""
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    if seconds < 1.0:
        return f"{seconds * 1000:.3g} ms"
    return f"{seconds:.1f} s"


def process_memory() -> tuple[int, int]:
    """Bytes this process holds now (``VmRSS``; the peak where there is no ``/proc``) and the
    most it has held so far (``ru_maxrss``, kB on Linux, bytes on macOS)."""
    scale = 1 if sys.platform == "darwin" else 1024
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024, peak
    return peak, peak


def device_memory(device) -> tuple[int, int]:
    """:func:`process_memory` on a CPU; on a CUDA device the bytes its caching allocator holds
    for tensors now and at most so far."""
    if str(device).startswith("cuda"):
        import torch  # torch loaded when used: keeps start-up fast

        return torch.cuda.memory_allocated(device), torch.cuda.max_memory_allocated(device)
    return process_memory()


def timed_call(run: Callable[[], object], synchronize: Callable[[], None] = lambda: None) -> float:
    """Wall seconds of one call of ``run`` (``synchronize`` waits for a GPU's queued work)."""
    synchronize()
    start = time.perf_counter()
    run()
    synchronize()
    return time.perf_counter() - start


CALIBRATION_SECONDS = 1.0
"""A timed call is repeated at least :data:`CALIBRATION_MIN_REPEATS` times, then until this long
has been spent on it or :data:`CALIBRATION_MAX_REPEATS` calls, and the fastest time is kept:
other processes sharing the cores only ever add to a time, so the estimate is that of this
machine when the run has it to itself."""
CALIBRATION_MIN_REPEATS = 3
CALIBRATION_MAX_REPEATS = 10


def fastest_seconds(
    run: Callable[[], object], synchronize: Callable[[], None] = lambda: None
) -> float:
    """Fastest wall seconds of ``run()`` over repeated calls (see :data:`CALIBRATION_SECONDS`)."""
    times = [timed_call(run, synchronize) for _ in range(CALIBRATION_MIN_REPEATS)]
    while sum(times) < CALIBRATION_SECONDS and len(times) < CALIBRATION_MAX_REPEATS:
        times.append(timed_call(run, synchronize))
    return min(times)


@dataclass(frozen=True)
class Affine:
    """``seconds(n) = fixed + per_unit n``: the time of an operation on ``n`` planes."""

    fixed: float
    per_unit: float

    def __call__(self, n: float) -> float:
        return self.fixed + self.per_unit * n
