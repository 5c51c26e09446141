"""Stopping a fit when its loss has plateaued."""

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
