"""The static stage (Notes S3.1, S3.2, S3.5.2) as a plain object: canonical Gaussians fitted to
one FLFM frame, with the optics fixed (3DGAT) or self-estimated by JPGM events (4DGAT).

One :meth:`StaticReconstruction.step` is one static iteration: voxelize the Gaussians (Eq. S16),
project them with the cached FLFM operator (Eq. S52), compare with the measured views (Eq. S27),
update; then densify when due and run a JPGM event when due. Nothing is logged: every call
returns what happened as data.
"""

from __future__ import annotations

import itertools
import time
import warnings
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch
from torch import Tensor, nn

from fgat._core.devices import adam
from fgat._core.resources import available_memory, check_memory
from fgat._core.validation import require, require_non_negative, require_positive
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.densify import Densification, DensificationStrategy
from fgat.optics.acquisition import MeasuredOperator, crop_guard
from fgat.optics.operator import operator_memory
from fgat.optics.psf import JPGM
from fgat.recon import names
from fgat.recon.costs import deconvolution_memory, gaussian_bytes, window_voxels
from fgat.recon.crop import Box, box_voxels, crop_scene, pad_volume, psf_reach, signal_box
from fgat.recon.deconvolution import deconvolve
from fgat.recon.estimation import (
    ESTIMATES,
    LEARNING_RATES,
    DepthChunks,
    OpticsEstimation,
    psf_errors,
    run_event,
)
from fgat.recon.guards import descend, synchronize
from fgat.recon.holdout import holdout_split
from fgat.recon.joint_step import joint_correction
from fgat.recon.losses import pixel_loss, static_loss
from fgat.recon.metrics import compare_volumes, registered_psnr, registration_window, scoring_pair
from fgat.recon.optics_report import (
    Identifiability,
    identifiability,
    identifiability_plan,
    optics_errors,
    optics_metrics,
    parameter_metrics,
)
from fgat.recon.scene import Scene


