"""What a reconstruction needs from its data: measurement, optics, grid (and truth on phantoms).

A :class:`SceneDataModule` serves one step index per training step to the static stage, and
``(index, time, views)`` frames, one per step and every frame once per epoch in a shuffled
order, to a module that declares ``per_frame = True`` (the dynamic stage).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset


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
    frames : numpy.ndarray or None
        A sequence's per-view images ``(T, V, Y, X)``, normalised with the reference frame's
        ``scale``; ``measurement`` is ``frames[reference]``. ``None`` for a single frame.
    times : numpy.ndarray or None
        Normalised acquisition times ``(T,)`` in [0, 1] (first frame 0, last frame 1).
    reference : int
        Index of the reference frame (``t_ref``, the static stage's frame).
    truth_frames : numpy.ndarray or None
        On dynamic phantoms, the truth ``(T, Z, Y, X)`` of every frame.
    truth_at : callable or None
        On dynamic phantoms, ``truth_at(times) -> (T', Z, Y, X)``: the truth at any normalised
        times (e.g. between frames).
    """

    measurement: np.ndarray
    scale: float
    psf: np.ndarray
    voxel_size_um: tuple[float, float, float]
    truth: np.ndarray | None = None
    name: str = "scene"
    optics: dict | None = None
    truth_optics: dict | None = None
    frames: np.ndarray | None = None
    times: np.ndarray | None = None
    reference: int = 0
    truth_frames: np.ndarray | None = None
    truth_at: Callable[[np.ndarray], np.ndarray] | None = None

    @property
    def volume_shape(self) -> tuple[int, int, int]:
        return (self.psf.shape[1], *self.measurement.shape[1:])

    @property
    def n_frames(self) -> int:
        return 1 if self.frames is None else len(self.frames)

    def sequence(self) -> tuple[np.ndarray, np.ndarray]:
        """``(frames (T, V, Y, X), times (T,))``; a single frame is a sequence of one at t = 0."""
        if self.frames is None:
            return self.measurement[None], np.zeros(1)
        return self.frames, self.times


def normalized_measurement(views: np.ndarray, background: float,
                           reference: int | None = None) -> tuple[np.ndarray, float]:
    """Subtract the camera offset, clip at zero and divide by the maximum of the views ``(V, Y, X)``,
    or of frame ``reference`` of a sequence ``(T, V, Y, X)`` (every frame by the same scale):
    ``(views, scale)``."""
    views = np.clip(np.asarray(views, dtype=np.float32) - background, 0, None)
    scale = float(views.max() if reference is None else views[reference].max())
    if scale <= 0:
        raise ValueError(f"the measurement is zero everywhere after subtracting the background ({background})")
    return views / scale, scale


def reference_index(frame: int | None, n_frames: int, source: str) -> int:
    """The reference frame: ``frame`` (checked) or the middle one, ``T // 2`` (Note S3)."""
    index = n_frames // 2 if frame is None else int(frame)
    if not 0 <= index < n_frames:
        raise ValueError(f"{source}: reference frame {index} is outside the {n_frames} frames")
    return index


class StepIndices(IterableDataset):
    """An endless stream of step indices: one static iteration per training step."""

    def __iter__(self):
        step = 0
        while True:
            yield torch.tensor(step)
            step += 1


class Frames(Dataset):
    """A scene's frames as ``{"index", "time", "views"}`` items."""

    def __init__(self, scene: FLFMScene) -> None:
        self.frames, self.times = scene.sequence()

    def __len__(self) -> int:
        return len(self.times)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {"index": torch.tensor(index), "time": torch.tensor(float(self.times[index]), dtype=torch.float64),
                "views": torch.from_numpy(np.ascontiguousarray(self.frames[index]))}


class SceneDataModule(pl.LightningDataModule):
    """A datamodule that builds one :class:`FLFMScene` on its first ``setup`` (:meth:`make_scene`).

    Training serves a step index per step (static stage) or shuffled frames (a module with
    ``per_frame = True``); validation one item or every frame; prediction the normalised times
    in ``predict_times`` (default: the frames' times).
    """

    def __init__(self) -> None:
        super().__init__()
        self.scene: FLFMScene | None = None
        self.predict_times: list[float] | None = None

    def make_scene(self) -> FLFMScene:
        raise NotImplementedError

    def setup(self, stage: str | None = None) -> None:
        if self.scene is None:
            self.scene = self.make_scene()

    def _per_frame(self) -> bool:
        return bool(getattr(getattr(self.trainer, "lightning_module", None), "per_frame", False))

    def train_dataloader(self) -> DataLoader:
        if self._per_frame():
            return DataLoader(Frames(self.scene), batch_size=None, shuffle=True)
        return DataLoader(StepIndices(), batch_size=None)

    def val_dataloader(self) -> DataLoader:
        if self._per_frame():
            return DataLoader(Frames(self.scene), batch_size=None)
        return DataLoader([torch.tensor(0)], batch_size=None)

    def predict_dataloader(self) -> DataLoader:
        times = self.predict_times if self.predict_times is not None else self.scene.sequence()[1].tolist()
        items = [{"index": torch.tensor(k), "time": torch.tensor(float(t), dtype=torch.float64)}
                 for k, t in enumerate(times)]
        return DataLoader(items, batch_size=None)
