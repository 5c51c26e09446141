"""The dynamic stage (Notes S3.3-S3.5.3, Fig. S3) as a plain object.

The canonical Gaussians ``G_0`` and the PSF stack of a static run are frozen; a HexPlane feature
field and deformation MLP carry ``G_0`` to the time of each frame (Eqs. S17-S22), the deformed
set is voxelized and projected, and only the field is trained with ``L_dyn`` (Eq. S29). One
:meth:`DynamicReconstruction.step` is one frame; every ``T`` steps cover every frame once, in a
shuffled order (:meth:`DynamicReconstruction.next_frame`), or, with ``frame_tolerance``, the frames
whose loss has not yet converged.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from fgat._core.devices import adam
from fgat._core.validation import require, require_non_negative, require_positive
from fgat.dynamics.deformation import (
    DeformationField,
    normalized_positions,
)
from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.voxelize import voxelize
from fgat.io.checkpoints import load_torch_file
from fgat.io.images import read_tiff
from fgat.io.yaml_files import read_yaml
from fgat.optics.acquisition import crop_guard
from fgat.recon import names
from fgat.recon.guards import descend, synchronize
from fgat.recon.losses import dynamic_loss, pixel_loss
from fgat.recon.metrics import compare_volumes, registered_psnr, scoring_pair, shifted_psnr
from fgat.recon.scene import Scene
from fgat.recon.static import StepResult

GAUSSIAN_KEYS = ("means", "scales", "quats", "intensities")
REGISTERED = "psnr_registered"  # a frame's PSNR with the scene moved by its registration shift


@dataclass(frozen=True)
class DynamicSettings:
    """The deformation MLP and the dynamic loss.

    Attributes
    ----------
    width, depth : int
        Deformation MLP trunk (Eq. S20: 128, 2).
    lr_planes, lr_mlp : float
        Adam learning rates of the HexPlane planes and of the MLP (the note gives none; on a
        12-frame beating shell these gained 4.1 dB over the no-deformation baseline in the first
        360 frame-iterations, 5x lower rates 1.0 dB).
    p : int
        Pixel loss exponent of Eq. S23.
    lambda_fourier, lambda_ssim : float
        ``lambda_F`` (constant in this stage) and ``lambda_S`` of Eq. S29.
    lambda_tv, lambda_sm, lambda_l1 : float
        Plane regulariser weights (Eqs. S30-S32; defaults of Note S3.5.3).
    seed : int
        Seed of the HexPlane initialisation (the MLP and the frame order follow
        ``seed_everything``).
    frame_tolerance : float
        Skip what has converged: a frame whose last visit changed its image loss by less than
        this fraction of what it has lost since its first visit is left out of the following
        passes, except every ``revisit``-th pass, which visits every frame again (a frame that
        regressed rejoins). Once every frame has converged the stage has
        (:attr:`DynamicReconstruction.converged_at`). 0: every frame in every pass.
    revisit : int
        Every this many passes all frames are visited.

    Raises
    ------
    ValueError
        A field out of its range, naming it (``lr_planes must be a positive number, got 0``).
    """

    width: int = 128
    depth: int = 2
    lr_planes: float = 1e-2
    lr_mlp: float = 1e-3
    p: int = 1
    lambda_fourier: float = 0.0
    lambda_ssim: float = 0.0
    lambda_tv: float = 1e-4
    lambda_sm: float = 1e-3
    lambda_l1: float = 1e-4
    seed: int = 0
    frame_tolerance: float = 0.0
    revisit: int = 4

    def __post_init__(self) -> None:
        require(self.width >= 1, "width", self.width, "a positive integer (MLP width)")
        require(
            0 <= self.frame_tolerance < 1,
            "frame_tolerance",
            self.frame_tolerance,
            "a relative change of the loss in [0, 1) (0: no frame is skipped)",
        )
        require(self.revisit >= 1, "revisit", self.revisit, "a positive number of passes")
        require(self.depth >= 1, "depth", self.depth, "a positive integer (MLP hidden layers)")
        require_positive("", lr_planes=self.lr_planes, lr_mlp=self.lr_mlp)
        require(self.p in (1, 2), "p", self.p, "1 (MAE) or 2 (MSE)")
        require_non_negative(
            "",
            lambda_fourier=self.lambda_fourier,
            lambda_ssim=self.lambda_ssim,
            lambda_tv=self.lambda_tv,
            lambda_sm=self.lambda_sm,
            lambda_l1=self.lambda_l1,
        )


class StaticResult(NamedTuple):
    """What the dynamic stage takes from a static run (:func:`load_static`).

    Attributes
    ----------
    cloud : GaussianCloud
        The canonical Gaussians ``G_0``.
    psf : Tensor or None
        The ``(V, Z, h, w)`` float32 PSF stack (``None``: the data's).
    gains : Tensor or None
        The ``(V,)`` float32 per-view gains the run estimated (``estimate_gains``): the effective
        gains of its forward model, the data's gains times the fitted correction (``None``: the
        run kept the data's gains, or predates gain estimation; the dynamic stage then uses the
        data's).
    """

    cloud: GaussianCloud
    psf: Tensor | None
    gains: Tensor | None


def load_static(path: str | Path, psf: str | Path | None = None) -> StaticResult:
    """``G_0``, the PSF stack and the estimated per-view gains of a static run.

    Parameters
    ----------
    path : str or Path
        A static run's checkpoint (``.ckpt``, holding a
        :meth:`~fgat.recon.static.StaticReconstruction.state_dict`: the Gaussians, the
        PSF stack, self-estimated or not, and the estimated gains), or its results folder /
        ``gaussians.pt`` (then the PSF is the folder's ``psf.ome.tif`` when JPGM estimated one,
        the gains its ``gains.yaml`` when the run estimated them).
    psf : str or Path, optional
        A PSF stack ``(V, Z, h, w)`` OME-TIFF that replaces the run's.

    Returns
    -------
    StaticResult
        The Gaussians, the PSF stack (``None`` when neither the run nor ``psf`` gives one) and
        the estimated gains (``None`` when the run has none: a checkpoint or results folder
        written without ``estimate_gains``, or before the gains were carried over).

    Raises
    ------
    FileNotFoundError
        ``path`` (or the folder's ``gaussians.pt``) does not exist.
    ValueError
        A checkpoint that is not a static stage's, or a ``gains.yaml`` that does not hold
        positive per-view gains.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(
            f"model.static: {path} does not exist (a static run's last.ckpt, or its results "
            "folder with gaussians.pt)"
        )
    stack = gains = None
    if path.suffix == ".ckpt":
        state = load_torch_file(path, "model.static").get("reconstruction")
        if not isinstance(state, dict) or not {"grid", "cloud", "psf"} <= set(state):
            raise ValueError(
                f"model.static: {path} is not a static-stage checkpoint (no Gaussians and PSF)"
            )
        if state.get("crop_box") is not None:
            raise ValueError(
                f"model.static: {path} was fitted on a crop of the grid (model.crop, voxel "
                f"ranges {state['crop_box']}); the dynamic stage deforms G0 over the whole grid: "
                "fit the static stage without model.crop"
            )
        grid = state["grid"]
        cloud = GaussianCloud(
            grid["shape"],
            grid["voxel_size"],
            origin=grid["origin"],
            scale_range=tuple(grid["scale_range"]),
        )
        cloud.load_state_dict(state["cloud"])
        stack = state["psf"].float()
        if state.get("gains") is not None:
            gains = state["gains"].float()
    else:
        folder = path if path.is_dir() else path.parent
        gaussians = path if path.is_file() else folder / "gaussians.pt"
        if not gaussians.is_file():
            raise FileNotFoundError(f"model.static: {gaussians} does not exist")
        cloud = GaussianCloud.load(gaussians, source="model.static")
        if (folder / "psf.ome.tif").is_file():
            psf = psf or folder / "psf.ome.tif"
        if (folder / "gains.yaml").is_file():
            gains = read_gains(folder / "gains.yaml")
    if psf is not None:
        stack = torch.from_numpy(
            read_tiff(psf, ndim=4, axes="(V, Z, h, w)", nonnegative=True).astype(np.float32)
        )
    return StaticResult(cloud, stack, gains)


def read_gains(path: Path) -> Tensor:
    """The per-view gains of a static run's ``gains.yaml`` (``gains: [g_0, ..., g_{V-1}]``, as
    :class:`~fgat.callbacks.ReconstructionArtifacts` writes it) as a float32 tensor ``(V,)``.

    Raises
    ------
    ValueError
        The file does not hold a list of finite positive numbers under ``gains``.
    """
    content = read_yaml(path, f"model.static: {path}")
    values = content.get("gains") if isinstance(content, dict) else None
    if not (
        isinstance(values, list)
        and values
        and all(
            isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g) and g > 0
            for g in values
        )
    ):
        raise ValueError(
            f"model.static: {path} must hold 'gains: [...]', one finite positive number per view"
        )
    return torch.tensor(values, dtype=torch.float32)


