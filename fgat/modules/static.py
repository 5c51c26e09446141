"""StaticModule: the static stage (Notes S3.1, S3.2, S3.5.2) with the optics held fixed (3DGAT).

One training step is one static iteration: voxelize the Gaussians (Eq. S16), project them with
the cached FLFM operator (Eq. S52), compare with the measured views (Eq. S27), update. The
module takes its measurement, PSF stack and grid from the datamodule's ``scene``.
"""

from __future__ import annotations

import math
import time

import lightning.pytorch as pl
import torch
from lightning.pytorch.utilities import rank_zero_info

from fgat.deconvolution import deconvolve
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.densify import DensificationStrategy
from fgat.losses import static_loss
from fgat.metrics import compare_volumes
from fgat.modules.guards import (check_gradients, check_loss_terms, dataclass_options, log_loss_terms, require,
                                 require_non_negative, require_positive, synchronize)
from fgat.optics.estimation import OpticsEstimation, psf_errors, remove_scene_gauge, run_event
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.resources import check_memory, deconvolution_memory, operator_memory

BASELINE_KEYS = {"psnr": "psnr_volume", "ssim": "ssim_volume", "ssim_xy": "ssim_mip_xy"}


class StaticModule(pl.LightningModule):
    """Canonical Gaussians fitted to one FLFM frame through a fixed PSF stack.

    Parameters
    ----------
    n_gaussians : int
        Initial number of Gaussians.
    init : {"shb", "random"}
        Seed the Gaussians where an SHB reconstruction is bright, or uniformly.
    init_iterations : int
        SHB iterations for the ``"shb"`` initialisation.
    init_scale : float
        Initial scale of every Gaussian, lateral voxels.
    scale_range : (float, float)
        ``(s_min, s_max)`` of Eq. S15 in lateral voxels.
    lr_means, lr_scales, lr_quats, lr_intensities : float
        Adam learning rates (means in um per step; the others on the raw parameters).
    p : int
        Pixel loss exponent of Eq. S23 (1: MAE, 2: MSE).
    lambda_fourier, lambda_ssim : float
        ``lambda_F^0`` (annealed by Eq. S28 over ``trainer.max_steps``) and ``lambda_S``.
    densification : dict, optional
        :class:`~fgat.gaussians.densify.DensificationStrategy` fields; ``{"enabled": False}``
        turns it off.
    optics : dict, optional
        :class:`~fgat.optics.estimation.OpticsEstimation` fields: JPGM self-estimation of the
        Zernike coefficients and/or lenslet shifts (``estimate``: none, shifts, zernike, joint),
        starting from the optics the datamodule's PSF was made with.
    baseline_iterations : int
        SHB iterations of the baseline every validation compares against (0: none).
    seed : int
        Seed of the initialisation.

    Raises
    ------
    ValueError
        A setting out of its range (naming it: ``model.lr_means must be a positive number``), or
        more Gaussians than the memory holds (:func:`gaussian_bytes`; the grid, operator and SHB
        are counted too in :meth:`setup`, before SHB runs).
    """

    def __init__(self, n_gaussians: int = 2000, init: str = "shb", init_iterations: int = 20,
                 init_scale: float = 1.0, scale_range: tuple[float, float] = (0.8, 20.0), lr_means: float = 0.02,
                 lr_scales: float = 0.01, lr_quats: float = 0.005, lr_intensities: float = 0.02, p: int = 1,
                 lambda_fourier: float = 0.0, lambda_ssim: float = 0.0, densification: dict | None = None,
                 optics: dict | None = None, baseline_iterations: int = 50, seed: int = 0) -> None:
        super().__init__()
        require(init in ("shb", "random"), "model.init", init, "'shb' or 'random'")
        require(n_gaussians >= 1, "model.n_gaussians", n_gaussians, "a positive integer")
        require(init != "shb" or init_iterations >= 1, "model.init_iterations", init_iterations,
                "a positive integer (SHB iterations of the 'shb' initialisation)")
        require(len(scale_range) == 2 and 0 < scale_range[0] < scale_range[1], "model.scale_range",
                list(scale_range), "[s_min, s_max] with 0 < s_min < s_max (lateral voxels)")
        require_positive("model", init_scale=init_scale, lr_means=lr_means, lr_scales=lr_scales, lr_quats=lr_quats,
                         lr_intensities=lr_intensities)
        require(scale_range[0] <= init_scale <= scale_range[1], "model.init_scale", init_scale,
                f"within model.scale_range {list(scale_range)} (lateral voxels)")
        require(p in (1, 2), "model.p", p, "1 (MAE) or 2 (MSE)")
        require_non_negative("model", lambda_fourier=lambda_fourier, lambda_ssim=lambda_ssim,
                             baseline_iterations=baseline_iterations)
        self.densification = densification_strategy(densification)
        self.estimation = dataclass_options("model.optics", OpticsEstimation, optics)
        check_memory(f"model.n_gaussians = {n_gaussians} Gaussians", gaussian_bytes(n_gaussians, window_voxels(
            init_scale, math.inf)), hint="lower model.n_gaussians")
        self.save_hyperparameters()
        self.jpgm: JPGM | None = None
        self.cloud: GaussianCloud | None = None
        self._operator: FLFMOperator | None = None
        self.baseline_scores: dict[str, float] = {}
        self.scene = None
        self.last_loss = math.nan
        # On phantoms with self-estimation: the true PSF stack (optics errors, figures); not a buffer.
        self.true_psf: torch.Tensor | None = None

    # ------------------------------------------------------------------ set-up
    def setup(self, stage: str) -> None:
        if self.cloud is not None:
            return
        datamodule = self.trainer.datamodule
        datamodule.setup(stage)
        scene = self.scene = datamodule.scene
        # Copies: the PSF buffer follows JPGM self-estimation and must not write into the scene.
        self.register_buffer("measurement", torch.tensor(scene.measurement, dtype=torch.float32))
        self.register_buffer("psf", torch.tensor(scene.psf, dtype=torch.float32))
        shape = scene.volume_shape
        dz, _, dx = scene.voxel_size_um
        shb = self.hparams.init == "shb" or self.hparams.baseline_iterations > 0
        check_memory(f"{self.hparams.n_gaussians} Gaussians on a {shape} (Z, Y, X) grid with the forward model of "
                     f"{len(scene.psf)} views" + (" and SHB" if shb else ""),
                     gaussian_bytes(self.hparams.n_gaussians, window_voxels(self.hparams.init_scale, dz / dx))
                     + (deconvolution_memory if shb else operator_memory)(scene.psf.shape, shape),
                     hint="lower model.n_gaussians or the grid size", device=self.trainer.strategy.root_device)
        snapshots = self._shb_snapshots(shape)
        self.register_buffer("baseline", snapshots.get(self.hparams.baseline_iterations, torch.zeros(shape)))
        self.cloud = GaussianCloud(shape, scene.voxel_size_um, scale_range=tuple(self.hparams.scale_range))
        if self.hparams.init == "shb":
            self.cloud.from_volume(snapshots[self.hparams.init_iterations].numpy(), self.hparams.n_gaussians,
                                   scale=self.hparams.init_scale, seed=self.hparams.seed)
        else:
            self.cloud.random(self.hparams.n_gaussians, scale=self.hparams.init_scale, seed=self.hparams.seed)
        if self.estimation.enabled:
            if scene.optics is None:
                raise ValueError("model.optics.estimate needs a PSF made from optics (PhantomDataModule psf 'true' "
                                 "or 'ideal', or FLFMDataModule with a system), not a PSF file")
            self.jpgm = JPGM.with_parameters(**scene.optics)
            self._optics_optimizer = self.estimation.optimizer(self.jpgm)
        if scene.truth is not None and self.hparams.baseline_iterations:
            scores = compare_volumes(self.baseline.numpy(), scene.truth)
            self.baseline_scores = {f"val/{name}_shb": scores[key] for key, name in BASELINE_KEYS.items()}

    def _shb_snapshots(self, shape: tuple[int, int, int]) -> dict[int, torch.Tensor]:
        """SHB reconstructions of the measurement at the baseline and initialisation iteration
        counts (one run), on the accelerator; empty when neither is wanted."""
        wanted = {self.hparams.baseline_iterations} - {0}
        if self.hparams.init == "shb":
            wanted.add(self.hparams.init_iterations)
        if not wanted:
            return {}
        device = self.trainer.strategy.root_device  # the accelerator, before the module moves there
        snapshots = {}
        deconvolve(self.measurement.to(device), FLFMOperator(self.psf.to(device), shape), max(wanted), method="shb",
                   callback=lambda k, v: snapshots.__setitem__(k + 1, v.float().cpu()) if k + 1 in wanted else None)
        return snapshots

    @property
    def operator(self) -> FLFMOperator:
        """The cached forward operator, rebuilt only when the PSF moves to another device."""
        if self._operator is None or self._operator.device != self.psf.device:
            self._operator = FLFMOperator(self.psf, tuple(self.cloud.shape))
        return self._operator

    def configure_optimizers(self):
        h = self.hparams
        groups = [{"params": [self.cloud.means], "lr": h.lr_means, "name": "means"},
                  {"params": [self.cloud.raw_scales], "lr": h.lr_scales, "name": "scales"},
                  {"params": [self.cloud.raw_quats], "lr": h.lr_quats, "name": "quats"},
                  {"params": [self.cloud.raw_intensities], "lr": h.lr_intensities, "name": "intensities"}]
        return torch.optim.Adam(groups, eps=1e-15)

    # ------------------------------------------------------------------ steps
    def forward(self) -> torch.Tensor:
        """The current volume ``(Z, Y, X)`` in normalised measurement units."""
        return self.cloud()

    def on_train_batch_start(self, batch, batch_idx) -> None:
        self._step_started = time.perf_counter()

    def training_step(self, batch, batch_idx):
        start = time.perf_counter()
        volume = self.cloud()
        synchronize(self.device)
        voxelized = time.perf_counter()
        prediction = self.operator.forward(volume)
        synchronize(self.device)
        projected = time.perf_counter()
        terms = static_loss(prediction, self.measurement, step=self.global_step,
                            total_steps=self.trainer.max_steps, p=self.hparams.p,
                            lambda_fourier=self.hparams.lambda_fourier, lambda_ssim=self.hparams.lambda_ssim)
        self.last_loss = check_loss_terms(terms, f"step {self.global_step}")
        log_loss_terms(self, terms)
        self.log_dict({"gaussians/count": float(self.cloud.count), "time/voxelize_ms": 1e3 * (voxelized - start),
                       "time/projection_ms": 1e3 * (projected - voxelized)})
        return terms["total"]

    def on_before_optimizer_step(self, optimizer) -> None:
        check_gradients(self.cloud.named_parameters(), self.global_step)

    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        synchronize(self.device)
        self.log("time/step_ms", 1e3 * (time.perf_counter() - self._step_started))
        if self.estimation.due(self.global_step):
            self.estimate_optics()

    def on_fit_start(self) -> None:
        if not self.estimation.enabled:
            rank_zero_info("fgat: optics fixed (model.optics.estimate = none): JPGM self-estimation skipped")
            return
        metrics = optics_metrics(self.jpgm)  # the starting point of the trajectories (Fig. S10)
        if self.scene.truth_optics is not None:
            metrics.update({key.replace("zernike/", "zernike_gt/").replace("shift/", "shift_gt/"): value
                            for key, value in parameter_metrics(*self.true_parameters()).items()})
            with torch.no_grad():
                self.true_psf = JPGM.with_parameters(**{**self.scene.optics, **self.scene.truth_optics},
                                                     zernike_indices=self.jpgm.zernike_indices).to(self.device)()
            initial = torch.as_tensor(self.scene.psf, device=self.device, dtype=self.true_psf.dtype)
            metrics.update(psf_errors(initial, self.true_psf, "psf/error_initial"))
        log_event(self.loggers, metrics, self.global_step)

    def true_parameters(self) -> tuple[tuple[int, ...], torch.Tensor, torch.Tensor, torch.Tensor]:
        """The phantom's true optics on this run's Zernike indices and views (indices, c, b, s)."""
        truth, indices, views = self.scene.truth_optics, self.jpgm.zernike_indices, self.jpgm.n_views
        coefficients = torch.tensor([float(truth["zernike"].get(j, 0.0)) for j in indices])
        shifts = [torch.tensor([truth[name].get(v, [0.0, 0.0]) for v in range(views)], dtype=torch.float32)
                  for name in ("intercepts", "slopes")]
        return indices, coefficients, *shifts

    def estimate_optics(self) -> dict[str, float]:
        """One JPGM event against the current volume; the PSF buffer and operator follow it."""
        with torch.no_grad():
            volume = self.cloud()
        result = run_event(self.jpgm, volume, self.measurement, self.estimation, self._optics_optimizer)
        with torch.no_grad():
            self.psf.copy_(self.jpgm())
        self._operator = None
        metrics = {"time/jpgm_iter_ms": result["ms_per_step"], "optics/loss_before": result["loss_before"],
                   "optics/loss_after": result["loss_after"], **optics_metrics(self.jpgm)}
        if self.scene.truth_optics is not None:
            metrics.update(self._optics_errors())
        log_event(self.loggers, metrics, self.global_step)
        return result

    def _optics_errors(self) -> dict[str, float]:
        """Distance of the estimated optics to a phantom's truth: ``zernike/residual_normalized``
        ``||c - c_gt|| / ||c_gt||`` (sigma of Fig. S9a; NaN without aberration), the largest
        intercept and slope errors (pixels), also without the part a moved scene explains
        (:func:`~fgat.optics.estimation.remove_scene_gauge`), and the relative PSF errors
        (:func:`~fgat.optics.estimation.psf_errors`)."""
        jpgm = self.jpgm
        coefficients, intercepts, slopes = (t.to(jpgm.intercepts) for t in self.true_parameters()[1:])
        norm = coefficients.norm()  # no aberration (Fig. S5): sigma undefined
        residual = (jpgm.zernike_coefficients.detach() - coefficients).norm() / norm if norm > 0 else math.nan
        metrics = {"zernike/residual_normalized": float(residual)}
        offsets = jpgm.centers - jpgm.centers[:1]
        for name, estimate, truth in (("intercept", jpgm.intercepts, intercepts), ("slope", jpgm.slopes, slopes)):
            difference = estimate.detach() - truth
            metrics[f"shift/{name}_error_max_px"] = float(difference.abs().max())
            residual = remove_scene_gauge(difference, offsets)
            metrics[f"shift/{name}_error_gauge_free_max_px"] = float(residual.abs().max())
        return {**metrics, **psf_errors(self.psf, self.true_psf, "psf/error")}

    def validation_step(self, batch, batch_idx):
        if self.scene is None or self.scene.truth is None:
            return
        scores = compare_volumes(self.cloud().detach().cpu().numpy(), self.scene.truth)
        metrics = {f"val/{name}": scores[key] for key, name in BASELINE_KEYS.items()}
        self.log_dict({**metrics, **self.baseline_scores}, prog_bar=False)
        self.log("val/psnr", scores["psnr"], prog_bar=True)


