"""Deformation MLP and the deformation-application operator (Note S3.4, Eqs. S19-S22).

``DeformationField`` maps a canonical Gaussian centre and a time to ``D_n(t) = (dmu, ds, dr, di)``
through the HexPlane feature (Eq. S18), a shared ReLU trunk (depth 2, width 128) and four linear
heads (Eq. S20). The anchoring of Note S3.4 is exact: the heads' outputs at the reference time
are subtracted, and the rotation increment is the normalised ``(1, 0, 0, 0) + h_r(t) - h_r(t_ref)``,
so ``D_n(t_ref) = (0, 0, (1, 0, 0, 0), 0)`` whatever the weights and ``G_{t_ref} = G_0``.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

from fgat.devices import constant
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
        return self._heads(self.hexplane(positions, times))

    def _heads(self, features: Tensor) -> dict[str, Tensor]:
        """The heads' outputs for HexPlane features ``(N, L C)``."""
        hidden = self.trunk(features)
        return {name: head(hidden) for name, head in self.heads.items()}

    def forward(self, positions: Tensor, times: Tensor | float) -> dict[str, Tensor]:
        """Anchored deformation: ``means`` ``(N, 3)``, ``scales`` ``(N, 3)`` and ``intensities``
        ``(N,)`` increments, and unit rotation increments ``quats`` ``(N, 4)`` (w, x, y, z).

        The features at ``times`` and at ``t_ref`` share their spatial samples
        (:meth:`HexPlane.at_times`); each goes through the MLP on its own, so that at ``t_ref``
        the two outputs are equal bit for bit."""
        t_ref = constant((self.reference_time,), positions.device, positions.dtype)
        now, reference = (
            self._heads(features) for features in self.hexplane.at_times(positions, (times, t_ref))
        )
        delta = {name: now[name] - reference[name] for name in HEADS}
        identity = constant(IDENTITY_QUATERNION, positions.device, positions.dtype)
        delta["quats"] = normalize_quaternion(identity + delta["quats"])
        delta["intensities"] = delta["intensities"].squeeze(-1)
        return delta


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
