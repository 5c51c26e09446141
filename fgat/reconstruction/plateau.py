"""Stopping a fit: when its loss has plateaued, or when the loss of pixels it never saw stops
improving (over-fitting the noise, told apart from progress without a truth)."""

from __future__ import annotations

import math


class Plateau:
    """Every ``window`` steps, compare the mean loss of the last window with the previous one;
    a relative improvement below ``tolerance`` after ``min_steps`` steps is a plateau.

    Parameters
    ----------
    tolerance : float
        Smallest relative improvement per window that keeps a fit going (> 0).
    window : int
        Steps per window (>= 1).
    min_steps : int
        No plateau before this many steps.
    """

    def __init__(self, tolerance: float = 1e-3, window: int = 100, min_steps: int = 200) -> None:
        if not tolerance > 0 or window < 1:
            raise ValueError(
                f"a plateau needs tolerance > 0 and window >= 1, got {tolerance}, {window}"
            )
        self.tolerance, self.window, self.min_steps = tolerance, window, min_steps
        self._losses: list[float] = []
        self._previous = math.inf

    def update(self, loss: float, steps_done: int) -> str | None:
        """Record the loss of a step; when it ends a plateau, the reason to stop (else ``None``)."""
        self._losses.append(loss)
        if len(self._losses) < self.window:
            return None
        current = sum(self._losses) / len(self._losses)
        self._losses.clear()
        previous, self._previous = self._previous, current
        improvement = (
            (previous - current) / max(abs(previous), 1e-30) if math.isfinite(previous) else 1.0
        )
        if steps_done >= self.min_steps and improvement < self.tolerance:
            return (
                f"the loss improved by {improvement:.2e} over the last {self.window} steps "
                f"(tolerance {self.tolerance:g})"
            )
        return None

    def state_dict(self) -> dict:
        return {"losses": list(self._losses), "previous": self._previous}

    def load_state_dict(self, state: dict) -> None:
        self._losses, self._previous = list(state["losses"]), float(state["previous"])


class HoldoutStop:
    """Stop once the loss on held-out pixels (:func:`fgat.holdout.holdout_split`) has gone
    ``patience`` steps without improving on its best by more than ``tolerance`` (relative),
    after ``min_steps``.

    Photon noise is independent from pixel to pixel, so what a fit learns about the object
    lowers the held-out loss while what it learns about the noise of the fitted pixels does not:
    the held-out loss flattens, or rises, where the volume stops improving. It works on
    measured data, with no truth.

    Parameters
    ----------
    tolerance : float
        Relative improvement of the best held-out loss that counts as progress (> 0).
    patience : int
        Steps without such progress before a stop (>= 1).
    min_steps : int
        No stop before this many steps.
    """

    def __init__(self, tolerance: float = 1e-3, patience: int = 100, min_steps: int = 200) -> None:
        if not tolerance > 0 or patience < 1:
            raise ValueError(
                f"a held-out stop needs tolerance > 0 and patience >= 1, got {tolerance}, "
                f"{patience}"
            )
        self.tolerance, self.patience, self.min_steps = tolerance, patience, min_steps
        self.best, self.best_step = math.inf, 0

    def update(self, loss: float, steps_done: int) -> str | None:
        """Record the held-out loss after ``steps_done`` steps; the reason to stop, or ``None``."""
        if not math.isfinite(loss):
            raise FloatingPointError(f"step {steps_done}: the held-out loss is {loss}")
        if loss < self.best * (1 - self.tolerance):
            self.best, self.best_step = loss, steps_done
        elif steps_done >= self.min_steps and steps_done - self.best_step >= self.patience:
            return (
                f"the held-out pixels' loss has not improved by {self.tolerance:g} on its best "
                f"({self.best:.4g}, step {self.best_step}) for {steps_done - self.best_step} steps"
            )
        return None

    def state_dict(self) -> dict:
        return {"best": self.best, "best_step": self.best_step}

    def load_state_dict(self, state: dict) -> None:
        self.best, self.best_step = float(state["best"]), int(state["best_step"])
