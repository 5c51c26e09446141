"""The canonical Gaussian set ``G_0`` (Eq. S13) with the activations of Eq. S15.

Raw tensors live on the real line; the physical attributes are

* ``scales = sigmoid(raw_scales) (s_max - s_min) + s_min`` in units of the lateral voxel size
  (``s_min = 0.8``, ``s_max = 20`` by default), returned in world units;
* ``quaternions = raw_quats / |raw_quats|`` (w, x, y, z);
* ``intensities = softplus(raw_intensities)``.

Means are stored directly in world units (um, z, y, x).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from fgat.gaussians.rotation import normalize_quaternion
from fgat.gaussians.voxelize import voxelize
from fgat.io.checkpoints import load_torch_file
from fgat.io.files import atomic_path

PARAMETER_NAMES = ("means", "raw_scales", "raw_quats", "raw_intensities")


def inverse_softplus(x: Tensor) -> Tensor:
    """``softplus^{-1}(x) = x + log(1 - exp(-x))`` for ``x > 0`` (guarded near zero)."""
    x = x.clamp(min=1e-6)
    return x + torch.log(-torch.expm1(-x))


def inverse_sigmoid(p: Tensor) -> Tensor:
    """``logit(p)`` with ``p`` clamped into ``(0, 1)``."""
    p = p.clamp(1e-6, 1 - 1e-6)
    return torch.log(p) - torch.log1p(-p)


class GaussianCloud(nn.Module):
    """``N`` anisotropic Gaussians on a voxel grid, differentiable and resizable.

    Parameters
    ----------
    shape : (Z, Y, X)
        Grid the cloud renders to, voxels.
    voxel_size : (dz, dy, dx)
        Voxel size in um.
    n_gaussians : int
        Initial count (random placement; see :meth:`from_volume` and :meth:`random`).
    scale_range : (float, float)
        ``(s_min, s_max)`` of Eq. S15, in units of the lateral voxel size ``dx``.
    origin : (z0, y0, x0), optional
        World position of the grid corner; default centres the grid on 0.
    """

    def __init__(
        self,
        shape: Sequence[int],
        voxel_size: Sequence[float],
        n_gaussians: int = 0,
        *,
        scale_range: tuple[float, float] = (0.8, 20.0),
        origin: Sequence[float] | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.shape = tuple(int(s) for s in shape)
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ValueError(f"shape must be three positive sizes (Z, Y, X), got {shape!r}")
        if len(voxel_size) != 3 or min(voxel_size) <= 0:
            raise ValueError(
                f"voxel_size must be three positive sizes (dz, dy, dx) in um, got {voxel_size!r}"
            )
        low, high = scale_range
        if not 0 < low < high:
            raise ValueError(f"scale_range must satisfy 0 < s_min < s_max, got {scale_range!r}")
        self.scale_range = (float(low), float(high))
        self.register_buffer("voxel_size", torch.tensor(voxel_size, dtype=torch.float32))
        self._unit = float(self.voxel_size[2])  # kept on the host: read at every step
        extent = torch.tensor(self.shape, dtype=torch.float32) * self.voxel_size
        self.register_buffer(
            "origin", -extent / 2 if origin is None else torch.tensor(origin, dtype=torch.float32)
        )
        for name, width in zip(PARAMETER_NAMES, ((3,), (3,), (4,), ())):
            self.register_parameter(name, nn.Parameter(torch.zeros(0, *width)))
        if n_gaussians:
            self.random(n_gaussians, seed=seed)

    # ------------------------------------------------------------------ attributes (Eq. S15)
    @property
    def count(self) -> int:
        return self.means.shape[0]

    @property
    def unit(self) -> float:
        """World length of one scale unit: the lateral voxel size ``dx`` (um)."""
        return self._unit

    @property
    def scales(self) -> Tensor:
        low, high = self.scale_range
        return (torch.sigmoid(self.raw_scales) * (high - low) + low) * self.unit

    @property
    def quaternions(self) -> Tensor:
        return normalize_quaternion(self.raw_quats)

    @property
    def intensities(self) -> Tensor:
        return torch.nn.functional.softplus(self.raw_intensities)

    def forward(self, backend: str = "auto") -> Tensor:
        """The rendered volume ``(Z, Y, X)`` (Eq. S16), by the voxelizer ``backend``
        (:func:`~fgat.gaussians.voxelize.voxelize`)."""
        return voxelize(
            self.means,
            self.scales,
            self.quaternions,
            self.intensities,
            self.shape,
            self.voxel_size.tolist(),
            self.origin.tolist(),
            backend=backend,
        )

    # ------------------------------------------------------------------ initialisation
    def set_gaussians(
        self, means: Tensor, scales: Tensor, intensities: Tensor, quats: Tensor | None = None
    ) -> None:
        """Replace every Gaussian: ``means`` (N, 3) um, ``scales`` (N, 3) um,
        ``intensities`` (N,) > 0."""
        low, high = self.scale_range
        fraction = (scales / self.unit - low) / (high - low)
        quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(len(means), 4) if quats is None else quats
        values = {
            "means": means,
            "raw_scales": inverse_sigmoid(fraction),
            "raw_quats": quats,
            "raw_intensities": inverse_softplus(intensities),
        }
        device = self.voxel_size.device
        for name, value in values.items():
            setattr(
                self,
                name,
                nn.Parameter(value.detach().to(device=device, dtype=torch.float32).contiguous()),
            )

    def voxel_centers(self, index: Tensor) -> Tensor:
        """World positions (um) of integer voxel indices ``(N, 3)``."""
        return self.origin + (index.to(self.origin.dtype) + 0.5) * self.voxel_size

    def random(
        self, n: int, *, scale: float = 1.0, intensity: float = 0.1, seed: int = 0
    ) -> GaussianCloud:
        """``n`` isotropic Gaussians uniformly in the grid, ``scale`` in scale units."""
        generator = torch.Generator().manual_seed(seed)
        extent = torch.tensor(self.shape, dtype=torch.float32) * self.voxel_size.cpu()
        means = self.origin.cpu() + torch.rand(n, 3, generator=generator) * extent
        self.set_gaussians(
            means, torch.full((n, 3), scale * self.unit), torch.full((n,), intensity)
        )
        return self

    def from_volume(
        self,
        volume: Tensor | np.ndarray,
        n: int,
        *,
        scale: float = 1.0,
        seed: int = 0,
        weights: Tensor | np.ndarray | None = None,
    ) -> GaussianCloud:
        """Seed ``n`` Gaussians where a volume (e.g. an SHB reconstruction) is bright.

        Voxels are drawn with probability proportional to ``weights`` (default the volume's
        intensity; without replacement where possible), jittered within the voxel, with
        intensity equal to the voxel value (the volume and weights are taken to be on this
        cloud's grid).
        """
        volume = torch.as_tensor(np.asarray(volume, dtype=np.float32)).clamp(min=0)
        if tuple(volume.shape) != self.shape:
            raise ValueError(
                f"volume has shape {tuple(volume.shape)}, expected the cloud's grid {self.shape}"
            )
        values = volume.flatten()
        weights = (
            values
            if weights is None
            else torch.as_tensor(np.asarray(weights, dtype=np.float32)).clamp(min=0).flatten()
        )
        if weights.shape != values.shape:
            raise ValueError(f"weights must have the volume's shape {self.shape}")
        if float(weights.sum()) <= 0:
            raise ValueError("cannot seed Gaussians from an all-zero volume")
        generator = torch.Generator().manual_seed(seed)
        replacement = n > int((weights > 0).sum())
        flat = torch.multinomial(weights, n, replacement=replacement, generator=generator)
        index = torch.stack(torch.unravel_index(flat, self.shape), dim=1)
        jitter = (torch.rand(n, 3, generator=generator) - 0.5) * self.voxel_size.cpu()
        means = self.voxel_centers(index.to(self.origin.device)).cpu() + jitter
        intensity = values[flat].clamp(min=1e-3 * float(values.max()))
        self.set_gaussians(means, torch.full((n, 3), scale * self.unit), intensity)
        return self

    # ------------------------------------------------------------------ persistence
    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """Accept a state with any number of Gaussians: resize the parameters first."""
        for name in PARAMETER_NAMES:
            key = prefix + name
            if key in state_dict and state_dict[key].shape != getattr(self, name).shape:
                setattr(
                    self,
                    name,
                    nn.Parameter(torch.empty_like(state_dict[key], device=self.voxel_size.device)),
                )
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def save(self, path) -> None:
        """Write the Gaussians (physical attributes and raw parameters) as a ``.pt`` file,
        atomically."""
        payload = {
            "shape": self.shape,
            "voxel_size": self.voxel_size.tolist(),
            "origin": self.origin.tolist(),
            "scale_range": self.scale_range,
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
            "means_um": self.means.detach().cpu(),
            "scales_um": self.scales.detach().cpu(),
            "quaternions": self.quaternions.detach().cpu(),
            "intensities": self.intensities.detach().cpu(),
        }
        with atomic_path(path) as temporary:
            torch.save(payload, temporary)

    @classmethod
    def load(cls, path, *, source: str = "gaussians") -> GaussianCloud:
        """Read a cloud written by :meth:`save` (tensors and plain values only: no code in the file
        runs); ``source`` names the file's origin in errors (e.g. ``"model.static"``)."""
        payload = load_torch_file(path, source)
        missing = sorted(
            {"shape", "voxel_size", "origin", "scale_range", "state_dict"} - set(payload)
        )
        if missing:
            raise ValueError(
                f"{source}: {path} is not a Gaussian set written by fgat (no {', '.join(missing)})"
            )
        cloud = cls(
            payload["shape"],
            payload["voxel_size"],
            origin=payload["origin"],
            scale_range=tuple(payload["scale_range"]),
        )
        cloud.load_state_dict(payload["state_dict"])
        return cloud
