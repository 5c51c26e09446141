"""Deformation MLP and the deformation-application operator (Note S3.4, Eqs. S19-S22).

``DeformationField`` maps a canonical Gaussian centre and a time to ``D_n(t) = (dmu, ds, dr, di)``
through the HexPlane feature (Eq. S18), a shared ReLU trunk (depth 2, width 128) and four linear
heads (Eq. S20). The anchoring of Note S3.4 is exact: the heads' outputs at the reference time
are subtracted, and the rotation increment is the normalised ``(1, 0, 0, 0) + h_r(t) - h_r(t_ref)``,
so ``D_n(t_ref) = (0, 0, (1, 0, 0, 0), 0)`` whatever the weights and ``G_{t_ref} = G_0``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fgat._core.devices import constant, functorch_wrapped, triton_fits
from fgat.dynamics.hexplane import HexPlane
from fgat.gaussians.rotation import normalize_quaternion, quaternion_multiply

HEADS = {"means": 3, "scales": 3, "quats": 4, "intensities": 1}
IDENTITY_QUATERNION = (1.0, 0.0, 0.0, 0.0)


class DeformationField(nn.Module):
    """``D_n(t)`` of Eqs. S19-S20 with exact anchoring at ``t_ref``.

    Parameters
    ----------
    hexplane : HexPlane
        The feature field.
    width, depth : int
        Trunk width and number of hidden layers (Eq. S20: 128, 2).
    reference_time : float
        Normalised reference time ``t_ref`` in [-1, 1] (the frame the canonical Gaussians were
        fitted to).
    """

    def __init__(
        self, hexplane: HexPlane, width: int = 128, depth: int = 2, reference_time: float = 0.0
    ) -> None:
        super().__init__()
        if width < 1 or depth < 1:
            raise ValueError(
                f"the deformation MLP needs width and depth >= 1, got {width}, {depth}"
            )
        self.hexplane = hexplane
        self.reference_time = float(reference_time)
        layers, size = [], hexplane.feature_dim
        for _ in range(depth):
            layers += [nn.Linear(size, width), nn.ReLU()]
            size = width
        self.trunk = nn.Sequential(*layers)
        # No head biases: the anchoring subtracts them out.
        self.heads = nn.ModuleDict(
            {name: nn.Linear(width, dim, bias=False) for name, dim in HEADS.items()}
        )

    def raw(self, positions: Tensor, times: Tensor | float) -> dict[str, Tensor]:
        """Unanchored head outputs for normalised positions ``(N, 3)`` (z, y, x) and times."""
        return _by_head(self._outputs(self.hexplane(positions, times), self._head_weight()))

    def _head_weight(self) -> Tensor:
        """The four heads' weights stacked ``(11, width)``, in :data:`HEADS` order."""
        return torch.cat([head.weight for head in self.heads.values()])

    def _outputs(self, features: Tensor, weight: Tensor) -> Tensor:
        """The heads' outputs ``(N, 11)`` for HexPlane features ``(N, L C)``: the trunk, then
        one product with the stacked head weights ``weight`` (:meth:`_head_weight`)."""
        return F.linear(self.trunk(features), weight)

    def _outputs_now_and_reference(
        self, positions: Tensor, times: Tensor | float, backend: str = "auto"
    ) -> tuple[Tensor, Tensor]:
        """The heads' outputs ``(N, 11)`` at ``times`` and at ``t_ref``. The features share
        their spatial samples (:meth:`HexPlane.at_times`); each goes through the MLP on its own,
        so that at ``t_ref`` the two are equal bit for bit."""
        t_ref = constant((self.reference_time,), positions.device, positions.dtype)
        weight = self._head_weight()
        now, reference = (
            self._outputs(features, weight)
            for features in self.hexplane.at_times(positions, (times, t_ref), backend=backend)
        )
        return now, reference

    def forward(self, positions: Tensor, times: Tensor | float) -> dict[str, Tensor]:
        """Anchored deformation: ``means`` ``(N, 3)``, ``scales`` ``(N, 3)`` and ``intensities``
        ``(N,)`` increments, and unit rotation increments ``quats`` ``(N, 4)`` (w, x, y, z)."""
        return anchored_increments(*self._outputs_now_and_reference(positions, times))

    def deform(
        self,
        positions: Tensor,
        times: Tensor | float,
        gaussians: Sequence[Tensor],
        *,
        min_scale: float = 1e-6,
        backend: str = "auto",
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``G_t`` (Eq. S22): the canonical Gaussians ``gaussians`` (means, scales,
        quaternions, intensities, constant) deformed by the field at ``times``, as
        :func:`apply_deformation` of :meth:`forward`.

        Parameters
        ----------
        positions : Tensor
            ``(N, 3)`` the Gaussians' normalised canonical positions (z, y, x).
        times : Tensor or float
            Normalised time in [-1, 1].
        gaussians : sequence of Tensor
            ``(N, 3)`` means and scales (um), ``(N, 4)`` quaternions, ``(N,)`` intensities.
        min_scale : float
            Floor of the deformed scales, um.
        backend : {"auto", "torch", "triton"}
            ``torch``: PyTorch operations. ``triton``: the HexPlane's kernels
            (:meth:`HexPlane.at_times`) and one kernel for the anchoring and Eq. S22 each way
            (:mod:`fgat.dynamics.deformation_triton`; float32 on a GPU or in Triton's
            interpreter, no gradient to the canonical Gaussians). ``auto``: each where it
            applies. The two agree to float32 rounding (tested).
        """
        now, reference = self._outputs_now_and_reference(positions, times, backend)
        if triton_fits(
            backend,
            positions,
            "positions",
            "the Triton deformation",
            lambda: {
                "float32 Gaussians": all(t.dtype == torch.float32 for t in gaussians),
                "Gaussians that need no gradient": not any(t.requires_grad for t in gaussians),
                "no functorch transform": not functorch_wrapped(now, reference, *gaussians),
            },
        ):
            from fgat.dynamics.deformation_triton import (  # Triton: only on the GPU path
                deformed_gaussians,
            )

            return deformed_gaussians(now, reference, *gaussians, min_scale)
        increments = anchored_increments(now, reference)
        return apply_deformation(*gaussians, increments, min_scale=min_scale)


def anchored_increments(now: Tensor, reference: Tensor) -> dict[str, Tensor]:
    """``D_n(t)`` from the heads' outputs ``(N, 11)`` at ``t`` and at ``t_ref`` (Note S3.4):
    their differences, the rotation's as the unit quaternion ``(1, 0, 0, 0) + dr`` normalised;
    zero increments and the identity rotation where the two are equal."""
    delta = _by_head(now - reference)
    identity = constant(IDENTITY_QUATERNION, now.device, now.dtype)
    delta["quats"] = normalize_quaternion(identity + delta["quats"])
    delta["intensities"] = delta["intensities"].squeeze(-1)
    return delta


def _by_head(outputs: Tensor) -> dict[str, Tensor]:
    """Head outputs ``(N, 11)`` split by head (:data:`HEADS`)."""
    return dict(zip(HEADS, outputs.split(list(HEADS.values()), dim=1)))


def apply_deformation(
    means: Tensor,
    scales: Tensor,
    quats: Tensor,
    intensities: Tensor,
    delta: dict[str, Tensor],
    *,
    min_scale: float = 1e-6,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Eq. S22: ``mu + dmu``, ``s + ds``, ``dr (x) r`` and ``i + di`` on activated Gaussian
    attributes (means and scales in um, quaternions (w, x, y, z), peak intensities).

    Scales are kept above ``min_scale`` and intensities non-negative, so that no deformation
    produces an invalid Gaussian; at ``t_ref`` (zero increments) the inputs come back unchanged.
    """
    return (
        means + delta["means"],
        (scales + delta["scales"]).clamp(min=min_scale),
        quaternion_multiply(delta["quats"], quats),
        (intensities + delta["intensities"]).clamp(min=0),
    )


def normalized_positions(means: Tensor, origin: Sequence[float], extent: Sequence[float]) -> Tensor:
    """Means (um, (z, y, x)) mapped from the box ``[origin, origin + extent]`` to [-1, 1]^3."""
    origin = means.new_tensor(origin)
    extent = means.new_tensor(extent)
    return 2 * (means - origin) / extent - 1
