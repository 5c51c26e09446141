"""StaticModule: the static stage (:class:`~fgat.recon.StaticReconstruction`) as a
Lightning run; each hook calls the engine and logs what it returns."""

from __future__ import annotations

import math

import lightning.pytorch as pl
from lightning.pytorch.utilities import rank_zero_info

from fgat._core.resources import check_memory
from fgat.app.modules.shell import (
    flat_settings,
    log_event,
    log_step,
    plain_hyperparameters,
    settings,
)
from fgat.gaussians.densify import Densification
from fgat.recon import StaticReconstruction, StaticSettings
from fgat.recon.costs import gaussian_bytes, window_voxels
from fgat.recon.estimation import OpticsEstimation
from fgat.recon.names import CROP_SAVED, PROGRESS_PSNR, PSNR
from fgat.recon.plateau import LossTrend


class StaticModule(pl.LightningModule):
    """Canonical Gaussians fitted to the datamodule's scene; one training step is one
    :meth:`~fgat.recon.StaticReconstruction.step`.

    Parameters
    ----------
    n_gaussians, init, init_iterations, init_scale, scale_range, lr_means, lr_scales, lr_quats, \
lr_intensities, p, lambda_fourier, lambda_ssim, baseline_iterations, seed, estimate_gains, \
lr_gains, holdout, crop, crop_margin_planes
        :class:`~fgat.recon.StaticSettings` fields (``lambda_fourier`` anneals over
        ``trainer.max_steps``; ``estimate_gains`` fits the per-view gains too, logged as
        ``gain/view{v}``; ``holdout`` leaves that share of the pixels out of the fit and logs
        their loss as ``loss/holdout``, for :class:`~fgat.callbacks.HoldoutStopping`; ``crop``
        fits on the box where the SHB pre-pass finds signal, logged as ``crop/voxels`` and
        ``crop/voxels_saved``).
    densification : Densification
        When the Gaussian set grows and shrinks (``{enabled: false}``: never).
    optics : OpticsEstimation
        JPGM self-estimation (``estimate``: none, shifts, zernike, joint), starting from the optics
        the datamodule's PSF was made with; with ``identifiability`` (default) the standard errors
        of the estimated parameters at the end, terms above ``stderr_tolerance`` flagged
        (:func:`~fgat.app.callbacks.artifacts.identifiability_files`).

    Raises
    ------
    ValueError
        A setting out of its range, naming it (``model.lr_means must be a positive number``), or
        more Gaussians than the memory holds (the grid, operator and SHB are counted once the
        data is known, before SHB runs).
    """

    per_frame = False  # the datamodule serves step indices

    def __init__(
        self,
        n_gaussians: int = 2000,
        init: str = "shb",
        init_iterations: int = 20,
        init_scale: float = 1.0,
        scale_range: tuple[float, float] = (0.8, 20.0),
        lr_means: float = 0.02,
        lr_scales: float = 0.01,
        lr_quats: float = 0.005,
        lr_intensities: float = 0.02,
        p: int = 1,
        lambda_fourier: float = 0.0,
        lambda_ssim: float = 0.0,
        densification: Densification = Densification(),
        optics: OpticsEstimation = OpticsEstimation(),
        baseline_iterations: int = 50,
        seed: int = 0,
        estimate_gains: bool = False,
        lr_gains: float = 0.01,
        holdout: float = 0.0,
        crop: float = 0.0,
        crop_margin_planes: int = 3,
    ) -> None:
        super().__init__()
        self.automatic_optimization = False  # the engine steps its own optimizer
        self.save_hyperparameters()
        self.settings = flat_settings(StaticSettings, self.hparams)
        self.densification = settings(Densification, "model.densification", densification)
        self.estimation = settings(OpticsEstimation, "model.optics", optics)
        plain_hyperparameters(self)
        check_memory(
            f"model.n_gaussians = {n_gaussians} Gaussians",
            gaussian_bytes(n_gaussians, window_voxels(init_scale, math.inf)),
            hint="lower model.n_gaussians",
        )
        self.engine: StaticReconstruction | None = None
        self.last_loss = self.last_holdout = math.nan
        self.loss_trend = LossTrend()  # the fit's first and last loss, for the end's check

    @property
    def scene(self):
        return self.engine.scene

    def setup(self, stage: str) -> None:
        if self.engine is None:
            self.trainer.datamodule.setup(stage)
            self.engine = StaticReconstruction(
                self.trainer.datamodule.scene,
                self.settings,
                self.densification,
                self.estimation,
                total_steps=self.trainer.max_steps,
                device=self.trainer.strategy.root_device,
            )

    def configure_optimizers(self):
        return self.engine.optimizer

    def forward(self):
        """The current volume ``(Z, Y, X)`` in normalised measurement units."""
        return self.engine.volume()

    def on_fit_start(self) -> None:
        if not self.densification.enabled:
            rank_zero_info("fgat: densification disabled: the Gaussian set stays fixed")
        if self.scene.truth is None and self.settings.baseline_iterations:
            rank_zero_info(
                "fgat: no truth to compare with: the SHB baseline (model.baseline_iterations) "
                "is skipped"
            )
        if not self.estimation.enabled:
            rank_zero_info(
                "fgat: optics fixed (model.optics.estimate = none): JPGM self-estimation skipped"
            )
        crop = self.engine.crop_metrics()
        if crop:
            rank_zero_info(
                f"fgat: the Gaussians are fitted on {self.engine.fit_scene.volume_shape} of the "
                f"{self.scene.volume_shape} (Z, Y, X) grid, where the SHB pre-pass finds signal "
                f"(model.crop): {100 * crop[CROP_SAVED]:.0f}% of the voxels left out"
            )
        if self.trainer.ckpt_path is None:  # a resumed run has them from the run it continues
            log_event(self.loggers, {**crop, **self.engine.optics_start()}, self.global_step)

    def training_step(self, batch, batch_idx) -> None:
        log_step(self, self.engine.step(self.optimizers()))

    def validation_step(self, batch, batch_idx) -> None:
        metrics = self.engine.evaluate()
        if metrics:
            self.log_dict(metrics)
            self.log(PROGRESS_PSNR, metrics[PSNR], prog_bar=True)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["reconstruction"] = self.engine.state_dict()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.engine.load_state_dict(checkpoint["reconstruction"])
