"""Thread pools sized to the CPUs this process may use, and idle threads that sleep.

PyTorch's intra-op pool (OpenMP; libgomp in Linux wheels) starts one thread per CPU it sees (a
cgroup CPU quota, as in a container limited to 1.5 CPUs, is not seen), and a thread waiting at
the end of a parallel region spins before it sleeps: about 3 ms with libgomp's defaults
(``GOMP_SPINCOUNT`` 300 000), for ever with ``OMP_WAIT_POLICY=ACTIVE``. On a machine shared with
other work, a thread spins while the partner it waits for is descheduled, so fgat burns CPU time
that the other work needs and runs several times slower than its share of the CPUs allows. So,
when fgat is imported before torch (``python -m fgat``, a trial's process, a script that imports
fgat first), it fills in, where the user has not, the environment that the OpenMP runtime reads
when torch loads it:

- ``OMP_NUM_THREADS``: :func:`usable_cpus`, the CPUs the process may use (its affinity mask,
  capped by a cgroup CPU quota), not the machine's cores;
- ``OMP_WAIT_POLICY=PASSIVE``: waiting threads sleep at once (libgomp's spin count 0; LLVM's
  and Intel's runtimes take it as ``KMP_BLOCKTIME=0``), unless the user chose a waiting policy
  with any of :data:`WAIT_VARIABLES`.

These are read once, when the runtime starts: setting them after ``import torch`` changes
nothing but child processes, so a process that imported torch first keeps its settings.
:func:`configure_threads` also applies the thread count to a torch already imported, for callers
that ask it explicitly. The waiting policy changes no result (it only decides how idle threads
wait); the thread count is torch's own choice except under a CPU quota, where fewer threads may
change reductions within float rounding.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping, MutableMapping
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")
"""Where the cgroup file systems are mounted (v2 unified, or one folder per v1 controller)."""

SELF_CGROUP = Path("/proc/self/cgroup")
"""The cgroups of this process, one ``id:controllers:path`` line per hierarchy."""

WAIT_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME", "KMP_LIBRARY")
"""Environment variables that choose how idle OpenMP threads wait (OpenMP, libgomp, LLVM and
Intel runtimes): when the user set any of them, fgat leaves the waiting policy alone."""


def affinity_cpus() -> int:
    """The number of CPUs in this process's affinity mask (``taskset``, ``numactl``, a batch
    scheduler's CPU set); ``os.cpu_count()`` where the platform has no affinity mask."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _quota_v2(path: Path) -> float | None:
    """CPUs allowed by a cgroup v2 ``cpu.max`` file (``"$MAX $PERIOD"`` in microseconds,
    ``max`` for no limit); ``None`` when unlimited or unreadable."""
    try:
        fields = path.read_text().split()
    except OSError:
        return None
    if len(fields) != 2 or fields[0] == "max":
        return None
    return _ratio(fields[0], fields[1])


def _quota_v1(folder: Path) -> float | None:
    """CPUs allowed by a cgroup v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` pair (quota
    ``-1`` for no limit); ``None`` when unlimited or unreadable."""
    try:
        quota = (folder / "cpu.cfs_quota_us").read_text().strip()
        period = (folder / "cpu.cfs_period_us").read_text().strip()
    except OSError:
        return None
    return _ratio(quota, period)


def _ratio(quota: str, period: str) -> float | None:
    """``quota / period`` when both are positive whole numbers, else ``None`` (no limit)."""
    try:
        quota_us, period_us = int(quota), int(period)
    except ValueError:
        return None
    if quota_us <= 0 or period_us <= 0:
        return None
    return quota_us / period_us


def _ancestors(path: str) -> list[str]:
    """``/a/b`` -> ``["a/b", "a", ""]``: a cgroup and the groups above it, relative to the
    mount point (a limit anywhere above a group applies to it)."""
    parts = [part for part in path.strip().split("/") if part]
    return ["/".join(parts[:n]) for n in range(len(parts), -1, -1)]


def cgroup_cpu_quota(root: Path = CGROUP_ROOT, self_cgroup: Path = SELF_CGROUP) -> float | None:
    """The CPU bandwidth (in CPUs, e.g. 1.5) that the cgroups of this process allow, the
    smallest over the process's group and the groups above it; ``None`` when there is no limit.

    Parameters
    ----------
    root : Path
        The cgroup mount point: cgroup v2 reads ``root/<group>/cpu.max``; v1 reads
        ``root/cpu/<group>/cpu.cfs_quota_us`` and ``cpu.cfs_period_us`` (or the folder named by
        the hierarchy's controllers, e.g. ``cpu,cpuacct``).
    self_cgroup : Path
        The process's ``/proc/self/cgroup``. A group path that the mount does not show (a
        container without its own cgroup namespace sees its group as the mount's root) is
        looked up by its ancestors down to the root.
    """
    try:
        lines = self_cgroup.read_text().splitlines()
    except OSError:
        return None
    limits = []
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        _, controllers, group = fields
        if controllers == "":  # cgroup v2
            files = [root / part / "cpu.max" for part in _ancestors(group)]
            limits += [_quota_v2(path) for path in files]
        elif "cpu" in controllers.split(","):  # cgroup v1
            mounts = [root / "cpu", root / controllers]
            limits += [_quota_v1(mount / part) for mount in mounts for part in _ancestors(group)]
    limits = [limit for limit in limits if limit is not None]
    return min(limits) if limits else None


