"""Stopping on SIGINT and SIGTERM: one handler for a process and its trials, the
:class:`Interrupted` error and its exit codes.
"""

from __future__ import annotations

import signal
from collections.abc import Sequence


def interrupt(number: int, frame=None) -> None:
    """A signal handler that interrupts this process as Ctrl-C does (``KeyboardInterrupt``)."""
    raise KeyboardInterrupt(f"signal {number}")


class Interrupted(Exception):
    """A run stopped by SIGINT (Ctrl-C) or SIGTERM; the command line exits with
    :attr:`exit_code`, 128 + the signal number (130 for SIGINT, 143 for SIGTERM), as a shell
    reports a process the signal ended."""

    def __init__(self, number: int, message: str) -> None:
        super().__init__(message)
        self.number = number

    @property
    def exit_code(self) -> int:
        return 128 + self.number


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

INTERRUPTED_CODES = tuple(128 + number for number in STOP_SIGNALS)
"""Exit codes of a command stopped by SIGINT or SIGTERM (:class:`Interrupted`)."""


def set_handler(number: int, handler):
    """Install ``handler`` for signal ``number``; the handler it replaced, or ``None`` outside
    the main thread, where handlers cannot be set."""
    try:
        return signal.signal(number, handler)
    except ValueError:
        return None


class StopSignals:
    """SIGINT (Ctrl-C) and SIGTERM (``kill``, SLURM's ``scancel``) stop the commands that run
    trials (``sweep``, ``pipeline``, the recipes) for good.

    Within its ``with`` block either signal interrupts this process as Ctrl-C does
    (``KeyboardInterrupt``) and :attr:`number` keeps the first one; the block then ends with
    :class:`Interrupted` (exit code 128 + the number), whatever the interrupted code made of the
    ``KeyboardInterrupt`` (Lightning turns it into ``SystemExit(1)``), so that no trial is run
    again or started after it. A fit's own handler (:class:`fgat.callbacks.SignalStop`) takes
    the signals while it trains and exits with the same codes. Blocks nest; each restores the
    handlers it replaced.
    """

    def __init__(self) -> None:
        self.number: int | None = None
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        """(Re)install the handlers (after a library, e.g. ``ray.init``, replaced them)."""
        for number in STOP_SIGNALS:
            previous = set_handler(number, self._handle)
            if previous is not None and number not in self._previous:
                self._previous[number] = previous

    def _handle(self, number: int, frame) -> None:
        if self.number is None:
            self.number = number
        interrupt(number, frame)

    def __enter__(self) -> StopSignals:
        self.number = None
        self.install()
        return self

    def __exit__(self, kind, error, traceback) -> None:
        for number, handler in self._previous.items():
            set_handler(number, handler)
        self._previous = {}
        if kind is KeyboardInterrupt or (self.number is not None and kind is SystemExit):
            number = self.number or signal.SIGINT
            raise Interrupted(number, stopped_message(number, [], [])) from None


def stopped_message(number: int, stopped: Sequence[str], killed: Sequence[str]) -> str:
    """What an interrupted set of trials says: the signal, the trials it stopped (by name), the
    MLflow runs marked KILLED here, and how to go on."""
    names = ", ".join(stopped) or "none running"
    marked = f"; MLflow run {', '.join(killed)} marked KILLED" if killed else ""
    return (
        f"stopped by {signal.Signals(number).name} (trials stopped: {names}{marked}); no further "
        "trial started. The same command goes on: finished trials are skipped, stopped fits "
        "resume from their last.ckpt"
    )
