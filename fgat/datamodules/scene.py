"""What a reconstruction needs from its data: measurement, optics, grid (and truth on phantoms)."""

from __future__ import annotations

from dataclasses import dataclass

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset


@dataclass
class FLFMScene:
    """One reference-frame measurement and the fixed optics it is reconstructed with.

    Attributes
    ----------
    measurement : numpy.ndarray
        ``(V, Y, X)`` per-view images, background subtracted, clipped at zero and divided by
        ``scale`` (maximum 1).
    scale : float
        Counts per unit of ``measurement`` (to report results in counts).
    psf : numpy.ndarray
        ``(V, Z, h, w)`` PSF stack used by the forward model.
    voxel_size_um : (dz, dy, dx)
        Grid spacing of the reconstruction.
    truth : numpy.ndarray or None
        ``(Z, Y, X)`` ground truth on phantoms.
    name : str
        Label for logs.
    optics : dict or None
        How ``psf`` was made, when it came from a JPGM: keyword arguments of
        :meth:`fgat.optics.psf.JPGM.with_parameters` (``system``, ``depths_um``, ``centers_px``,
        ``zernike``, ``intercepts``, ``slopes``), the starting point of JPGM self-estimation.
    truth_optics : dict or None
        On phantoms, the true ``zernike`` ({Noll index: waves}), ``intercepts`` and ``slopes``
        ({view: [row, col]} pixels) the measurement was simulated with.
    """

    measurement: np.ndarray
    scale: float
    psf: np.ndarray
    voxel_size_um: tuple[float, float, float]
    truth: np.ndarray | None = None
    name: str = "scene"
    optics: dict | None = None
    truth_optics: dict | None = None

    @property
    def volume_shape(self) -> tuple[int, int, int]:
        return (self.psf.shape[1], *self.measurement.shape[1:])


def normalized_measurement(views: np.ndarray, background: float) -> tuple[np.ndarray, float]:
    """Subtract the camera offset, clip at zero, divide by the maximum: ``(views, scale)``."""
    views = np.clip(np.asarray(views, dtype=np.float32) - background, 0, None)
    scale = float(views.max())
    if scale <= 0:
        raise ValueError(f"the measurement is zero everywhere after subtracting the background ({background})")
    return views / scale, scale


class StepIndices(IterableDataset):
    """An endless stream of step indices: one static iteration per training step."""

    def __iter__(self):
        step = 0
        while True:
            yield torch.tensor(step)
            step += 1


class SceneDataModule(pl.LightningDataModule):
    """A datamodule that builds one :class:`FLFMScene` on its first ``setup`` (:meth:`make_scene`)
    and serves a step index per training step and one validation item."""

    def __init__(self) -> None:
        super().__init__()
        self.scene: FLFMScene | None = None

    def make_scene(self) -> FLFMScene:
        raise NotImplementedError

    def setup(self, stage: str | None = None) -> None:
        if self.scene is None:
            self.scene = self.make_scene()

    def train_dataloader(self) -> DataLoader:
        return DataLoader(StepIndices(), batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return DataLoader([torch.tensor(0)], batch_size=None)