def densification_strategy(options: dict | None) -> DensificationStrategy:
    """``model.densification`` as a :class:`~fgat.gaussians.densify.DensificationStrategy`, checked."""
    strategy = dataclass_options("model.densification", DensificationStrategy, options)
    require(strategy.start >= 0, "model.densification.start", strategy.start, "a step >= 0")
    require(strategy.interval >= 1, "model.densification.interval", strategy.interval, "a positive number of steps")
    require(strategy.stop >= strategy.start, "model.densification.stop", strategy.stop,
            f">= model.densification.start ({strategy.start})")
    require(strategy.max_gaussians >= 1, "model.densification.max_gaussians", strategy.max_gaussians,
            "a positive integer")
    require(0 <= strategy.min_intensity < 1, "model.densification.min_intensity", strategy.min_intensity,
            "a fraction of the largest intensity in [0, 1)")
    require_non_negative("model.densification", grad_threshold=strategy.grad_threshold)
    require_positive("model.densification", split_scale=strategy.split_scale)
    return strategy


def window_voxels(scale: float, axial_ratio: float) -> int:
    """Voxels in the voxelizer's window around a Gaussian of ``scale`` lateral voxels (its 3-sigma
    box, at least the smallest window), the axial voxel being ``axial_ratio`` lateral voxels."""
    lateral = 2 * math.floor(3 * scale + 0.5) + 1
    axial = 2 * max(1, math.floor(3 * scale / axial_ratio + 0.5)) + 1
    return lateral * lateral * axial


