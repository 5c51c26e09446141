"""DynamicModule: the dynamic stage (Notes S3.3-S3.5.3, Fig. S3).

The canonical Gaussians ``G_0`` and the PSF stack of a static run are frozen; a HexPlane feature
field and deformation MLP carry ``G_0`` to the time of each frame (Eqs. S17-S22), the deformed
set is voxelized and projected, and only the field is trained with ``L_dyn`` (Eq. S29). One
training step is one frame; an epoch covers every frame once, in a shuffled order.
"""

from __future__ import annotations

import time
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor

from fgat.checkpoints import load_torch_file
from fgat.dynamics.deformation import DeformationField, apply_deformation, normalized_positions
from fgat.dynamics.hexplane import HexPlane
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.voxelize import voxelize
from fgat.io import parse_overrides, read_tiff
from fgat.losses import dynamic_loss, pixel_loss
from fgat.metrics import compare_volumes
from fgat.modules.guards import (check_gradients, check_loss_terms, log_loss_terms, require, require_non_negative,
                                 require_positive, synchronize)
from fgat.modules.static import BASELINE_KEYS
from fgat.optics.operator import FLFMOperator

GAUSSIAN_KEYS = ("means", "scales", "quats", "intensities")


def load_static(path: str | Path, psf: str | Path | None = None) -> dict:
    """``G_0`` and the PSF stack of a static run.

    Parameters
    ----------
    path : str or Path
        A static run's Lightning checkpoint (``.ckpt``, holding the Gaussians and the PSF stack,
        self-estimated or not), or its results folder / ``gaussians.pt`` (then the PSF is the
        folder's ``psf.ome.tif`` when JPGM estimated one).
    psf : str or Path, optional
        A PSF stack ``(V, Z, h, w)`` OME-TIFF that replaces the run's.

    Returns
    -------
    dict
        ``cloud`` (:class:`~fgat.gaussians.cloud.GaussianCloud`) and ``psf`` (``(V, Z, h, w)``
        float32 tensor, or ``None`` when neither the run nor ``psf`` gives one).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"model.static: {path} does not exist (a static run's last.ckpt, or its results "
                                "folder with gaussians.pt)")
    stack = None
    if path.suffix == ".ckpt":
        checkpoint = load_torch_file(path, "model.static")
        state = checkpoint.get("state_dict", {})
        needed = ("cloud.means", "cloud.voxel_size", "cloud.origin", "psf", "measurement")
        if not isinstance(state, dict) or any(key not in state for key in needed) \
                or "scale_range" not in checkpoint.get("hyper_parameters", {}):
            raise ValueError(f"model.static: {path} is not a StaticModule checkpoint (no cloud.* / psf entries)")
        shape = (state["psf"].shape[1], *state["measurement"].shape[1:])
        cloud = GaussianCloud(shape, state["cloud.voxel_size"].tolist(), origin=state["cloud.origin"].tolist(),
                              scale_range=tuple(checkpoint["hyper_parameters"]["scale_range"]))
        cloud.load_state_dict({key[len("cloud."):]: value for key, value in state.items() if key.startswith("cloud.")})
        stack = state["psf"].float()
    else:
        folder = path if path.is_dir() else path.parent
        gaussians = path if path.is_file() else folder / "gaussians.pt"
        if not gaussians.is_file():
            raise FileNotFoundError(f"model.static: {gaussians} does not exist")
        cloud = GaussianCloud.load(gaussians, source="model.static")
        if (folder / "psf.ome.tif").is_file():
            psf = psf or folder / "psf.ome.tif"
    if psf is not None:
        stack = torch.from_numpy(read_tiff(psf, ndim=4, axes="(V, Z, h, w)", nonnegative=True).astype(np.float32))
    return {"cloud": cloud, "psf": stack}


def check_hexplane_field(name: str, value) -> None:
    """``model.hexplane.<name>``: positive sizes (at least 2 cells per axis), an increasing init range."""
    field = f"model.hexplane.{name}"
    if name == "spatial_resolution":
        require(len(value) == 3 and min(value) >= 2, field, value, "three sizes >= 2 (z, y, x)")
    elif name == "init_range":
        require(len(value) == 2 and value[0] <= value[1], field, value, "[low, high] with low <= high")
    elif name == "temporal_resolution":
        require(value >= 2, field, value, "an integer >= 2")
    else:
        require(value >= 1, field, value, "a positive integer")


class DynamicModule(pl.LightningModule):
    """A HexPlane + MLP deformation of frozen canonical Gaussians, fitted to every frame.

    Parameters
    ----------
    static : str
        The static stage's result: its ``last.ckpt`` or results folder (see :func:`load_static`),
        read and checked by the constructor when it exists (``fit`` needs it; ``validate`` and
        ``predict`` from a dynamic checkpoint do not).
    static_psf : str, optional
        PSF stack OME-TIFF to use instead of the static run's (default: the run's, else the
        datamodule's).
    hexplane : dict, optional
        :class:`~fgat.dynamics.hexplane.HexPlane` fields: ``channels`` (default 16),
        ``spatial_resolution`` (z, y, x; default 64 x 64 x 64 as Table S6), ``temporal_resolution``
        (default half the number of frames, as Table S6), ``levels`` (3), ``init_range``.
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
        Seed of the HexPlane initialisation (the MLP follows ``seed_everything``).

    Raises
    ------
    ValueError
        A setting out of its range, naming it (``model.lr_planes must be a positive number``).
    """

    per_frame = True  # the datamodule serves one frame per training step

    def __init__(self, static: str, static_psf: str | None = None, hexplane: dict | None = None, width: int = 128,
                 depth: int = 2, lr_planes: float = 1e-2, lr_mlp: float = 1e-3, p: int = 1,
                 lambda_fourier: float = 0.0, lambda_ssim: float = 0.0, lambda_tv: float = 1e-4,
                 lambda_sm: float = 1e-3, lambda_l1: float = 1e-4, seed: int = 0) -> None:
        super().__init__()
        known = {"channels", "spatial_resolution", "temporal_resolution", "levels", "init_range"}
        self.hexplane_options = parse_overrides(hexplane or {})  # overridden entries arrive as text
        unknown = set(self.hexplane_options) - known
        if unknown:
            raise ValueError(f"model.hexplane: unknown field(s) {sorted(unknown)}; expected some of {sorted(known)}")
        for name, value in self.hexplane_options.items():
            check_hexplane_field(name, value)
        require(width >= 1, "model.width", width, "a positive integer (MLP width)")
        require(depth >= 1, "model.depth", depth, "a positive integer (MLP hidden layers)")
        require_positive("model", lr_planes=lr_planes, lr_mlp=lr_mlp)
        require(p in (1, 2), "model.p", p, "1 (MAE) or 2 (MSE)")
        require_non_negative("model", lambda_fourier=lambda_fourier, lambda_ssim=lambda_ssim, lambda_tv=lambda_tv,
                             lambda_sm=lambda_sm, lambda_l1=lambda_l1)
        # Read (and check) the static run now, before any data is made; a checkpoint brings G0 itself.
        self._static = load_static(static, static_psf) if Path(static).exists() else None
        self.save_hyperparameters()
        self.field: DeformationField | None = None
        self.grid: dict = {}  # shape, voxel_size, origin, min_scale, reference_time, temporal_resolution
        self.scene = None
        self._operator: FLFMOperator | None = None
        self.last_loss = float("nan")
        self.baseline_scores: list[dict[str, float]] = []  # G_0 at every frame (no deformation)
        self._validation: dict[int, dict[str, float]] = {}

    # ------------------------------------------------------------------ set-up
    def setup(self, stage: str) -> None:
        if self.field is None and self._static is None and stage == "fit":
            raise FileNotFoundError(f"model.static: {self.hparams.static} does not exist (a static run's last.ckpt, "
                                    "or its results folder with gaussians.pt)")
        if self.scene is None:
            datamodule = self.trainer.datamodule
            datamodule.setup(stage)
            self.scene = datamodule.scene
        if self.field is None:
            if self._static is None:
                rank_zero_info(f"fgat: {self.hparams.static} not found: G0 and the PSF come from the checkpoint")
                return
            self._build_from_static()
        self._check_scene()

    def _build_from_static(self) -> None:
        """Frozen G0 and PSF from the static run (read by the constructor), and a fresh deformation field."""
        cloud, psf = self._static["cloud"], self._static["psf"]
        self._static = None
        frames, times = self.scene.sequence()
        grid = {"shape": list(cloud.shape), "voxel_size": cloud.voxel_size.tolist(), "origin": cloud.origin.tolist(),
                "min_scale": cloud.scale_range[0] * cloud.unit,
                "reference_time": 2 * float(times[self.scene.reference]) - 1,
                "temporal_resolution": max(2, len(frames) // 2)}
        with torch.no_grad():
            gaussians = (cloud.means, cloud.scales, cloud.quaternions, cloud.intensities)
            self._build({f"g0_{key}": value.detach().clone() for key, value in zip(GAUSSIAN_KEYS, gaussians)},
                        psf if psf is not None else torch.tensor(self.scene.psf, dtype=torch.float32), grid)

    def _build(self, gaussians: dict[str, Tensor], psf: Tensor, grid: dict) -> None:
        """Register the frozen buffers and create the field (from a static run or a checkpoint)."""
        for name, value in gaussians.items():
            self.register_buffer(name, value)
        self.register_buffer("psf", psf)
        self.grid = grid
        extent = (np.asarray(grid["shape"]) * np.asarray(grid["voxel_size"])).tolist()
        self.register_buffer("positions", normalized_positions(self.g0_means, grid["origin"], extent))
        options = {"channels": 16, "temporal_resolution": grid["temporal_resolution"], **self.hexplane_options,
                   "seed": self.hparams.seed}
        self.field = DeformationField(HexPlane(**options), width=self.hparams.width, depth=self.hparams.depth,
                                      reference_time=grid["reference_time"])

    def _check_scene(self) -> None:
        """The data must match the static run's grid and PSF; the no-deformation baseline on phantoms."""
        scene, source = self.scene, self.hparams.static_psf or self.hparams.static
        if tuple(self.grid["shape"]) != scene.volume_shape:
            raise ValueError(f"model.static: {self.hparams.static} holds Gaussians on a {tuple(self.grid['shape'])} "
                             f"grid, but the data's volume is {scene.volume_shape} (Z, Y, X)")
        if tuple(self.psf.shape[:2]) != tuple(scene.psf.shape[:2]):
            raise ValueError(f"model.static_psf: {source} has {tuple(self.psf.shape[:2])} (views, depths), the data "
                             f"{tuple(scene.psf.shape[:2])}")
        if scene.truth_frames is not None and not self.baseline_scores:
            with torch.no_grad():
                static_volume = self.voxelize(self.g0_means, self.g0_scales, self.g0_quats, self.g0_intensities)
            self.baseline_scores = [compare_volumes(static_volume.cpu().numpy(), truth) for truth in scene.truth_frames]

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["fgat_grid"] = self.grid

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """A checkpoint is self-contained: G0, PSF and field come back without the static run."""
        if self.field is not None:
            return
        state = checkpoint["state_dict"]
        self._build({f"g0_{key}": torch.empty_like(state[f"g0_{key}"]) for key in GAUSSIAN_KEYS},
                    torch.empty_like(state["psf"]), checkpoint["fgat_grid"])
        if self.scene is not None:
            self._check_scene()

    @property
    def operator(self) -> FLFMOperator:
        """The cached forward operator, rebuilt only when the PSF moves to another device."""
        if self._operator is None or self._operator.device != self.psf.device:
            self._operator = FLFMOperator(self.psf, tuple(self.grid["shape"]))
        return self._operator

    def configure_optimizers(self):
        h = self.hparams
        groups = [{"params": list(self.field.hexplane.parameters()), "lr": h.lr_planes, "name": "planes"},
                  {"params": [p for name, p in self.field.named_parameters() if not name.startswith("hexplane.")],
                   "lr": h.lr_mlp, "name": "mlp"}]
        return torch.optim.Adam(groups, eps=1e-15)

    # ------------------------------------------------------------------ the deformed scene
    def voxelize(self, means: Tensor, scales: Tensor, quats: Tensor, intensities: Tensor) -> Tensor:
        return voxelize(means, scales, quats, intensities, tuple(self.grid["shape"]), self.grid["voxel_size"],
                        self.grid["origin"])

    def gaussians_at(self, t: Tensor | float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``G_t`` (Eq. S22): means and scales (um), quaternions and intensities at normalised
        sequence time ``t`` in [0, 1]; ``G_0`` itself at the reference frame's time."""
        delta = self.field(self.positions, 2 * torch.as_tensor(t, dtype=self.positions.dtype,
                                                               device=self.positions.device) - 1)
        return apply_deformation(self.g0_means, self.g0_scales, self.g0_quats, self.g0_intensities, delta,
                                 min_scale=self.grid["min_scale"])

    def forward(self, t: Tensor | float) -> Tensor:
        """The volume ``V_t`` ``(Z, Y, X)`` at normalised time ``t`` (measurement units)."""
        return self.voxelize(*self.gaussians_at(t))

    # ------------------------------------------------------------------ training
    def on_fit_start(self) -> None:
        if self.scene.n_frames == 1:
            rank_zero_info("fgat: the data has a single frame: dynamic stage skipped (nothing moves); the static "
                           "stage's Gaussians G0 are the result")
            self.trainer.should_stop = True

    def on_train_batch_start(self, batch, batch_idx) -> None:
        self._step_started = time.perf_counter()

    def training_step(self, batch, batch_idx):
        prediction = self.operator.forward(self(batch["time"]))
        h = self.hparams
        terms = dynamic_loss(prediction, batch["views"], self.field.hexplane, p=h.p, lambda_fourier=h.lambda_fourier,
                             lambda_ssim=h.lambda_ssim, lambda_tv=h.lambda_tv, lambda_sm=h.lambda_sm,
                             lambda_l1=h.lambda_l1)
        self.last_loss = check_loss_terms(terms, f"step {self.global_step} (frame {int(batch['index'])})")
        log_loss_terms(self, terms)
        return terms["total"]

    def on_before_optimizer_step(self, optimizer) -> None:
        check_gradients(self.field.named_parameters(), self.global_step)

    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        synchronize(self.device)
        self.log("time/frame_step_ms", 1e3 * (time.perf_counter() - self._step_started))

    # ------------------------------------------------------------------ validation and prediction
    def on_validation_epoch_start(self) -> None:
        self._validation = {}

    def validation_step(self, batch, batch_idx):
        """Every frame: the data misfit ``L_pix`` of its views (measured data has no truth) and,
        on phantoms, the volume scores against its truth."""
        index = int(batch["index"])
        with torch.no_grad():
            volume = self(batch["time"])
            scores = {"pix": float(pixel_loss(self.operator.forward(volume), batch["views"], self.hparams.p))}
        if self.scene.truth_frames is not None:
            scores.update(compare_volumes(volume.cpu().numpy(), self.scene.truth_frames[index]))
        self._validation[index] = scores

    def on_validation_epoch_end(self) -> None:
        if not self._validation:
            return
        frames = [self._validation[k] for k in sorted(self._validation)]
        metrics = {"val/loss_pix": float(np.mean([s["pix"] for s in frames]))}
        if self.scene.truth_frames is not None:
            for suffix, scores in (("", frames), ("_no_deformation", self.baseline_scores)):
                for key, name in BASELINE_KEYS.items():
                    metrics[f"val/{name}{suffix}"] = float(np.mean([s[key] for s in scores]))
            self.log("val/psnr", metrics["val/psnr_volume"], prog_bar=True)
        self.log_dict(metrics)

    def predict_step(self, batch, batch_idx):
        with torch.no_grad():
            volume = self(batch["time"]) * self.scene.scale
        return {"index": int(batch["index"]), "time": float(batch["time"]), "volume": volume.cpu().numpy()}
