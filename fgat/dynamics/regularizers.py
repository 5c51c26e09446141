"""Regularisers of the HexPlane planes (Note S3.5.3, Eqs. S30-S32).

Planes are ``(1, C, R_a, R_b)`` tensors (:mod:`fgat.dynamics.hexplane`); the spatio-temporal ones
have time along the last axis. The dynamic loss (Eq. S29) weighs them by lambda_TV = 1e-4,
lambda_sm = 1e-3 and lambda_l1 = 1e-4 unless configured otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
from torch import Tensor


def _summed(planes: Iterable[Tensor], term) -> Tensor:
    """``sum over planes of term(P) / |P|`` (|P|: the plane's number of elements); 0 for none.
    Planes of one shape are stacked and ``term`` (elementwise along a leading plane axis) runs
    once per shape: a few operations instead of a few per plane, which is what a step of the
    dynamic stage on a GPU waits for."""
    by_shape: dict[tuple[int, ...], list[Tensor]] = {}
    for plane in planes:
        by_shape.setdefault(tuple(plane.shape), []).append(plane)
    total = None  # no zero made on the host and copied to the planes' device at every step
    for shape, group in by_shape.items():
        stacked = torch.stack(group) if len(group) > 1 else group[0][None]
        value = term(stacked).sum() / math.prod(shape)
        total = value if total is None else total + value
    return torch.zeros(()) if total is None else total


def plane_tv(planes: Iterable[Tensor]) -> Tensor:
    """Eq. S30: summed over planes, the squared first differences along both plane axes divided
    by the plane's number of elements."""
    return _summed(
        planes,
        lambda p: (
            (p[..., 1:, :] - p[..., :-1, :]).square().sum()
            + (p[..., :, 1:] - p[..., :, :-1]).square().sum()
        ),
    )


def temporal_smoothness(planes: Iterable[Tensor]) -> Tensor:
    """Eq. S31: summed over the spatio-temporal planes, the squared second differences along
    time (the last axis) divided by the plane's number of elements."""
    return _summed(planes, lambda p: (p[..., 2:] - 2 * p[..., 1:-1] + p[..., :-2]).square())


def plane_l1_to_one(planes: Iterable[Tensor]) -> Tensor:
    """Eq. S32: summed over the spatio-temporal planes, ``mean |1 - P|`` (zero for the identity)."""
    return _summed(planes, lambda p: (1 - p).abs())