@dataclass(frozen=True)
class StaticSettings:
    """How the canonical Gaussians are initialised and fitted.

    Attributes
    ----------
    n_gaussians : int
        Initial number of Gaussians.
    init : {"shb", "random"}
        Seed the Gaussians where an SHB reconstruction sends light into the views (its value
        times the voxel's :meth:`StaticReconstruction.visibility`, so the guard band gets the
        seeds its light calls for), with the SHB value as intensity; or uniformly.
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
        ``lambda_F^0`` (annealed by Eq. S28 over the run's steps) and ``lambda_S``.
    baseline_iterations : int
        SHB iterations of the baseline every evaluation compares against (0: none); computed
        only when the scene has a truth to compare both with (measured data skips it).
    seed : int
        Seed of the initialisation.
    estimate_gains : bool
        Estimate the per-view gains jointly with the Gaussians (see
        :meth:`StaticReconstruction.gains` for the gauge), starting from the scene's gains (or 1).
    lr_gains : float
        Adam learning rate of the per-view log-gains (log units per step).
    holdout : float
        Share of the measurement's pixels left out of the fit (drawn with ``seed``), whose
        loss every step reports as ``loss/holdout``: the signal of
        :class:`~fgat.recon.HoldoutStop`. 0: every pixel is fitted.
    crop : float
        Skip empty space (0: off): the Gaussians are fitted on the box around the voxels of the
        SHB pre-pass (the ``init_iterations`` run) at or above this fraction of its maximum,
        grown by the PSFs' lateral reach (99% of their light) and ``crop_margin_planes``
        planes (the views and PSF planes cut to it: :mod:`fgat.recon.crop`);
        :meth:`StaticReconstruction.volume` pads the result back with zeros. Axially only with
        the optics fixed (the JPGM's depth normalisation spans every plane).
    crop_margin_planes : int
        Planes kept on each side of the signal's axial extent.

    Raises
    ------
    ValueError
        A field out of its range, naming it (``lr_means must be a positive number, got -1``).
    """

    n_gaussians: int = 2000
    init: str = "shb"
    init_iterations: int = 20
    init_scale: float = 1.0
    scale_range: tuple[float, float] = (0.8, 20.0)
    lr_means: float = 0.02
    lr_scales: float = 0.01
    lr_quats: float = 0.005
    lr_intensities: float = 0.02
    p: int = 1
    lambda_fourier: float = 0.0
    lambda_ssim: float = 0.0
    baseline_iterations: int = 50
    seed: int = 0
    estimate_gains: bool = False
    lr_gains: float = 0.01
    holdout: float = 0.0
    crop: float = 0.0
    crop_margin_planes: int = 3

    def __post_init__(self) -> None:
        require(
            0 <= self.crop < 1,
            "crop",
            self.crop,
            "a fraction of the SHB pre-pass maximum in [0, 1) (0: no crop)",
        )
        require(
            self.crop_margin_planes >= 0,
            "crop_margin_planes",
            self.crop_margin_planes,
            "a number of planes >= 0",
        )
        require(self.init in ("shb", "random"), "init", self.init, "'shb' or 'random'")
        require(self.n_gaussians >= 1, "n_gaussians", self.n_gaussians, "a positive integer")
        require(
            self.init != "shb" or self.init_iterations >= 1,
            "init_iterations",
            self.init_iterations,
            "a positive integer (SHB iterations of the 'shb' initialisation)",
        )
        low_high = tuple(self.scale_range)
        require(
            len(low_high) == 2 and 0 < low_high[0] < low_high[1],
            "scale_range",
            list(low_high),
            "[s_min, s_max] with 0 < s_min < s_max (lateral voxels)",
        )
        require_positive(
            "",
            init_scale=self.init_scale,
            lr_means=self.lr_means,
            lr_scales=self.lr_scales,
            lr_quats=self.lr_quats,
            lr_intensities=self.lr_intensities,
            lr_gains=self.lr_gains,
        )
        require(
            low_high[0] <= self.init_scale <= low_high[1],
            "init_scale",
            self.init_scale,
            f"within scale_range {list(low_high)} (lateral voxels)",
        )
        require(self.p in (1, 2), "p", self.p, "1 (MAE) or 2 (MSE)")
        require(
            0 <= self.holdout <= 0.5,
            "holdout",
            self.holdout,
            "a share of the pixels in [0, 0.5] (0: none held out)",
        )
        require_non_negative(
            "",
            lambda_fourier=self.lambda_fourier,
            lambda_ssim=self.lambda_ssim,
            baseline_iterations=self.baseline_iterations,
        )


@dataclass
class StepResult:
    """What one step did.

    Attributes
    ----------
    losses : dict
        Loss terms of the step (``pix``, ``fourier``, ``ssim``, ..., ``total``), floats.
    timings_ms : dict
        Wall times of the step's parts, milliseconds.
    events : dict
        One-off events after the step, by name (``densification``: cloned/split/pruned/count;
        ``optics``: the JPGM event's metrics; ``frames``: the dynamic stage's frames all
        converged), each a dict of floats.
    count : int
        Gaussians after the step.
    metrics : dict
        Other numbers of the state after the step, by logged name (``gain/view{v}``: the
        estimated per-view gains; ``loss/holdout``: the pixel loss of the held-out pixels, with
        ``holdout``), floats.
    """

    losses: dict[str, float]
    timings_ms: dict[str, float]
    events: dict[str, dict[str, float]] = field(default_factory=dict)
    count: int = 0
    metrics: dict[str, float] = field(default_factory=dict)


