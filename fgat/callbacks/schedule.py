"""Callbacks that decide what a step does: densification and early stopping on a plateau."""

from __future__ import annotations

import math

from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_info

from fgat.modules.static import log_event


class Densification(pl.Callback):
    """Drive the module's :class:`~fgat.gaussians.densify.DensificationStrategy`.

    Gradient statistics are accumulated before each optimizer step; the strategy densifies and
    prunes after the step when it is due, and the changes are logged (``gaussians/cloned``,
    ``gaussians/split``, ``gaussians/pruned``).
    """

    def on_fit_start(self, trainer, pl_module) -> None:
        if not pl_module.densification.enabled:
            rank_zero_info("fgat: densification disabled: the Gaussian set stays fixed (step skipped)")

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        pl_module.densification.update_statistics(pl_module.cloud)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        changes = pl_module.densification.step(pl_module.cloud, trainer.optimizers[0], trainer.global_step)
        if changes:
            log_event(trainer.loggers, {f"gaussians/{key}": float(value) for key, value in changes.items()
                                        if key != "count"}, trainer.global_step)
            rank_zero_info(f"fgat: step {trainer.global_step}: densification cloned {changes['cloned']}, split "
                           f"{changes['split']}, pruned {changes['pruned']} -> {changes['count']} Gaussians")


class PlateauStopping(pl.Callback):
    """Stop when the training loss has plateaued.

    Every ``window`` steps the mean loss of the last window is compared with the previous one;
    a relative improvement below ``tolerance`` stops the run (after ``min_steps``) and says so.
    """

    def __init__(self, tolerance: float = 1e-3, window: int = 100, min_steps: int = 200) -> None:
        if not tolerance > 0 or window < 1:
            raise ValueError(f"PlateauStopping needs tolerance > 0 and window >= 1, got {tolerance}, {window}")
        self.tolerance, self.window, self.min_steps = tolerance, window, min_steps
        self._losses: list[float] = []
        self._previous = math.inf

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._losses.append(pl_module.last_loss)
        if len(self._losses) < self.window:
            return
        current = sum(self._losses) / len(self._losses)
        self._losses.clear()
        improvement = (self._previous - current) / max(abs(self._previous), 1e-30) if math.isfinite(self._previous) else 1.0
        self._previous = current
        if trainer.global_step >= self.min_steps and improvement < self.tolerance:
            trainer.should_stop = True
            rank_zero_info(f"fgat: early stop at step {trainer.global_step}: the loss improved by "
                           f"{improvement:.2e} over the last {self.window} steps (tolerance {self.tolerance:g})")


class StepCheckpoint(ModelCheckpoint):
    """``last.ckpt`` every ``every_n_train_steps`` steps and once more when training ends, so a
    run that stops between two intervals (max_steps, early stop) resumes from its final state."""

    def on_train_end(self, trainer, pl_module) -> None:
        super().on_train_end(trainer, pl_module)
        if self.save_last and self.dirpath and trainer.global_step > 0:
            path = self.last_model_path or str(Path(self.dirpath) / f"{self.CHECKPOINT_NAME_LAST}{self.FILE_EXTENSION}")
            trainer.save_checkpoint(path, weights_only=self.save_weights_only)
            self.last_model_path = path
