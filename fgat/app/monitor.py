"""Progress and stopping of a command that another program runs in this process (the napari
widgets, :mod:`fgat.napari.widgets`): who draws the progress bars, and when to stop.

A command asks :func:`current` for the monitor of the code that called it. On the command line
that is the default one: ``tqdm`` bars, never stopped (Ctrl-C stops a command there,
:mod:`fgat.app.signals`). A caller that runs a command in a worker thread sets its own with
:func:`monitored` (the monitor is a context variable: it holds in that thread only) and asks it
to stop with :meth:`Monitor.cancel`; the command then raises :class:`Cancelled` at its next
check: after the iteration under way for a deconvolution, after the step under way for a fit
(which then ends as a finished run, its results written; :class:`fgat.app.callbacks.MonitorStop`).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from dataclasses import dataclass, field


class Cancelled(Exception):
    """A run stopped because its caller asked it to (:meth:`Monitor.cancel`)."""


def _tqdm(**kwargs):
    from tqdm import tqdm  # loaded when a bar is drawn: keeps start-up fast

    return tqdm(**kwargs)


@dataclass
class Monitor:
    """Where a command reports its progress, and the flag that stops it.

    Attributes
    ----------
    progress : callable or None
        Makes a progress bar as ``tqdm`` does (``progress(total=..., desc=..., unit=...)``, a
        context manager with ``update(n)``); ``None``: ``tqdm`` for the commands that draw their
        own bars, and no extra bar over a fit's (Lightning draws one).
    stop : threading.Event
        Set by :meth:`cancel`; read by :meth:`check` and :attr:`cancelled`.
    outputs : dict
        What the command made, for its caller: a fit stores its results folder, the step it
        reached and its MLflow runs there (:class:`fgat.app.callbacks.MonitorStop`).
    """

    progress: Callable[..., object] | None = None
    stop: threading.Event = field(default_factory=threading.Event)
    outputs: dict[str, object] = field(default_factory=dict)

    def bar(self, *, total: int | None, desc: str, unit: str = "it"):
        """A progress bar of ``total`` steps (``None``: of unknown length)."""
        return (self.progress or _tqdm)(total=total, desc=desc, unit=unit)

    def cancel(self) -> None:
        """Ask the command to stop at its next :meth:`check`."""
        self.stop.set()

    @property
    def cancelled(self) -> bool:
        return self.stop.is_set()

    def check(self, where: str) -> None:
        """Raise :class:`Cancelled` (``"cancelled <where>"``) once :meth:`cancel` was called."""
        if self.stop.is_set():
            raise Cancelled(f"cancelled {where}")


_CURRENT: ContextVar[Monitor | None] = ContextVar("fgat_monitor", default=None)


def active() -> Monitor | None:
    """The monitor set by :func:`monitored` in this thread; ``None`` when no caller set one (a
    command run from the command line)."""
    return _CURRENT.get()


def current() -> Monitor:
    """The monitor set by :func:`monitored` in this thread, or a new default one."""
    return active() or Monitor()


@contextlib.contextmanager
def monitored(monitor: Monitor) -> Iterator[Monitor]:
    """Run the commands called within the block under ``monitor`` (this thread only)."""
    token = _CURRENT.set(monitor)
    try:
        yield monitor
    finally:
        _CURRENT.reset(token)