def gaussian_bytes(count: int, window: int) -> int:
    """Memory of ``count`` Gaussians in a training step: 11 float32 parameters with their
    gradients and two Adam moments, and per window voxel what the voxelizer keeps for the
    backward pass (quadratic form, exponential, values, mask, int64 voxel index: about 32 bytes).
    A lower bound: windows grow when the Gaussians do."""
    return count * (11 * 4 * 4 + 32 * window)


def log_event(loggers, metrics: dict[str, float], step: int) -> None:
    """Log metrics of a one-off event once, at ``step`` (``self.log`` would repeat the last value)."""
    for logger in loggers:
        logger.log_metrics(metrics, step=step)


def parameter_metrics(indices, coefficients, intercepts, slopes) -> dict[str, float]:
    """``zernike/c{j}`` (waves), ``shift/b{v}_y``, ``shift/b{v}_x``, ``shift/s{v}_y``, ``shift/s{v}_x`` (pixels)."""
    metrics = {f"zernike/c{j}": float(c) for j, c in zip(indices, coefficients.detach().tolist())}
    for letter, values in (("b", intercepts), ("s", slopes)):
        for v, (row, col) in enumerate(values.detach().tolist()):
            metrics[f"shift/{letter}{v}_y"], metrics[f"shift/{letter}{v}_x"] = row, col
    return metrics


def optics_metrics(jpgm: JPGM) -> dict[str, float]:
    """:func:`parameter_metrics` of a JPGM's current parameters."""
    return parameter_metrics(jpgm.zernike_indices, jpgm.zernike_coefficients, jpgm.intercepts, jpgm.slopes)
