"""Stopping a fit: when its loss has plateaued, or when the loss of pixels it never saw stops
improving (over-fitting the noise, told apart from progress without a truth); and what a fit's
loss did from its start to its end (:class:`LossTrend`, for the check of
:mod:`fgat.recon.outcome`)."""

from __future__ import annotations

import math


class Plateau:
    """Every ``window`` steps, compare the mean loss of the last window with the best window
    mean so far: a window within ``tolerance`` of it (relative, either side) after
    ``min_steps`` steps is a plateau.

    A worsening (a window whose mean is more than ``tolerance`` above the best) is not a
    plateau: the fit goes on. A Gaussian fit's loss rises for a while after the Gaussian set or
    the optics change (a densification or JPGM event), and the optimiser brings it back down;
    stopping there, or once the loss has flattened at the worse level, would keep the worst
    state of the run as if it had converged. A fit whose loss never comes back runs to its
    step limit, and one that ends above where it started, or with an empty volume, is reported
    as failed (:func:`fgat.recon.outcome.check_fit`).

    Parameters
    ----------
    tolerance : float
        Smallest relative improvement on the best window per window that keeps a fit going
        (> 0).
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
        self._best = math.inf

    def update(self, loss: float, steps_done: int) -> str | None:
        """Record the loss of a step; when it ends a plateau, the reason to stop (else ``None``)."""
        self._losses.append(loss)
        if len(self._losses) < self.window:
            return None
        current = sum(self._losses) / len(self._losses)
        self._losses.clear()
        best, self._best = self._best, min(self._best, current)
        if not math.isfinite(best):
            return None
        improvement = (best - current) / max(abs(best), 1e-30)
        if steps_done >= self.min_steps and abs(improvement) < self.tolerance:
            return (
                f"the loss improved by {improvement:.2e} on its best window over the last "
                f"{self.window} steps (tolerance {self.tolerance:g})"
            )
        return None

    def state_dict(self) -> dict:
        return {"losses": list(self._losses), "best": self._best}

    def load_state_dict(self, state: dict) -> None:
        self._losses = list(state["losses"])
        self._best = float(state.get("best", state.get("previous", math.inf)))


class HoldoutStop:
    """Stop once the loss on held-out pixels (:func:`fgat.recon.holdout.holdout_split`) has gone
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


class LossTrend:
    """The mean loss of a fit's first ``window`` steps and of its last ``window`` steps.

    A step's loss in the dynamic stage is one frame's, and frames differ in how well they can
    be fitted: a whole pass over the frames (``window`` = the number of frames) is the unit
    the start and the end are compared in. A run resumed from a checkpoint starts its record
    at the resumed step.

    Parameters
    ----------
    window : int
        Steps averaged at the start and at the end (>= 1).
    """

    def __init__(self, window: int = 1) -> None:
        if window < 1:
            raise ValueError(f"a loss trend needs window >= 1, got {window}")
        self.window = int(window)
        self._first: list[float] = []
        self._last: list[float] = []

    def update(self, loss: float) -> None:
        """Record the loss of a step."""
        if len(self._first) < self.window:
            self._first.append(float(loss))
        self._last.append(float(loss))
        del self._last[: -self.window]

    @property
    def first(self) -> float:
        """Mean loss of the first ``window`` steps (NaN before any step)."""
        return sum(self._first) / len(self._first) if self._first else math.nan

    @property
    def last(self) -> float:
        """Mean loss of the last ``window`` steps (NaN before any step)."""
        return sum(self._last) / len(self._last) if self._last else math.nan