def requested_threads(environ: Mapping[str, str]) -> int | None:
    """The thread count the user asked for with ``OMP_NUM_THREADS`` (the first entry of an
    OpenMP list such as ``4,2``); ``None`` when it is unset.

    Raises
    ------
    ValueError
        One line naming the variable, when it is set but not a positive whole number (the
        OpenMP runtime ignores such a value too).
    """
    text = environ.get("OMP_NUM_THREADS")
    if text is None or not text.strip():
        return None
    first = text.split(",")[0].strip()
    if not first.isdigit() or int(first) < 1:
        raise ValueError(
            f"OMP_NUM_THREADS={text!r} is not a positive whole number (e.g. OMP_NUM_THREADS=2)"
        )
    return int(first)


def usable_cpus(
    environ: Mapping[str, str] | None = None,
    affinity: int | None = None,
    root: Path = CGROUP_ROOT,
    self_cgroup: Path = SELF_CGROUP,
) -> int:
    """How many threads fgat's pools should have: ``OMP_NUM_THREADS`` when the user set it,
    else the CPUs of the affinity mask capped by the cgroup CPU quota.

    A fractional quota is rounded up (1.5 CPUs -> 2 threads, 0.5 -> 1): the kernel throttles a
    group's threads together once they used its quota in a period, so ``ceil(quota)`` threads
    use all of it where ``floor`` would leave part of it idle.

    Parameters
    ----------
    environ : mapping, optional
        The environment (default ``os.environ``).
    affinity : int, optional
        The CPUs of the affinity mask (default :func:`affinity_cpus`).
    root, self_cgroup : Path
        See :func:`cgroup_cpu_quota`.

    Raises
    ------
    ValueError
        When ``OMP_NUM_THREADS`` is set to something else than a positive whole number.
    """
    requested = requested_threads(os.environ if environ is None else environ)
    if requested is not None:
        return requested
    cpus = affinity_cpus() if affinity is None else affinity
    quota = cgroup_cpu_quota(root, self_cgroup)
    if quota is not None:
        cpus = min(cpus, math.ceil(quota - 1e-9))
    return max(1, cpus)


def thread_environment(environ: Mapping[str, str], threads: int) -> dict[str, str]:
    """The variables :func:`configure_threads` adds to ``environ``: ``OMP_NUM_THREADS`` (when
    unset) and ``OMP_WAIT_POLICY=PASSIVE`` (when none of :data:`WAIT_VARIABLES` is set). A value
    the user set is never replaced."""
    added = {}
    if "OMP_NUM_THREADS" not in environ:
        added["OMP_NUM_THREADS"] = str(threads)
    if not any(name in environ for name in WAIT_VARIABLES):
        added["OMP_WAIT_POLICY"] = "PASSIVE"
    return added


def configure_threads(
    environ: MutableMapping[str, str] | None = None,
    affinity: int | None = None,
    root: Path = CGROUP_ROOT,
    self_cgroup: Path = SELF_CGROUP,
) -> int:
    """Size the thread pools to :func:`usable_cpus` and let idle threads sleep; the thread count.

    Adds :func:`thread_environment` to ``environ`` (default ``os.environ``), which takes effect
    when torch is imported afterwards, and, when torch is already imported, sets its intra-op
    threads (``torch.set_num_threads``) and, if its inter-op pool has not started yet, its
    inter-op threads. An ``OMP_NUM_THREADS`` that is not a positive whole number is ignored with
    one warning line on stderr, as the OpenMP runtime ignores it.
    """
    environ = os.environ if environ is None else environ
    try:
        threads = usable_cpus(environ, affinity, root, self_cgroup)
    except ValueError as error:
        threads = usable_cpus({}, affinity, root, self_cgroup)
        print(f"fgat: warning: {error}: ignored, using {threads} threads", file=sys.stderr)
    environ.update(thread_environment(environ, threads))
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)
        try:
            torch.set_num_interop_threads(threads)
        except RuntimeError:  # the inter-op pool has started: its size is fixed
            pass
    return threads
