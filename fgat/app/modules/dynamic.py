"""DynamicModule: the dynamic stage (:class:`~fgat.recon.DynamicReconstruction`) as a
Lightning run; each hook calls the engine and logs what it returns."""

from __future__ import annotations

import math
from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.utilities import rank_zero_info

from fgat.app.modules.shell import flat_settings, log_step, plain_hyperparameters, settings
from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.recon import DynamicReconstruction, DynamicSettings, load_static
from fgat.recon.names import PROGRESS_PSNR, PSNR
from fgat.recon.plateau import LossTrend


class DynamicModule(pl.LightningModule):
    """A HexPlane + MLP deformation of a static run's frozen Gaussians, fitted to every frame;
    one training step is one frame (:meth:`~fgat.recon.DynamicReconstruction.step`),
    an epoch every frame once.

    Parameters
    ----------
    static : str
        The static stage's result: its ``last.ckpt`` or results folder (see
        :func:`~fgat.recon.load_static`), read and checked by the constructor when it
        exists (``fit`` needs it; ``validate`` and ``predict`` from a dynamic checkpoint do not).
        Per-view gains the static stage estimated (``model.estimate_gains``) replace the
        datamodule's in the forward model.
    static_psf : str, optional
        PSF stack OME-TIFF to use instead of the static run's (default: the run's, else the
        datamodule's).
    hexplane : HexPlaneSettings
        The feature planes (Table S6; time nodes default to half the frames).
    width, depth, lr_planes, lr_mlp, p
        :class:`~fgat.recon.DynamicSettings` fields.
    lambda_fourier, lambda_ssim, lambda_tv, lambda_sm, lambda_l1, seed
        :class:`~fgat.recon.DynamicSettings` fields.
    frame_tolerance, revisit
        Skip converged frames (:class:`~fgat.recon.DynamicSettings`); the run stops
        once every frame has converged (logged as ``frames/converged_at_step``).

    Raises
    ------
    ValueError
        A setting out of its range, naming it (``model.lr_planes must be a positive number``).
    """

    per_frame = True  # the datamodule serves one step per frame, T per epoch

    def __init__(
        self,
        static: str,
        static_psf: str | None = None,
        hexplane: HexPlaneSettings = HexPlaneSettings(),
        width: int = 128,
        depth: int = 2,
        lr_planes: float = 1e-2,
        lr_mlp: float = 1e-3,
        p: int = 1,
        lambda_fourier: float = 0.0,
        lambda_ssim: float = 0.0,
        lambda_tv: float = 1e-4,
        lambda_sm: float = 1e-3,
        lambda_l1: float = 1e-4,
        seed: int = 0,
        frame_tolerance: float = 0.0,
        revisit: int = 4,
    ) -> None:
        super().__init__()
        self.automatic_optimization = False  # the engine steps its own optimizer
        self.save_hyperparameters()
        self.settings = flat_settings(DynamicSettings, self.hparams)
        self.hexplane = settings(HexPlaneSettings, "model.hexplane", hexplane)
        plain_hyperparameters(self)
        # Read (and check) the static run now, before any data is made; a checkpoint brings G0
        # itself.
        self._static = load_static(static, static_psf) if Path(static).exists() else None
        self.engine: DynamicReconstruction | None = None
        self._state: dict | None = None  # a checkpoint's engine state, until the scene is known
        self.scene = None
        self.last_loss = math.nan
        self.stop_reason: str | None = None  # why it stopped before its step budget
        self.loss_trend = LossTrend()

    def setup(self, stage: str) -> None:
        if self.scene is None:
            self.trainer.datamodule.setup(stage)
            self.scene = self.trainer.datamodule.scene
            self.loss_trend = LossTrend(self.scene.n_frames)  # a pass over the frames
        if self.engine is None:
            self._build(stage)

    def _build(self, stage: str) -> None:
        """The engine from a checkpoint's state, else from the static run; says so when it uses
        the static stage's estimated gains."""
        device = self.trainer.strategy.root_device
        if self._state is not None:
            self.engine = DynamicReconstruction.from_state_dict(
                self.scene, self._state, self.settings, device
            )
        elif self._static is not None:
            self.engine = DynamicReconstruction.from_static(
                self.scene, *self._static, self.hexplane, self.settings, device
            )
        elif stage == "fit":
            raise FileNotFoundError(
                f"model.static: {self.hparams.static} does not exist (a static run's last.ckpt, "
                "or its results folder with gaussians.pt)"
            )
        else:
            rank_zero_info(
                f"fgat: {self.hparams.static} not found: G0 and the PSF come from the checkpoint"
            )
        gains = None if self.engine is None else self.engine.gains
        if gains is not None:
            rank_zero_info(
                "fgat: the dynamic stage uses the static stage's estimated per-view gains "
                f"(min {float(gains.min()):.4g}, max {float(gains.max()):.4g}) instead of the "
                "data's"
            )

    def configure_optimizers(self):
        return self.engine.optimizer

    def forward(self, t: float):
        """The volume ``V_t`` ``(Z, Y, X)`` at normalised time ``t`` (measurement units)."""
        return self.engine.volume_at(t)

    def on_fit_start(self) -> None:
        if self.scene.n_frames == 1:
            rank_zero_info(
                "fgat: the data has a single frame: dynamic stage skipped (nothing moves); the "
                "static stage's Gaussians G0 are the result"
            )
            self.trainer.should_stop = True

    def training_step(self, batch, batch_idx) -> None:
        result = self.engine.step(self.optimizers())
        log_step(self, result)
        if "frames" in result.events:
            self.stop_reason = (
                "every frame's last visit changed its loss by less than frame_tolerance = "
                f"{self.settings.frame_tolerance:g} of what it has lost since its first"
            )
            rank_zero_info(
                f"fgat: step {self.global_step}: {self.stop_reason}: the dynamic stage has "
                "converged and stops"
            )
            self.trainer.should_stop = True

    def validation_step(self, batch, batch_idx) -> None:
        metrics = self.engine.evaluate()
        self.log_dict(metrics)
        if PSNR in metrics:
            self.log(PROGRESS_PSNR, metrics[PSNR], prog_bar=True)

    def predict_step(self, batch, batch_idx) -> dict:
        volume = self.engine.volumes([float(batch["time"])])[0] * self.scene.scale
        return {"index": int(batch["index"]), "time": float(batch["time"]), "volume": volume}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["reconstruction"] = self.engine.state_dict()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """A checkpoint is self-contained: G0, PSF, gains and field come back without the static
        run."""
        self._state, self.engine = checkpoint["reconstruction"], None
        if self.scene is not None:
            self._build("resume")
