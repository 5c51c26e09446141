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
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fgat._core.devices import constant, functorch_wrapped, triton_fits
from fgat._core.validation import require

AXES = {"z": 0, "y": 1, "x": 2, "t": 3}  # fgat vectors are (z, y, x); time last
PLANES = (("x", "y"), ("x", "z"), ("y", "z"), ("x", "t"), ("y", "t"), ("z", "t"))  # Eq. S17
SPATIAL, SPATIOTEMPORAL = PLANES[:3], PLANES[3:]


@dataclass(frozen=True)
class HexPlaneSettings:
    """The HexPlane of the dynamic stage (Table S6).

    Attributes
    ----------
    channels : int
        Feature channels per plane (16 in Table S6).
    spatial_resolution : (int, int, int)
        Base plane resolution (z, y, x) (Table S6: 64 x 64 x 64).
    temporal_resolution : int or None
        Time nodes; ``None``: half the number of frames, at least 2 (Table S6).
    levels : int
        Resolution levels (3 in Eq. S18).
    init_range : (float, float)
        Uniform initialisation of the spatial planes.

    Raises
    ------
    ValueError
        A field out of its range, naming it (``hexplane.levels must be ...``).
    """

    channels: int = 16
    spatial_resolution: tuple[int, int, int] = (64, 64, 64)
    temporal_resolution: int | None = None
    levels: int = 3
    init_range: tuple[float, float] = (0.1, 0.5)

    def __post_init__(self) -> None:
        require(self.channels >= 1, "hexplane.channels", self.channels, "a positive integer")
        require(self.levels >= 1, "hexplane.levels", self.levels, "a positive integer")
        require(
            len(self.spatial_resolution) == 3 and min(self.spatial_resolution) >= 2,
            "hexplane.spatial_resolution",
            self.spatial_resolution,
            "three sizes >= 2 (z, y, x)",
        )
        require(
            self.temporal_resolution is None or self.temporal_resolution >= 2,
            "hexplane.temporal_resolution",
            self.temporal_resolution,
            "an integer >= 2, or null (half the number of frames)",
        )
        require(
            len(self.init_range) == 2 and self.init_range[0] <= self.init_range[1],
            "hexplane.init_range",
            self.init_range,
            "[low, high] with low <= high",
        )

    def build(self, n_frames: int, seed: int = 0) -> HexPlane:
        """The :class:`HexPlane` for a sequence of ``n_frames`` frames."""
        temporal = self.temporal_resolution or max(2, n_frames // 2)
        return HexPlane(
            self.channels,
            self.spatial_resolution,
            temporal,
            self.levels,
            self.init_range,
            seed=seed,
        )


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

    def __init__(
        self,
        channels: int = 32,
        spatial_resolution: Sequence[int] = (64, 64, 64),
        temporal_resolution: int = 25,
        levels: int = 3,
        init_range: tuple[float, float] = (0.1, 0.5),
        seed: int = 0,
    ) -> None:
        super().__init__()
        if (
            channels < 1
            or levels < 1
            or temporal_resolution < 2
            or len(spatial_resolution) != 3
            or min(spatial_resolution) < 2
        ):
            raise ValueError(
                "HexPlane needs channels >= 1, levels >= 1 and every resolution >= 2, got "
                f"channels={channels}, levels={levels}, spatial={tuple(spatial_resolution)}, "
                f"temporal={temporal_resolution}"
            )
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

    def forward(self, positions: Tensor, times: Tensor | float, *, backend: str = "auto") -> Tensor:
        """Features ``(N, L C)`` (Eq. S18).

        Parameters
        ----------
        positions : Tensor
            ``(N, 3)`` normalised positions (z, y, x) in [-1, 1].
        times : Tensor or float
            Normalised time in [-1, 1], one value or ``(N,)``.
        backend : {"auto", "torch", "triton"}
            As :meth:`at_times`.
        """
        return self.at_times(positions, (times,), backend=backend)[0]

    def at_times(
        self, positions: Tensor, times: Sequence[Tensor | float], *, backend: str = "auto"
    ) -> list[Tensor]:
        """Features ``(N, L C)`` of the same points at each of several times (Eq. S18).

        The spatial planes' samples do not depend on time, so they are taken once and shared;
        each time's features are those :meth:`forward` gives, bit for bit (the same samples,
        multiplied in ``PLANES`` order).

        Parameters
        ----------
        positions : Tensor
            ``(N, 3)`` normalised positions (z, y, x) in [-1, 1].
        times : sequence of Tensor or float
            Normalised times in [-1, 1], each one value or ``(N,)``.
        backend : {"auto", "torch", "triton"}
            ``torch``: ``grid_sample`` and products (any device and type). ``triton``: one
            kernel per level each way (:mod:`fgat.dynamics.hexplane_triton`; float32 points
            and planes on a GPU or in Triton's interpreter, one or two scalar times, no
            gradient to the points). ``auto``: ``triton`` where it applies. The two agree to
            float32 rounding (tested).

        Returns
        -------
        list of Tensor
            One ``(N, L C)`` feature per time.
        """
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions must have shape (N, 3), got {tuple(positions.shape)}")
        if self.fits_triton(backend, positions, times):
            from fgat.dynamics.hexplane_triton import (  # Triton: only on the GPU path
                hexplane_features,
            )

            stamps = torch.cat(
                [
                    torch.as_tensor(t, dtype=positions.dtype, device=positions.device).view(1)
                    for t in times
                ]
            )
            return list(hexplane_features(positions, stamps, list(self.planes)).unbind(0))
        n = positions.shape[0]
        stamps = [
            torch.as_tensor(t, dtype=positions.dtype, device=positions.device).expand(n)[:, None]
            for t in times
        ]
        at_time = [torch.cat([positions, stamp], dim=1) for stamp in stamps]  # (N, 4): z, y, x, t
        space_grids, time_grids = {}, [{} for _ in times]
        features: list[list[Tensor]] = [[] for _ in times]
        for level in range(self.levels):
            spatial = self._product(level, SPATIAL, positions, space_grids)
            for per_time, coordinates, grids in zip(features, at_time, time_grids):
                per_time.append(
                    self._product(level, SPATIOTEMPORAL, coordinates, grids, spatial).t()
                )
        return [torch.cat(per_time, dim=1) for per_time in features]

    def fits_triton(self, backend: str, positions: Tensor, times: Sequence) -> bool:
        """Whether :meth:`at_times` takes the Triton kernel for ``positions`` at ``times``
        (``auto`` takes the PyTorch path where the call does not fit it; ``triton`` is refused,
        naming what does not fit)."""
        return triton_fits(
            backend,
            positions,
            "positions",
            "the Triton HexPlane",
            lambda: {
                "float32 planes": all(p.dtype == torch.float32 for p in self.planes),
                "one or two times, each one value": len(times) in (1, 2)
                and all(torch.as_tensor(t).numel() == 1 for t in times),
                "positions that need no gradient": not positions.requires_grad,
                "no functorch transform": not functorch_wrapped(positions, *self.planes),
            },
        )

    def _product(
        self,
        level: int,
        pairs: tuple[tuple[str, str], ...],
        coordinates: Tensor,
        grids: dict,
        product: Tensor | None = None,
    ) -> Tensor:
        """``product`` (``(C, N)``; none: start from the first) times the level's samples of
        ``pairs`` at ``coordinates`` (``(N, >= 3)``: z, y, x and, for time, t), in order;
        ``grids`` keeps the sampling grids made from these coordinates for the other levels."""
        samples = {}
        for group in self._same_shape_pairs(level, pairs):
            if group not in grids:
                grids[group] = self._grid(group, coordinates)
            samples.update(zip(group, self._sample(level, group, grids[group])))
        for pair in pairs:
            product = samples[pair] if product is None else product * samples[pair]
        return product

    def _same_shape_pairs(
        self, level: int, pairs: tuple[tuple[str, str], ...]
    ) -> list[tuple[tuple[str, str], ...]]:
        """The level's planes of ``pairs`` grouped by shape (in the order of ``pairs``)."""
        groups: dict[tuple[int, ...], list[tuple[str, str]]] = {}
        for pair in pairs:
            groups.setdefault(tuple(self.plane(level, pair).shape), []).append(pair)
        return [tuple(group) for group in groups.values()]

    @staticmethod
    def _grid(pairs: tuple[tuple[str, str], ...], coordinates: Tensor) -> Tensor:
        """``grid_sample``'s ``(G, N, 1, 2)`` grid of the planes of ``pairs``: each point's
        ``(p_b, p_a)``."""
        columns = constant(
            tuple(AXES[axis] for a, b in pairs for axis in (b, a)), coordinates.device
        )
        grid = coordinates.index_select(1, columns).reshape(-1, len(pairs), 1, 2)
        return grid.transpose(0, 1).contiguous()

    def _sample(self, level: int, pairs: tuple[tuple[str, str], ...], grid: Tensor) -> tuple:
        """Bilinear samples ``(C, N)`` of the level's planes of ``pairs`` (one shape) on their
        grid: one ``grid_sample`` over the stacked planes (a plane per batch entry computes
        what it would alone)."""
        planes = torch.cat([self.plane(level, pair) for pair in pairs]).to(grid.dtype)
        sampled = F.grid_sample(
            planes, grid, mode="bilinear", padding_mode="border", align_corners=True
        )  # (G, C, N, 1)
        return sampled.reshape(len(pairs), self.channels, -1).unbind(0)
