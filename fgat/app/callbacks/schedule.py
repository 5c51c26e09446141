"""Callbacks that decide when a fit stops and what it keeps: early stopping on a plateau or on
the held-out pixels' loss, the last checkpoint."""

from __future__ import annotations

import warnings
from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_info

from fgat.recon import HoldoutStop, Plateau


class _RuleStopping(pl.Callback):
    """Stop when ``rule.update(<the module's attribute watched>, step)`` gives a reason, and say
    so; the rule's state goes into the checkpoint."""

    watched = "last_loss"
    reason: str | None = None  # why it stopped the fit, once it has

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        reason = self.rule.update(getattr(pl_module, self.watched), trainer.global_step)
        if reason:
            trainer.should_stop = True
            self.reason = reason
            rank_zero_info(f"fgat: early stop at step {trainer.global_step}: {reason}")

    def state_dict(self) -> dict:
        return self.rule.state_dict()

    def load_state_dict(self, state_dict: dict) -> None:
        self.rule.load_state_dict(state_dict)


class PlateauStopping(_RuleStopping):
    """Stop when the training loss has plateaued (:class:`~fgat.recon.Plateau`: every
    ``window`` steps, a mean loss within ``tolerance`` (relative) of the best window's after
    ``min_steps`` steps; a worsening loss is no plateau and the fit goes on), and say so."""

    def __init__(self, tolerance: float = 1e-3, window: int = 100, min_steps: int = 200) -> None:
        self.rule = Plateau(tolerance, window, min_steps)


class HoldoutStopping(_RuleStopping):
    """Stop when the loss of the pixels held out of the fit (``model.init_args.holdout``) has
    stopped improving (:class:`~fgat.recon.HoldoutStop`), and say so: the fit has begun
    to learn the noise. Needs a model that reports ``loss/holdout`` every step."""

    watched = "last_holdout"

    def __init__(self, tolerance: float = 1e-3, patience: int = 100, min_steps: int = 200) -> None:
        self.rule = HoldoutStop(tolerance, patience, min_steps)

    def on_fit_start(self, trainer, pl_module) -> None:
        if not getattr(pl_module.settings, "holdout", 0) > 0:
            raise ValueError(
                "trainer.callbacks: HoldoutStopping needs pixels held out of the fit: set "
                "model.init_args.holdout (e.g. 0.1)"
            )


class StepCheckpoint(ModelCheckpoint):
    """``last.ckpt`` every ``every_n_train_steps`` steps and once more when training ends, so a
    run that stops between two intervals (max_steps, early stop) resumes from its final state.

    The state saved is the engine's after the step, which is where a resumed run continues
    (Lightning's warning about manual optimization, which expects the state before, is muted).
    """

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        with warnings.catch_warnings():
            warnings.filterwarnings(
                "ignore", message="Using ModelCheckpoint with manual optimization"
            )
            super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)

    def on_train_end(self, trainer, pl_module) -> None:
        super().on_train_end(trainer, pl_module)
        self.save_last_now(trainer)

    def save_last_now(self, trainer) -> Path | None:
        """Write ``last.ckpt`` of the state now (a fit that ends, or one stopped between two
        steps); its path, or ``None`` when no step was done or no last checkpoint is kept."""
        if not (self.save_last and self.dirpath and trainer.global_step > 0):
            return None
        path = self.last_model_path or str(
            Path(self.dirpath) / f"{self.CHECKPOINT_NAME_LAST}{self.FILE_EXTENSION}"
        )
        trainer.save_checkpoint(path, weights_only=self.save_weights_only)
        self.last_model_path = path
        return Path(path)