def reference_shift(still: np.ndarray, truth: np.ndarray) -> tuple[float, ...] | None:
    """The translation ``(dz, dy, dx)`` (voxels) that registers ``G_0`` rendered still
    (``(Z, Y, X)``) to the reference frame's truth (:func:`~fgat.recon.metrics.registered_psnr`):
    the scene's gauge translation, which every frame shares since all are rendered with the same
    optics (one registration instead of one per frame). ``None`` where the grid is too thin to
    register (:func:`~fgat.recon.metrics.registration_window`) or ``G_0`` does not register."""
    return registered_psnr(still, truth, max_shift=None)[1]


class DynamicReconstruction:
    """A HexPlane + MLP deformation of frozen canonical Gaussians, fitted to every frame.

    The forward model is the scene's acquisition (gains, pixel mask, guard band; see
    :class:`~fgat.recon.static.StaticReconstruction`), with the per-view gains the
    static run estimated in place of the scene's when it estimated them: ``G_0`` lives on the
    static run's padded grid, and the volumes returned are its central ``scene.volume_shape``.

    Parameters
    ----------
    scene : Scene
        The sequence (``scene.frames``; a single frame is a sequence of one).
    gaussians : dict
        ``G_0``: ``means``, ``scales`` (um), ``quats``, ``intensities`` tensors ``(N, ...)``.
    psf : Tensor
        ``(V, Z, h, w)`` PSF stack (the static run's).
    gains : Tensor or None
        ``(V,)`` per-view gains of the forward model (the static run's estimated ones); ``None``:
        the scene's.
    grid : dict
        ``shape`` (Z, Y, X) of the (padded) grid, ``scene.grid_shape``, ``voxel_size`` and
        ``origin`` (um), ``min_scale`` (um),
        ``reference_time`` (in [-1, 1]) and the field's architecture: :class:`HexPlaneSettings`
        fields (``temporal_resolution`` resolved), ``width``, ``depth``.
    settings : DynamicSettings
        Learning rates and loss weights.
    device : torch.device or str
        Where everything is computed.

    Raises
    ------
    ValueError
        The scene's grid, PSF or views do not match the static run's.
    """

    def __init__(
        self,
        scene: Scene,
        gaussians: dict[str, Tensor],
        psf: Tensor,
        gains: Tensor | None,
        grid: dict,
        settings: DynamicSettings = DynamicSettings(),
        device: torch.device | str = "cpu",
    ) -> None:
        self.scene, self.settings, self.grid, self.device = (
            scene,
            settings,
            grid,
            torch.device(device),
        )
        check_scene(scene, tuple(grid["shape"]), tuple(psf.shape), gains)
        self.mask = (
            None
            if scene.mask is None
            else torch.tensor(scene.mask, dtype=torch.float32, device=self.device)
        )
        self.g0 = {
            key: gaussians[key].detach().to(self.device, torch.float32) for key in GAUSSIAN_KEYS
        }
        self.psf = psf.detach().to(self.device, torch.float32)
        self.gains = None if gains is None else gains.detach().to(self.device, torch.float32)
        extent = (np.asarray(grid["shape"]) * np.asarray(grid["voxel_size"])).tolist()
        self.positions = normalized_positions(self.g0["means"], grid["origin"], extent)
        hexplane = HexPlaneSettings(
            **{f.name: grid[f.name] for f in dataclasses.fields(HexPlaneSettings)}
        )
        self.field = DeformationField(
            hexplane.build(scene.n_frames, seed=settings.seed),
            width=grid["width"],
            depth=grid["depth"],
            reference_time=grid["reference_time"],
        ).to(self.device)
        self.optimizer = adam(
            [
                {
                    "params": list(self.field.hexplane.parameters()),
                    "lr": settings.lr_planes,
                    "name": "planes",
                },
                {
                    "params": [
                        p
                        for name, p in self.field.named_parameters()
                        if not name.startswith("hexplane.")
                    ],
                    "lr": settings.lr_mlp,
                    "name": "mlp",
                },
            ],
            eps=1e-15,
        )
        self.operator = scene.operator(self.psf, self.gains)
        self.frames, self.times = scene.sequence()
        self.steps_done = 0
        self._order: list[int] = []  # the frames still to visit in the pass in progress
        self.passes = 0  # passes begun
        n_frames = len(self.times)
        self.first_losses = [math.nan] * n_frames  # image loss at each frame's first visit
        self.frame_losses = [math.nan] * n_frames  # and at its last
        self.frame_changes = [math.inf] * n_frames  # last change / loss lost since the first
        self.converged_at: int | None = None  # step after which every frame had converged
        self.still_scores: list[
            dict[str, float]
        ] = []  # G_0 at every frame (no deformation), on phantoms
        self.scene_shift: tuple[float, ...] | None = None  # G_0's registration to the truth
        if scene.truth_frames is not None:
            still = self.still_volume()
            reference = scene.truth_frames[scene.reference]
            self.scene_shift = reference_shift(still.cpu().numpy(), reference)
            self.still_scores = [self._scores(still, truth) for truth in scene.truth_frames]

    @classmethod
    def from_static(
        cls,
        scene: Scene,
        cloud: GaussianCloud,
        psf: Tensor | None,
        gains: Tensor | None = None,
        hexplane: HexPlaneSettings = HexPlaneSettings(),
        settings: DynamicSettings = DynamicSettings(),
        device: torch.device | str = "cpu",
    ) -> DynamicReconstruction:
        """A fresh deformation of a static run's Gaussians (PSF: the run's, else the scene's;
        gains: the run's estimated ones, else the scene's), e.g. of a :func:`load_static`
        result unpacked: ``from_static(scene, *load_static(path), hexplane, settings)``."""
        times = scene.sequence()[1]
        architecture = {
            **dataclasses.asdict(hexplane),
            "width": settings.width,
            "depth": settings.depth,
            "temporal_resolution": hexplane.temporal_resolution or max(2, scene.n_frames // 2),
        }
        grid = {
            "shape": list(cloud.shape),
            "voxel_size": cloud.voxel_size.tolist(),
            "origin": cloud.origin.tolist(),
            "min_scale": cloud.scale_range[0] * cloud.unit,
            "reference_time": 2 * float(times[scene.reference]) - 1,
            **architecture,
        }
        with torch.no_grad():
            gaussians = dict(
                zip(
                    GAUSSIAN_KEYS, (cloud.means, cloud.scales, cloud.quaternions, cloud.intensities)
                )
            )
        return cls(
            scene,
            gaussians,
            psf if psf is not None else torch.tensor(scene.psf, dtype=torch.float32),
            gains,
            grid,
            settings,
            device,
        )

    @classmethod
    def from_state_dict(
        cls,
        scene: Scene,
        state: dict,
        settings: DynamicSettings = DynamicSettings(),
        device: torch.device | str = "cpu",
    ) -> DynamicReconstruction:
        """The reconstruction a :meth:`state_dict` holds (no static run needed; a state without
        ``gains``, written before they were carried over, uses the scene's)."""
        engine = cls(
            scene, state["g0"], state["psf"], state.get("gains"), state["grid"], settings, device
        )
        engine.load_state_dict(state)
        return engine

    # ------------------------------------------------------------------ the deformed scene
    def _voxelize(
        self, means: Tensor, scales: Tensor, quats: Tensor, intensities: Tensor
    ) -> Tensor:
        return voxelize(
            means,
            scales,
            quats,
            intensities,
            tuple(self.grid["shape"]),
            self.grid["voxel_size"],
            self.grid["origin"],
        )

    def gaussians_at(self, t: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``G_t`` (Eq. S22): means and scales (um), quaternions and intensities at normalised
        sequence time ``t`` in [0, 1]; ``G_0`` itself at the reference frame's time."""
        return self.field.deform(
            self.positions,
            2 * torch.as_tensor(t, dtype=self.positions.dtype, device=self.device) - 1,
            [self.g0[key] for key in GAUSSIAN_KEYS],
            min_scale=self.grid["min_scale"],
        )

    def grid_volume_at(self, t: float) -> Tensor:
        """The volume ``V_t`` on the padded grid ``scene.grid_shape`` at normalised time ``t``
        (measurement units, with gradient): what the forward model sees."""
        return self._voxelize(*self.gaussians_at(t))

    def volume_at(self, t: float) -> Tensor:
        """The volume ``V_t`` ``(Z, Y, X)`` (the guard band cropped) at normalised time ``t``
        (measurement units, with gradient)."""
        return crop_guard(self.grid_volume_at(t), self.scene.guard_px)

    def still_volume(self) -> Tensor:
        """``G_0`` voxelized without deformation ``(Z, Y, X)`` (the guard band cropped)."""
        with torch.no_grad():
            return crop_guard(
                self._voxelize(*(self.g0[key] for key in GAUSSIAN_KEYS)), self.scene.guard_px
            )

    def next_frame(self) -> int:
        """The frame of the next step (the pass in progress gives it up when the step is done).
        Each pass visits every
        frame once (with ``frame_tolerance``, the frames that have not converged, and every
        ``revisit``-th pass all of them) in a permutation drawn at the pass's start from a seed
        taken from torch's global random stream (as a shuffled ``DataLoader`` draws it, so
        ``seed_everything`` fixes the order)."""
        if not self._order:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
            order = torch.randperm(
                len(self.times), generator=torch.Generator().manual_seed(seed)
            ).tolist()
            self.passes += 1
            if self.settings.frame_tolerance > 0 and self.passes % self.settings.revisit != 0:
                order = [k for k in order if not self.frame_converged(k)] or order
            self._order = order
        return self._order[0]

    def frame_converged(self, index: int) -> bool:
        """Whether frame ``index``'s last visit changed its image loss by less than
        ``frame_tolerance`` of the loss it has lost since its first visit (a frame whose loss
        does not move at all, like the reference frame, anchored to ``G_0``, has converged)."""
        return self.frame_changes[index] < self.settings.frame_tolerance

    def _record_frame(self, index: int, loss: float) -> None:
        """Frame ``index`` was visited with image loss ``loss``; notes when every frame has
        converged (``converged_at``)."""
        previous, first = self.frame_losses[index], self.first_losses[index]
        if math.isnan(first):
            self.first_losses[index] = loss
        else:
            change, gained = abs(loss - previous), first - loss
            self.frame_changes[index] = (
                0.0 if change == 0 else change / gained if gained > 0 else math.inf
            )
        self.frame_losses[index] = loss
        tolerance = self.settings.frame_tolerance
        if tolerance > 0 and self.converged_at is None:
            if all(self.frame_converged(k) for k in range(len(self.times))):
                self.converged_at = self.steps_done

    # ------------------------------------------------------------------ a step
    def frame_loss(self, index: int) -> dict[str, Tensor]:
        """The terms of Eq. S29 for frame ``index`` (``"total"`` among them), with the graph."""
        views = torch.from_numpy(np.ascontiguousarray(self.frames[index])).to(self.device)
        s = self.settings
        return dynamic_loss(
            self.operator.forward(self.grid_volume_at(float(self.times[index]))),
            views,
            self.field.hexplane,
            p=s.p,
            lambda_fourier=s.lambda_fourier,
            lambda_ssim=s.lambda_ssim,
            lambda_tv=s.lambda_tv,
            lambda_sm=s.lambda_sm,
            lambda_l1=s.lambda_l1,
            mask=self.mask,
        )

    def step(self, optimizer=None) -> StepResult:
        """One frame-iteration (see :meth:`StaticReconstruction.step` for ``optimizer``)."""
        start = time.perf_counter()
        index = self.next_frame()
        self.optimizer.zero_grad(set_to_none=True)
        terms = self.frame_loss(index)
        values = descend(
            terms,
            self.field.named_parameters(),
            optimizer or self.optimizer,
            f"step {self.steps_done} (frame {index})",
            self.steps_done,
        )
        self.steps_done += 1
        self._order.pop(0)
        self._record_frame(index, values["img"])
        synchronize(self.device)
        events, metrics = {}, {}
        if self.settings.frame_tolerance > 0:
            metrics[names.FRAMES_SETTLED] = float(
                sum(self.frame_converged(k) for k in range(len(self.times)))
            )
            if self.converged_at == self.steps_done:
                events["frames"] = {names.FRAMES_CONVERGED: float(self.steps_done)}
        return StepResult(
            values,
            {"frame_step_ms": 1e3 * (time.perf_counter() - start)},
            events,
            len(self.positions),
            metrics,
        )

    # ------------------------------------------------------------------ evaluation
    def volumes(self, times=None) -> np.ndarray:
        """Volumes ``(T, Z, Y, X)`` at normalised ``times`` (default the frames'), measurement
        units."""
        with torch.no_grad():
            return np.stack(
                [
                    self.volume_at(float(t)).cpu().numpy()
                    for t in (self.times if times is None else times)
                ]
            )

    def evaluate(self) -> dict[str, float]:
        """Mean over the frames of the data misfit ``val/loss_pix`` (measured data has no truth)
        and, on phantoms, of the volume scores (``val/...``) beside ``G_0`` left still's
        (``val/..._no_deformation``)."""
        misfits, scores = [], []
        with torch.no_grad():
            for index, t in enumerate(self.times):
                volume = self.grid_volume_at(float(t))
                views = torch.from_numpy(np.ascontiguousarray(self.frames[index])).to(self.device)
                misfits.append(
                    float(
                        pixel_loss(self.operator.forward(volume), views, self.settings.p, self.mask)
                    )
                )
                if self.scene.truth_frames is not None:
                    cropped = self.operator.crop(volume)
                    scores.append(self._scores(cropped, self.scene.truth_frames[index]))
        metrics = {names.LOSS_PIX: float(np.mean(misfits))}
        for suffix, frames in (("", scores), (names.STILL, self.still_scores)):
            if frames:
                metrics.update(
                    names.volume_scores(
                        {key: np.mean([s[key] for s in frames]) for key in names.VOLUME_SCORES},
                        suffix,
                    )
                )
                if self.scene_shift is not None:
                    mean = float(np.mean([s[REGISTERED] for s in frames]))
                    metrics.update(names.registered_scores(mean, self.scene_shift, suffix))
        return metrics

    def _scores(self, volume: Tensor, truth: np.ndarray) -> dict[str, float]:
        """A volume ``(Z, Y, X)`` on the grid (a frame's, or ``G_0`` still) scored against its
        truth on its device (:func:`compare_volumes`, :func:`scoring_pair`), and on the host
        with the scene moved by :attr:`scene_shift` (``REGISTERED``) where ``G_0`` registered."""
        volume, on_device = scoring_pair(volume, truth)
        scores = compare_volumes(volume, on_device)
        if self.scene_shift is not None:
            scores[REGISTERED] = shifted_psnr(volume.cpu().numpy(), truth, self.scene_shift)
        return scores

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Everything a resumed run or a prediction needs: ``G_0``, PSF, gains (``None``: the
        scene's), grid and architecture, the field, its Adam moments, the step count and the
        frames still to visit in the pass in progress (later passes draw theirs from the global
        random stream) and the frames' convergence."""
        return {
            "steps_done": self.steps_done,
            "pending": list(self._order),
            "passes": self.passes,
            "first_losses": list(self.first_losses),
            "frame_losses": list(self.frame_losses),
            "frame_changes": list(self.frame_changes),
            "converged_at": self.converged_at,
            "grid": dict(self.grid),
            "psf": self.psf.cpu(),
            "gains": None if self.gains is None else self.gains.cpu(),
            "g0": {key: value.cpu() for key, value in self.g0.items()},
            "field": {key: value.detach().cpu() for key, value in self.field.state_dict().items()},
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.steps_done = int(state["steps_done"])
        if "pending" in state:
            self._order = list(state["pending"])
            self.passes, self.converged_at = int(state["passes"]), state["converged_at"]
            self.first_losses = list(state["first_losses"])
            self.frame_losses = list(state["frame_losses"])
            self.frame_changes = list(state["frame_changes"])
        else:  # a state written before frames could be skipped: the whole pass's order
            n_frames, position = len(self.times), self.steps_done % len(self.times)
            self._order = list(state["order"])[position:] if position else []
            self.passes = -(-self.steps_done // n_frames)


def check_scene(
    scene: Scene,
    shape: tuple[int, int, int],
    psf_shape: tuple[int, ...],
    gains: Tensor | None = None,
) -> None:
    """The data must match the static run's grid (the padded ``scene.grid_shape``), PSF (views,
    depths) and estimated gains (one per view)."""
    if shape != scene.grid_shape:
        guard = f" with a {scene.guard_px}-voxel guard band" if scene.guard_px else ""
        raise ValueError(
            f"model.static: the static run's Gaussians are on a {shape} grid, but the data's "
            f"volume is {scene.grid_shape} (Z, Y, X){guard}"
        )
    if psf_shape[:2] != tuple(scene.psf.shape[:2]):
        raise ValueError(
            f"model.static_psf: the static run's PSF has {psf_shape[:2]} (views, depths), the data "
            f"{tuple(scene.psf.shape[:2])}"
        )
    if gains is not None and tuple(gains.shape) != (scene.psf.shape[0],):
        raise ValueError(
            f"model.static: the static run estimated gains of shape {tuple(gains.shape)}, the "
            f"data has {scene.psf.shape[0]} views"
        )
