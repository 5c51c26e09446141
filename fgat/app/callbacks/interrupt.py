"""Stop a fit on Ctrl-C (SIGINT) or SIGTERM between two steps, with a checkpoint to resume from."""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.utilities.exceptions import SIGTERMException

from fgat.app.callbacks.schedule import StepCheckpoint
from fgat.app.signals import STOP_SIGNALS, interrupt, set_handler


class SignalStop(pl.Callback):
    """Stop a fit on SIGINT or SIGTERM at the end of the step under way.

    During training the first signal lets the step (and a validation under way) finish, with its
    metrics logged; then the fit stops and ``last.ckpt`` is written from that state
    (:meth:`~fgat.callbacks.StepCheckpoint.save_last_now`), so ``--ckpt_path last`` continues
    where it stopped. A second signal, or one before training starts (the SHB initialisation),
    interrupts at once (``KeyboardInterrupt``); the last periodic checkpoint is then the one to
    resume from. :attr:`signal` is the signal that stopped the fit (``None``: none did);
    the command line marks its MLflow runs KILLED and exits with 128 + its number.
    """

    def __init__(self) -> None:
        self.signal: int | None = None
        self.checkpoint: Path | None = None
        self._training = self._between_steps = self._saving = False
        self._previous: dict[int, object] = {}

    def setup(self, trainer, pl_module, stage: str) -> None:
        if stage == "fit" and not self._previous:
            self.signal, self.checkpoint = None, None
            for number in STOP_SIGNALS:
                previous = set_handler(number, self._handle)
                if previous is not None:
                    self._previous[number] = previous

    def teardown(self, trainer, pl_module, stage: str) -> None:
        self._restore()

    def _restore(self) -> None:
        for number, handler in self._previous.items():
            set_handler(number, handler)
        self._previous = {}

    def _handle(self, number: int, frame) -> None:
        first = self.signal is None
        if first:
            self.signal = number
        if self._saving or (first and self._training):
            return  # stop at the end of the step (:meth:`_stop_if_signalled`)
        interrupt(number, frame)

    def _stop_if_signalled(self) -> None:
        if self.signal is not None:
            self._between_steps = True
            interrupt(self.signal)

    def on_train_start(self, trainer, pl_module) -> None:
        self._training = True
        self._stop_if_signalled()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._stop_if_signalled()

    def on_train_end(self, trainer, pl_module) -> None:
        self._stop_if_signalled()  # before the last checkpoint and the results are written
        self._training = False

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        """Stopped between two steps (here, or by Lightning's own SIGTERM check): write the
        last checkpoint, further signals held off until it is whole."""
        between = self._between_steps or isinstance(exception, SIGTERMException)
        if self.signal is not None and between:
            self._saving = True
            try:
                for callback in trainer.checkpoint_callbacks:
                    if isinstance(callback, StepCheckpoint):
                        self.checkpoint = callback.save_last_now(trainer) or self.checkpoint
            finally:
                self._saving = False
        self._training = False
        self._restore()
