"""Keep freed host memory in the process for the next allocation (Linux, glibc).

On a CPU every FLFM projection allocates a few MB of FFT temporaries per depth chunk (PyTorch's
FFTs allocate their results even with ``out=``) and, for an adjoint, the volume it returns (36
MB at paper size), and frees them again. glibc's default policy maps blocks above a few MB on
their own and unmaps them when freed, and hands freed heap back to the kernel, so the next call
touches fresh pages and pays a page fault per 4 KiB: on a virtual machine about as much time as
the FFTs. :func:`retain_freed_memory` switches the process to the policy PyTorch's CPU
performance guide gets from jemalloc or tcmalloc: every block comes from the heap and up to
``trim_bytes`` of freed heap stays mapped for reuse. :func:`release_freed_memory` hands the rest
back, and :func:`fgat._core.resources.available_memory` calls it before it asks the kernel what is
free, so memory checks see the memory this process holds but no longer uses.
"""

from __future__ import annotations

import ctypes
import os
import platform

__all__ = ["release_freed_memory", "retain_freed_memory"]

M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4

OPT_OUT = "FGAT_RETURN_FREED_MEMORY"
"""Set to ``1`` to keep glibc's default policy (freed memory handed back to the kernel)."""

_USER_SETTINGS = (
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_MMAP_MAX_",
    "GLIBC_TUNABLES",
)


def _glibc() -> ctypes.CDLL | None:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    return ctypes.CDLL(None)


def retain_freed_memory(trim_bytes: int = 2**30) -> bool:
    """Serve every host block from the heap and keep up to ``trim_bytes`` of freed heap mapped,
    for the rest of the process.

    Parameters
    ----------
    trim_bytes : int
        Freed memory (bytes, at most ``2**31 - 1``) at the top of the heap that stays mapped
        before glibc hands it back to the kernel.

    Returns
    -------
    bool
        Whether the policy was set: ``False`` off glibc, when the environment already tunes
        glibc's allocator (``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_MMAP_THRESHOLD_``,
        ``MALLOC_MMAP_MAX_``, ``GLIBC_TUNABLES``: the user's choice stands) or when
        ``FGAT_RETURN_FREED_MEMORY=1``.
    """
    if not 0 <= trim_bytes < 2**31:
        raise ValueError(f"trim_bytes must be in [0, 2**31) bytes, got {trim_bytes}")
    libc = _glibc()
    if libc is None or os.environ.get(OPT_OUT) == "1":
        return False
    if any(name in os.environ for name in _USER_SETTINGS):
        return False
    return bool(libc.mallopt(M_MMAP_MAX, 0) and libc.mallopt(M_TRIM_THRESHOLD, trim_bytes))


def release_freed_memory() -> bool:
    """Hand the freed heap this process keeps back to the kernel (``malloc_trim(0)``); ``True``
    if glibc released any. Cheap when nothing is kept: call it before measuring free memory."""
    libc = _glibc()
    return libc is not None and bool(libc.malloc_trim(0))