class StaticReconstruction:
    """Canonical Gaussians fitted to a scene's reference frame.

    The forward model is the scene's acquisition (:class:`~fgat.optics.acquisition.
    MeasuredOperator`): its per-view gains (known, or estimated with ``estimate_gains``), its
    pixel mask (every loss term and SHB ignore masked pixels) and its guard band: the Gaussians
    live on the padded grid ``scene.grid_shape`` (corner ``scene.grid_origin``, so the output
    voxels keep their positions), and :meth:`volume` returns the central ``scene.volume_shape``.

    Parameters
    ----------
    scene : Scene
        Measurement, PSF stack, grid (and truth, true optics on phantoms).
    settings : StaticSettings
        Initialisation, learning rates, loss weights.
    densification : Densification
        When the Gaussian set grows and shrinks (``Densification(enabled=False)``: never).
    optics : OpticsEstimation
        JPGM self-estimation; anything but ``estimate="none"`` needs ``scene.optics``.
    total_steps : int
        Steps of the whole run (the Fourier weight of Eq. S28 anneals over them).
    device : torch.device or str
        Where everything is computed.

    Raises
    ------
    ValueError
        Self-estimation without optics to start from, or more than the memory holds (counted
        before SHB runs: Gaussians, operator and SHB).
    """

    def __init__(
        self,
        scene: Scene,
        settings: StaticSettings = StaticSettings(),
        densification: Densification = Densification(),
        optics: OpticsEstimation = OpticsEstimation(),
        total_steps: int = 2000,
        device: torch.device | str = "cpu",
    ) -> None:
        if optics.enabled and scene.optics is None:
            raise ValueError(
                "optics.estimate needs a PSF made from optics (a phantom's 'true' or 'ideal' PSF, "
                "or a measurement with a system), not a PSF file"
            )
        self.scene, self.settings, self.estimation = scene, settings, optics
        self.total_steps, self.device = int(total_steps), torch.device(device)
        shape = scene.grid_shape
        shb = settings.init == "shb" or settings.baseline_iterations > 0
        dz, _, dx = scene.voxel_size_um
        check_memory(
            f"{settings.n_gaussians} Gaussians on a {shape} (Z, Y, X) grid with the forward "
            f"model of {len(scene.psf)} views" + (" and SHB" if shb else ""),
            gaussian_bytes(settings.n_gaussians, window_voxels(settings.init_scale, dz / dx))
            + (deconvolution_memory if shb else operator_memory)(
                scene.psf.shape, scene.volume_shape, guard_px=scene.guard_px
            ),
            hint="lower n_gaussians or the grid size",
            device=self.device,
        )
        self._fit_on(scene)
        self._operator: MeasuredOperator | None = None
        self.log_gains: nn.Parameter | None = None
        if settings.estimate_gains:
            known = np.ones(len(scene.psf)) if scene.gains is None else scene.gains
            self.log_gains = nn.Parameter(
                torch.tensor(np.log(known), dtype=torch.float32, device=self.device)
            )
            self.log_gain_mean = float(np.log(known).mean())  # the gauge: fixed geometric mean
        snapshots = self._shb_snapshots()
        self.baseline = snapshots.get(settings.baseline_iterations)
        if self.baseline is not None:
            self.baseline = crop_guard(self.baseline, scene.guard_px).contiguous()
        self.box: Box | None = None  # the crop of the output grid the Gaussians are fitted on
        if settings.crop > 0:
            snapshots = self._crop_to_signal(snapshots[settings.init_iterations], optics)
        self.holdout_mask: Tensor | None = None
        if settings.holdout > 0:  # after SHB: the baseline and the seeds see every pixel
            self.mask, self.holdout_mask = holdout_split(
                self.mask, self.measurement.shape, settings.holdout, settings.seed, self.device
            )
        self.cloud = GaussianCloud(
            self.fit_scene.grid_shape,
            scene.voxel_size_um,
            scale_range=tuple(settings.scale_range),
            origin=self.fit_scene.grid_origin,
        )
        if settings.init == "shb":
            prepass = snapshots[settings.init_iterations]
            self.cloud.from_volume(
                prepass.numpy(),
                settings.n_gaussians,
                scale=settings.init_scale,
                seed=settings.seed,
                weights=(prepass * self.visibility()).numpy(),
            )
        else:
            self.cloud.random(settings.n_gaussians, scale=settings.init_scale, seed=settings.seed)
        self.cloud.to(self.device)
        groups = [
            {"params": [getattr(self.cloud, name)], "lr": rate, "name": label}
            for name, rate, label in (
                ("means", settings.lr_means, "means"),
                ("raw_scales", settings.lr_scales, "scales"),
                ("raw_quats", settings.lr_quats, "quats"),
                ("raw_intensities", settings.lr_intensities, "intensities"),
            )
        ]
        if self.log_gains is not None:
            groups.append({"params": [self.log_gains], "lr": settings.lr_gains, "name": "gains"})
        self.optimizer = adam(groups, eps=1e-15)
        self.densification = DensificationStrategy(densification, self.fit_scene.guard_px)
        self.jpgm: JPGM | None = None
        self.true_psf: Tensor | None = None  # the phantom's true PSF when optics are estimated
        if optics.enabled:
            self.jpgm = scene.optics.jpgm(device=self.device, method=optics.psf_method)
            self.optics_optimizer = optics.optimizer(self.jpgm)
            self.depth_chunks = DepthChunks(optics.depth_chunk, self.jpgm.n_depths, self.device)
            if scene.truth_optics is not None:
                with torch.no_grad():
                    self.true_psf = scene.truth_optics.jpgm(
                        zernike_indices=self.jpgm.zernike_indices, device=self.device
                    )()
        self.baseline_scores = {}
        if scene.truth is not None and self.baseline is not None:
            self.baseline_scores = truth_scores(self.baseline.numpy(), scene.truth, names.SHB)
        self.steps_done = 0
        self.quiet_events = 0
        self.optics_converged_at: int | None = None  # step after which JPGM events are skipped
        # the last JPGM event: its step and its entries still moving (parameter name -> count)
        self.last_event: tuple[int, dict[str, int]] | None = None

    def _fit_on(self, scene: Scene) -> None:
        """Fit the Gaussians to ``scene`` (the whole one, or its crop): its measurement, mask and
        a copy of its PSF (the PSF follows JPGM self-estimation and must not write into it)."""
        self.fit_scene = scene
        self.measurement = torch.tensor(scene.measurement, dtype=torch.float32, device=self.device)
        self.mask = (
            None
            if scene.mask is None
            else torch.tensor(scene.mask, dtype=torch.float32, device=self.device)
        )
        self.psf = torch.tensor(scene.psf, dtype=torch.float32, device=self.device)

    def _crop_to_signal(self, prepass: Tensor, optics: OpticsEstimation) -> dict[int, Tensor]:
        """Fit on the box around the SHB pre-pass's signal (``prepass``: the padded grid);
        returns the initialisation snapshot cut to the box's padded grid."""
        scene, settings, guard = self.scene, self.settings, self.scene.guard_px
        volume = crop_guard(prepass, guard).numpy()
        planes = slice(0, scene.volume_shape[0])
        if not optics.enabled:
            planes = signal_box(volume, settings.crop, (settings.crop_margin_planes, 0, 0))[0]
        reach = psf_reach(scene.psf[:, planes])  # of the planes kept: light of the signal's depths
        box = (planes, *signal_box(volume, settings.crop, (0, *reach))[1:])
        self.box = box
        self._fit_on(crop_scene(scene, box))
        z, y, x = box
        padded = prepass[z, y.start : y.stop + 2 * guard, x.start : x.stop + 2 * guard]
        return {settings.init_iterations: padded.contiguous()}

    def visibility(self) -> Tensor:
        """The share of a voxel's light that reaches the fitted pixels ``(Z, Y + 2g, X + 2g)``
        on the fitted grid, relative to the most visible voxel's: ``A^T w / max A^T w``
        (``w`` the pixel mask, 1 without), on CPU.

        The SHB pre-pass divides its update by this sensitivity, so guard-band voxels whose
        light mostly misses the views get large values for the little light they explain;
        seeding in proportion to value x visibility, the light each voxel sends into the views,
        puts the Gaussians where the measured light comes from, not in the band."""
        weights = torch.ones_like(self.measurement) if self.mask is None else self.mask
        with torch.no_grad():
            sensitivity = self.fit_scene.operator(self.psf).adjoint(weights).float().cpu()
        return sensitivity / sensitivity.max().clamp(min=1e-30)

    def crop_metrics(self) -> dict[str, float]:
        """``crop/voxels`` of the grid the Gaussians are fitted on and ``crop/voxels_saved``
        (the share of the whole grid left out); empty without a crop."""
        if self.box is None:
            return {}
        kept, whole = box_voxels(self.box), int(np.prod(self.scene.volume_shape))
        return {names.CROP_VOXELS: float(kept), names.CROP_SAVED: 1.0 - kept / whole}

    def _shb_snapshots(self) -> dict[int, Tensor]:
        """SHB reconstructions on the padded grid at the baseline (with a truth) and
        initialisation (or crop) iteration counts (one run, with the scene's gains, mask and
        guard band), on CPU; empty when none is wanted."""
        settings = self.settings
        wanted = {settings.baseline_iterations} - {0} if self.scene.truth is not None else set()
        if settings.init == "shb" or settings.crop > 0:
            wanted.add(settings.init_iterations)
        if not wanted:
            return {}
        snapshots = {}
        deconvolve(
            self.measurement,
            self.scene.operator(self.psf),
            max(wanted),
            method="shb",
            callback=lambda k, v: (
                snapshots.__setitem__(k + 1, v.float().cpu()) if k + 1 in wanted else None
            ),
            weights=self.mask,
        )
        return snapshots

    def gains(self) -> Tensor | None:
        """The per-view gains ``(V,)`` of the forward model: ``None`` for the scene's (known or
        all 1), or, with ``estimate_gains``, ``exp(l - mean(l)) * G`` of the log-gains ``l``
        (with gradient), ``G`` the geometric mean of the scene's gains (1 without). The gauge:
        a uniform change of all log-gains changes nothing (the global scale belongs to the
        Gaussians' intensities), and the gains' geometric mean stays the scene's."""
        if self.log_gains is None:
            return None
        return torch.exp(self.log_gains - self.log_gains.mean() + self.log_gain_mean)

    @property
    def operator(self) -> MeasuredOperator:
        """The forward model of the current PSF (OTFs cached until the PSF changes) with the
        current gains."""
        if self._operator is None:
            self._operator = self.fit_scene.operator(self.psf)
        gains = self.gains()
        return self._operator if gains is None else self._operator.with_gains(gains)

    def grid_volume(self) -> Tensor:
        """The rendered padded volume ``scene.grid_shape`` in normalised measurement units (no
        gradient)."""
        with torch.no_grad():
            return self.cloud()

    def volume(self) -> Tensor:
        """The current reconstruction ``(Z, Y, X)`` (the output grid: the guard band cropped; a
        crop padded back with zeros) in normalised measurement units (no gradient)."""
        volume = crop_guard(self.grid_volume(), self.scene.guard_px)
        return volume if self.box is None else pad_volume(volume, self.box, self.scene.volume_shape)

    # ------------------------------------------------------------------ a step
    def step(self, optimizer=None) -> StepResult:
        """One static iteration, then densification and a JPGM event when due.

        Parameters
        ----------
        optimizer : optional
            What steps :attr:`optimizer` (a wrapper that also counts steps, e.g. Lightning's);
            default :attr:`optimizer` itself.

        Raises
        ------
        FloatingPointError
            A non-finite loss term or gradient, naming the step and the term or parameter.
        """
        start = time.perf_counter()
        self.optimizer.zero_grad(set_to_none=True)
        volume = self.cloud()
        synchronize(self.device)
        voxelized = time.perf_counter()
        prediction = self.operator.forward(volume)
        synchronize(self.device)
        projected = time.perf_counter()
        s = self.settings
        terms = static_loss(
            prediction,
            self.measurement,
            step=self.steps_done,
            total_steps=self.total_steps,
            p=s.p,
            lambda_fourier=s.lambda_fourier,
            lambda_ssim=s.lambda_ssim,
            mask=self.mask,
        )
        values = descend(
            terms,
            self.named_parameters(),
            optimizer or self.optimizer,
            f"step {self.steps_done}",
            self.steps_done,
            before_step=lambda: self.densification.update_statistics(self.cloud),
        )
        self.steps_done += 1
        events = {}
        changes = self.densification.step(self.cloud, self.optimizer, self.steps_done)
        if changes:
            events["densification"] = {key: float(value) for key, value in changes.items()}
        synchronize(self.device)
        timings = {
            "voxelize_ms": 1e3 * (voxelized - start),
            "projection_ms": 1e3 * (projected - voxelized),
            "step_ms": 1e3 * (time.perf_counter() - start),
        }
        metrics = self.gain_metrics()
        if self.holdout_mask is not None:  # the step's own prediction: no extra projection
            metrics[names.HOLDOUT_LOSS] = float(
                pixel_loss(prediction.detach(), self.measurement, s.p, self.holdout_mask)
            )
        if self.estimation.due(self.steps_done) and self.optics_converged_at is None:
            events["optics"] = self.estimate_optics()
        return StepResult(
            values,
            timings,
            events,
            self.cloud.count,
            metrics,
        )

    def named_parameters(self):
        """``(name, parameter)`` of everything the step optimises: the Gaussians' raw parameters
        and, with ``estimate_gains``, ``log_gains``."""
        gains = [] if self.log_gains is None else [("log_gains", self.log_gains)]
        return itertools.chain(self.cloud.named_parameters(), gains)

    def gain_metrics(self) -> dict[str, float]:
        """``gain/view{v}``: the estimated gains (empty with the gains fixed)."""
        if self.log_gains is None:
            return {}
        with torch.no_grad():
            return {f"gain/view{v}": float(g) for v, g in enumerate(self.gains().tolist())}

    def estimate_optics(self) -> dict[str, float]:
        """One JPGM event against the current volume (Note S3.5.2); the PSF and the operator
        follow it. Returns the event's metrics: losses, time per inner step, the parameters and,
        on phantoms, the errors to the true optics."""
        gains = self.gains()
        gains = None if gains is None else gains.detach()
        blur_px = self.estimation.blur_at(self.steps_done)
        result = run_event(
            self.jpgm,
            self.grid_volume(),
            self.measurement,
            self.estimation,
            self.optics_optimizer,
            operator=lambda psf: self.fit_scene.operator(psf, gains),
            mask=self.mask,
            chunks=self.depth_chunks,
            blur_px=blur_px,
        )
        with torch.no_grad():
            estimated = self.jpgm()
            change = float((estimated - self.psf).norm() / self.psf.norm().clamp(min=1e-30))
            self.psf.copy_(estimated)
        self._operator = None
        metrics = {
            names.PSF_CHANGE: change,
            "time/jpgm_iter_ms": result["ms_per_step"],
            "optics/loss_before": result["loss_before"],
            "optics/loss_after": result["loss_after"],
            "optics/inner_steps": float(result["steps"]),
            **({"optics/blur_px": blur_px} if self.estimation.blur_px else {}),
            **optics_metrics(self.jpgm),
        }
        self.quiet_events = self.quiet_events + 1 if result["quiet"] else 0
        if self.quiet_events >= 2:
            self.optics_converged_at = self.steps_done
            metrics[names.OPTICS_CONVERGED] = float(self.steps_done)
            warnings.warn(
                f"JPGM: the optics converged after step {self.steps_done} (two events in a row "
                f"changed the data loss by less than optics.tolerance = "
                f"{self.estimation.tolerance:g} and no parameter by more than "
                f"{self.estimation.parameter_tolerance:g}): later JPGM events are skipped",
                RuntimeWarning,
                stacklevel=2,
            )
        for name, count in result["unconverged"].items():
            metrics[f"optics/unconverged_{name}"] = float(count)
        self.last_event = (self.steps_done, dict(result["unconverged"]))
        if self.true_psf is not None:
            metrics.update(self.optics_errors())
        return metrics

    def optics_settling(self) -> str | None:
        """The sentence a fit ends with when its last JPGM event stopped with entries still
        moving at the full learning rate (:func:`~fgat.recon.estimation.still_moving`): those
        entries stopped where the event's steps ran out, not at an estimate. ``None`` when the
        last event settled or none ran. Earlier events moving at full speed are the
        alternation at work: they are logged (``optics/unconverged_<name>``), not reported."""
        if self.last_event is None or not self.last_event[1]:
            return None
        step, moving = self.last_event
        counts = ", ".join(
            f"{count} of {getattr(self.jpgm, name).numel()} {name.replace('_', ' ')}"
            for name, count in moving.items()
        )
        rates = " or ".join(f"optics.lr_{LEARNING_RATES[name]}" for name in moving)
        return (
            f"the last JPGM event (after step {step}) ended with entries still moving at the full "
            f"learning rate ({counts}): they stopped where its {self.estimation.steps} steps ran "
            f"out, not at an estimate; raise {rates} or optics.steps, or give the fit more events"
        )

    def optics_start(self) -> dict[str, float]:
        """The estimated optics at the start (the first point of the trajectories of Fig. S10),
        and on phantoms the true parameters (``zernike_gt/...``, ``shift_gt/...``) and the
        starting PSF's error; empty with the optics fixed."""
        if self.jpgm is None:
            return {}
        metrics = optics_metrics(self.jpgm)
        if self.true_psf is not None:
            truth = parameter_metrics(self.jpgm.zernike_indices, *self.true_parameters())
            metrics.update(
                {
                    key.replace("zernike/", "zernike_gt/").replace("shift/", "shift_gt/"): value
                    for key, value in truth.items()
                }
            )
            initial = torch.as_tensor(self.scene.psf, device=self.device, dtype=self.true_psf.dtype)
            metrics.update(psf_errors(initial, self.true_psf, names.PSF_ERROR_INITIAL))
        return metrics

    def true_parameters(self) -> tuple[Tensor, Tensor, Tensor]:
        """The phantom's true ``(c (K,), b (V, 2), s (V, 2))`` on the estimated indices and
        views."""
        return self.scene.truth_optics.parameters(self.jpgm.zernike_indices, self.jpgm.n_views)

    def optics_errors(self) -> dict[str, float]:
        """:func:`~fgat.recon.optics_report.optics_errors` of the current estimate."""
        return optics_errors(self.jpgm, self.true_parameters(), self.psf, self.true_psf)

    def identifiability(self) -> Identifiability | None:
        """Standard errors of the estimated optics at the current optics and volume
        (:func:`~fgat.recon.optics_report.identifiability`, computed in float64 with
        the fit's forward model, gains and mask), with the joint Gauss-Newton correction of the
        optics (:func:`~fgat.recon.joint_step.joint_correction`, the gains held), and on
        phantoms the true values; ``None`` with the optics fixed or ``optics.identifiability``
        off.

        The noise level counts every estimated parameter as stored: the Gaussians' raw
        parameters, the estimated optics groups and, with ``estimate_gains``, the log-gains.

        Raises
        ------
        ValueError
            More memory than the device has (checked before the Jacobians are formed), or a
            Hessian block that is not positive definite (optics with no effect on the image).
        """
        if self.jpgm is None or not self.estimation.identifiability:
            return None
        jpgm = self.scene.optics.jpgm(
            zernike_indices=self.jpgm.zernike_indices,
            method=self.estimation.psf_method,
            oversampling=self.jpgm.oversampling,
            dtype=torch.float64,
            device=self.device,
        )
        with torch.no_grad():
            for name in ("zernike_coefficients", "intercepts", "slopes"):
                getattr(jpgm, name).copy_(getattr(self.jpgm, name))
        plan = identifiability_plan(
            jpgm,
            self.fit_scene.volume_shape,
            self.scene.guard_px,
            self.estimation.estimate,
            available_memory(self.device),
        )
        check_memory(
            "the standard errors of the estimated optics (optics.identifiability)",
            plan.nbytes,
            hint="set model.optics.identifiability = false",
            device=self.device,
        )
        gains = self.gains()
        gains = None if gains is None else gains.detach()
        operator = partial(self.fit_scene.operator, gains=gains)
        correction = partial(
            joint_correction,
            self.cloud,
            self.jpgm,
            self.estimation.estimate,
            self.measurement,
            operator,
            mask=self.mask,
        )
        estimated = ESTIMATES[self.estimation.estimate]
        n_parameters = sum(parameter.numel() for _, parameter in self.named_parameters())
        n_parameters += sum(getattr(self.jpgm, name).numel() for name in estimated)
        return identifiability(
            jpgm,
            self.grid_volume(),
            self.measurement,
            self.estimation.estimate,
            operator=operator,
            n_parameters=n_parameters,
            tolerance=self.estimation.stderr_tolerance,
            mask=self.mask,
            truth=None if self.true_psf is None else self.true_parameters(),
            correction=correction,
            chunk_size=plan.chunk_size,
            depth_chunk=plan.depth_chunk,
        )

    # ------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict[str, float]:
        """The volume's scores against the truth (:func:`truth_scores`, ``val/...``), beside the
        SHB baseline's (``val/..._shb``); empty without a truth."""
        if self.scene.truth is None:
            return {}
        return {
            **truth_scores(self.volume(), self.scene.truth),
            **self.baseline_scores,
        }

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Everything a resumed run needs (tensors and plain values only): step count, grid,
        Gaussians and their Adam moments, densification statistics, PSF, JPGM and its optimizer,
        and the estimated log-gains; with them ``gains``, the effective gains :meth:`gains` of
        the forward model, which the dynamic stage uses
        (:func:`~fgat.recon.load_static`)."""
        cloud = self.cloud
        state = {
            "steps_done": self.steps_done,
            "psf": self.psf.detach().cpu(),
            "grid": {
                "shape": list(cloud.shape),
                "voxel_size": cloud.voxel_size.tolist(),
                "origin": cloud.origin.tolist(),
                "scale_range": list(cloud.scale_range),
            },
            "cloud": {key: value.detach().cpu() for key, value in cloud.state_dict().items()},
            "optimizer": self.optimizer.state_dict(),
            "densification": self.densification.state_dict(),
            "quiet_events": self.quiet_events,
            "optics_converged_at": self.optics_converged_at,
            "last_event": self.last_event,
            "crop_box": None if self.box is None else [[b.start, b.stop] for b in self.box],
        }
        if self.jpgm is not None:
            state["jpgm"] = {
                key: value.detach().cpu() for key, value in self.jpgm.state_dict().items()
            }
            state["optics_optimizer"] = self.optics_optimizer.state_dict()
        if self.log_gains is not None:
            state["log_gains"] = self.log_gains.detach().cpu()
            state["gains"] = self.gains().detach().cpu()
        return state

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (any number of Gaussians).

        Raises
        ------
        ValueError
            The state was fitted on another crop of the grid than this run's pre-pass finds.
        """
        box = None if self.box is None else [[b.start, b.stop] for b in self.box]
        if state.get("crop_box") != box:
            raise ValueError(
                f"the checkpoint was fitted on the crop {state.get('crop_box')} (z, y, x voxel "
                f"ranges) of the grid, this run's SHB pre-pass gives {box}: resume with the "
                "checkpoint's data and settings"
            )
        self.cloud.load_state_dict(state["cloud"])
        for group, name in zip(
            self.optimizer.param_groups, ("means", "raw_scales", "raw_quats", "raw_intensities")
        ):
            group["params"] = [getattr(self.cloud, name)]
        self.optimizer.state.clear()
        self.optimizer.load_state_dict(state["optimizer"])
        self.densification.load_state_dict(state["densification"], self.device)
        with torch.no_grad():
            self.psf.copy_(state["psf"])
            if self.log_gains is not None:
                self.log_gains.copy_(state["log_gains"])
        self._operator = None
        if self.jpgm is not None:
            self.jpgm.load_state_dict(state["jpgm"])
            self.optics_optimizer.load_state_dict(state["optics_optimizer"])
        self.steps_done = int(state["steps_done"])
        self.quiet_events = int(state.get("quiet_events", 0))
        self.optics_converged_at = state.get("optics_converged_at")
        self.last_event = state.get("last_event")


