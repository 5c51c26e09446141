"""Whether a finished fit is a result: the check both stages run on what they write.

A fit can end without an error and still have nothing to show: its loss ended above where it
started (the Gaussians explain the measurement worse than their initialisation), or the volume
it writes is zero over the whole field of view (every Gaussian left in the guard band or
pruned) or holds NaN/Inf. Such a run is a failure: :func:`check_fit` raises :class:`FitFailed`
with one line saying which, which ``python -m fgat fit`` reports as its error (non-zero exit)
and which marks the MLflow run FAILED.
"""

from __future__ import annotations

import math

import numpy as np


class FitFailed(ValueError):
    """A fit that ran to its end without a usable result (:func:`check_fit`)."""


class VolumeRecord:
    """What :func:`check_fit` needs of the volumes a fit writes, gathered one volume at a time
    (a dynamic stage writes its frames one by one): whether every voxel was finite and the
    largest absolute value."""

    def __init__(self) -> None:
        self.volumes = 0
        self.non_finite = 0  # volumes with a NaN or Inf voxel
        self.peak = 0.0

    def add(self, volume: np.ndarray) -> None:
        """Record one written volume ``(Z, Y, X)`` (any units)."""
        volume = np.asarray(volume)
        self.volumes += 1
        finite = np.isfinite(volume)
        if not finite.all():
            self.non_finite += 1
        if finite.any():
            self.peak = max(self.peak, float(np.abs(volume[finite]).max()))


def fit_failure(volumes: VolumeRecord, first_loss: float, last_loss: float) -> str | None:
    """Why a finished fit is no result, or ``None`` when it is one.

    Parameters
    ----------
    volumes : VolumeRecord
        The volumes the fit wrote (the field of view, the guard band cropped).
    first_loss, last_loss : float
        The fit's loss at its start and at its end (e.g. :class:`~fgat.recon.plateau.
        LossTrend`); NaN when no step ran (then only the volumes are checked).

    Returns
    -------
    str or None
        One line: a non-finite volume, an empty one, or a loss that ended above its start.
    """
    if volumes.non_finite:
        return (
            f"{volumes.non_finite} of the {volumes.volumes} volume(s) written hold NaN or Inf "
            "voxels"
        )
    if volumes.volumes and not volumes.peak > 0:
        return (
            "the volume written is zero over the whole field of view (no Gaussian is left "
            "inside it)"
        )
    if math.isfinite(first_loss) and not last_loss <= first_loss:
        return (
            f"the loss ended at {last_loss:.4g}, above the {first_loss:.4g} it started at "
            "(the fit made the reconstruction worse)"
        )
    return None


def check_fit(volumes: VolumeRecord, first_loss: float, last_loss: float, folder=None) -> None:
    """Raise :class:`FitFailed` with :func:`fit_failure`'s line when the fit is no result
    (naming ``folder``, where its files were written for inspection, when given)."""
    reason = fit_failure(volumes, first_loss, last_loss)
    if reason is not None:
        where = "" if folder is None else f" (its files, for inspection: {folder})"
        raise FitFailed(f"the fit failed: {reason}{where}")
