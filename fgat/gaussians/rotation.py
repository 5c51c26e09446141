"""Quaternions (w, x, y, z) acting on (z, y, x)-ordered vectors.

fgat stores every 3D vector in (z, y, x) order. A unit quaternion ``q = (w, a, b, c)`` rotates
the right-handed (x, y, z) frame as usual; :func:`quaternion_to_rotation` returns that rotation
expressed on (z, y, x) vectors, so ``R @ v`` works directly on fgat's vectors.
"""

from __future__ import annotations

import torch
from torch import Tensor

QUATERNION_EPS = 1e-12
"""Floor of a quaternion's norm when it is normalised (here and in the Triton kernels)."""


def normalize_quaternion(q: Tensor, eps: float = QUATERNION_EPS) -> Tensor:
    """``q / |q|`` along the last axis (Eq. S15), guarded against zero quaternions."""
    return q / q.norm(dim=-1, keepdim=True).clamp(min=eps)


def quaternion_to_rotation(q: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` on (z, y, x) vectors from quaternions ``(..., 4)``
    (w, x, y, z).

    The input is normalised first.
    """
    w, x, y, z = normalize_quaternion(q).unbind(-1)
    # Standard matrix on (x, y, z) vectors ...
    xyz = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)
    # ... re-indexed for (z, y, x) vectors: reverse rows and columns.
    return xyz.flip(-1).flip(-2)


def quaternion_multiply(p: Tensor, q: Tensor) -> Tensor:
    """Hamilton product ``p (x) q`` of quaternions ``(..., 4)`` (w, x, y, z) (Eq. S22)."""
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        dim=-1,
    )


def covariance(scales: Tensor, quaternions: Tensor) -> Tensor:
    """``Sigma = R S S^T R^T`` (Eq. S14), ``(N, 3, 3)`` on (z, y, x) from scales ``(N, 3)``
    (standard deviations along the Gaussian's own axes, in the (z, y, x) order of its frame) and
    quaternions ``(N, 4)``."""
    rotation = quaternion_to_rotation(quaternions)
    m = rotation * scales[..., None, :]
    return m @ m.transpose(-1, -2)
