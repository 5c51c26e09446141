"""HexPlane 4D feature field (Note S3.3, Eqs. S17-S18).

The 4D space (x, y, z, t) is factorised into six planes: three spatial, (x, y), (x, z), (y, z),
and three spatio-temporal, (x, t), (y, t), (z, t). At each of ``L`` resolution levels every plane
holds ``C`` feature channels; the feature of a point is the elementwise product of the six
bilinear samples of a level, concatenated over the levels (``L C`` values).

Storage: the plane of the axis pair ``(a, b)`` is a tensor ``(1, C, R_a, R_b)``, sampled with
``grid_sample`` at ``(p_b, p_a)`` (``align_corners=True``), so that a spatio-temporal plane has
time along its last axis, as Eq. S31 indexes it. Coordinates are normalised to [-1, 1].
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

AXES = {"z": 0, "y": 1, "x": 2, "t": 3}  # fgat vectors are (z, y, x); time last
PLANES = (("x", "y"), ("x", "z"), ("y", "z"), ("x", "t"), ("y", "t"), ("z", "t"))  # Eq. S17
SPATIOTEMPORAL = PLANES[3:]


class HexPlane(nn.Module):
    """Six feature planes at ``levels`` resolutions.

    Parameters
    ----------
    channels : int
        Feature channels ``C`` per plane.
    spatial_resolution : (int, int, int)
        Base plane resolution along (z, y, x) (Table S6: 64 x 64 x 64); level ``l`` multiplies it
        by ``2**l``.
    temporal_resolution : int
        Resolution along t (Table S6: half the number of frames), the same at every level.
    levels : int
        Number of resolution levels ``L`` (3 in Eq. S18).
    init_range : (float, float)
        Uniform initialisation of the spatial planes; the spatio-temporal planes start at one,
        so that at initialisation the feature does not depend on time (the minimum of Eq. S32).
    seed : int
        Seed of the initialisation.
    """

    def __init__(self, channels: int = 32, spatial_resolution: Sequence[int] = (64, 64, 64),
                 temporal_resolution: int = 25, levels: int = 3, init_range: tuple[float, float] = (0.1, 0.5),
                 seed: int = 0) -> None:
        super().__init__()
        if channels < 1 or levels < 1 or temporal_resolution < 2 or len(spatial_resolution) != 3 \
                or min(spatial_resolution) < 2:
            raise ValueError("HexPlane needs channels >= 1, levels >= 1 and every resolution >= 2, got "
                             f"channels={channels}, levels={levels}, spatial={tuple(spatial_resolution)}, "
                             f"temporal={temporal_resolution}")
        self.channels, self.levels = channels, levels
        generator = torch.Generator().manual_seed(seed)
        self.planes = nn.ParameterList()
        for level in range(levels):
            size = {axis: int(spatial_resolution[AXES[axis]]) * 2**level for axis in "zyx"}
            size["t"] = int(temporal_resolution)
            for a, b in PLANES:
                shape = (1, channels, size[a], size[b])
                if b == "t":
                    plane = torch.ones(shape)
                else:
                    low, high = init_range
                    plane = torch.rand(shape, generator=generator) * (high - low) + low
                self.planes.append(nn.Parameter(plane))

    @property
    def feature_dim(self) -> int:
        return self.levels * self.channels

    def plane(self, level: int, pair: tuple[str, str]) -> Tensor:
        """The ``(1, C, R_a, R_b)`` plane of an axis pair at a level."""
        return self.planes[level * len(PLANES) + PLANES.index(pair)]

    def spatiotemporal_planes(self) -> list[Tensor]:
        return [self.plane(level, pair) for level in range(self.levels) for pair in SPATIOTEMPORAL]

    def forward(self, positions: Tensor, times: Tensor | float) -> Tensor:
        """Features ``(N, L C)`` (Eq. S18).

        Parameters
        ----------
        positions : Tensor
            ``(N, 3)`` normalised positions (z, y, x) in [-1, 1].
        times : Tensor or float
            Normalised time in [-1, 1], one value or ``(N,)``.
        """
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions must have shape (N, 3), got {tuple(positions.shape)}")
        times = torch.as_tensor(times, dtype=positions.dtype, device=positions.device).expand(positions.shape[0])
        coordinates = torch.cat([positions, times[:, None]], dim=1)  # (N, 4): z, y, x, t
        features = []
        for level in range(self.levels):
            product = None
            for pair in PLANES:
                grid = coordinates[:, [AXES[pair[1]], AXES[pair[0]]]].reshape(1, -1, 1, 2)
                plane = self.plane(level, pair).to(positions.dtype)
                sample = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)
                sample = sample.reshape(self.channels, -1).transpose(0, 1)  # (N, C)
                product = sample if product is None else product * sample
            features.append(product)
        return torch.cat(features, dim=1)