def truth_scores(
    volume: np.ndarray | Tensor, truth: np.ndarray, suffix: str = ""
) -> dict[str, float]:
    """A volume ``(Z, Y, X)`` scored against the truth: PSNR, SSIM and x-y MIP SSIM as they are
    (:func:`~fgat.recon.metrics.compare_volumes`), and the PSNR after registering the volume to the
    truth with the shift it took (:func:`~fgat.recon.metrics.registered_psnr`, within
    :data:`~fgat.recon.metrics.REGISTRATION_WINDOW` voxels or less than half the grid's smallest
    side), under the logged names of :mod:`fgat.recon.names` with ``suffix``. A joint
    estimate of the lenslet shifts fixes the scene only up to a translation (the shifts' gauge)
    that the raw scores count as error and the registered one does not. A grid with a side
    under three voxels gets no registered score. A tensor ``volume`` is scored on its device
    (:func:`~fgat.recon.metrics.scoring_pair`), and registered on the host."""
    volume, on_device = scoring_pair(torch.as_tensor(volume), truth)
    scores = names.volume_scores(compare_volumes(volume, on_device), suffix)
    window = registration_window(np.shape(truth))
    if window >= 1:
        registered = registered_psnr(volume.cpu().numpy(), truth, window)
        scores |= names.registered_scores(*registered, suffix)
    return scores
