"""The datamodule side of a :class:`~fgat.recon.Scene`.

A :class:`SceneDataModule` builds the scene once and serves step indices: an endless stream to
the static stage, ``T`` per epoch to a module that declares ``per_frame = True`` (the dynamic
stage, whose engine picks each step's frame); validation one item (the engine evaluates every
frame), prediction the times to render.
"""

from __future__ import annotations

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader, IterableDataset

from fgat._core.validation import check_number
from fgat.recon.scene import Scene


class StepIndices(IterableDataset):
    """An endless stream of step indices: one static iteration per training step."""

    def __iter__(self):
        step = 0
        while True:
            yield torch.tensor(step)
            step += 1


class SceneDataModule(pl.LightningDataModule):
    """A datamodule that builds one :class:`~fgat.recon.Scene` on its first ``setup``
    (:meth:`make_scene`); prediction renders the normalised times in ``predict_times`` (default:
    the frames' times).

    Parameters
    ----------
    frame_interval_s : float, optional
        Seconds between consecutive frames of a sequence: the time axis of the volume series
        written (``data.frame_interval_s``); without it that axis counts frames.
    """

    def __init__(self, frame_interval_s: float | None = None) -> None:
        super().__init__()
        self.scene: Scene | None = None
        self.predict_times: list[float] | None = None
        self.frame_interval_s = (
            None
            if frame_interval_s is None
            else check_number("data.frame_interval_s", frame_interval_s, above=0.0)
        )

    def make_scene(self) -> Scene:
        raise NotImplementedError

    def setup(self, stage: str | None = None) -> None:
        if self.scene is None:
            self.scene = self.make_scene()
            self.scene.frame_interval_s = self.frame_interval_s

    def _per_frame(self) -> bool:
        return bool(getattr(getattr(self.trainer, "lightning_module", None), "per_frame", False))

    def train_dataloader(self) -> DataLoader:
        steps = torch.arange(self.scene.n_frames) if self._per_frame() else StepIndices()
        return DataLoader(steps, batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return DataLoader([torch.tensor(0)], batch_size=None)

    def predict_dataloader(self) -> DataLoader:
        times = (
            self.predict_times
            if self.predict_times is not None
            else self.scene.sequence()[1].tolist()
        )
        items = [
            {"index": torch.tensor(k), "time": torch.tensor(float(t), dtype=torch.float64)}
            for k, t in enumerate(times)
        ]
        return DataLoader(items, batch_size=None)
