"""Regularisers of the HexPlane planes (Note S3.5.3, Eqs. S30-S32).

Planes are ``(1, C, R_a, R_b)`` tensors (:mod:`fgat.dynamics.hexplane`); the spatio-temporal ones
have time along the last axis.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

LAMBDA_TV, LAMBDA_SMOOTH, LAMBDA_L1 = 1e-4, 1e-3, 1e-4  # default weights of Note S3.5.3


def plane_tv(planes: Iterable[Tensor]) -> Tensor:
    """Eq. S30: summed over planes, the squared first differences along both plane axes divided
    by the plane's number of elements."""
    total = None
    for plane in planes:
        term = ((plane[..., 1:, :] - plane[..., :-1, :]).square().sum()
                + (plane[..., :, 1:] - plane[..., :, :-1]).square().sum()) / plane.numel()
        total = term if total is None else total + term
    return total if total is not None else torch.zeros(())


def temporal_smoothness(planes: Iterable[Tensor]) -> Tensor:
    """Eq. S31: summed over the spatio-temporal planes, the squared second differences along
    time (the last axis) divided by the plane's number of elements."""
    total = None
    for plane in planes:
        term = (plane[..., 2:] - 2 * plane[..., 1:-1] + plane[..., :-2]).square().sum() / plane.numel()
        total = term if total is None else total + term
    return total if total is not None else torch.zeros(())


def plane_l1_to_one(planes: Iterable[Tensor]) -> Tensor:
    """Eq. S32: summed over the spatio-temporal planes, ``mean |1 - P|`` (zero for the identity)."""
    total = None
    for plane in planes:
        term = (1 - plane).abs().sum() / plane.numel()
        total = term if total is None else total + term
    return total if total is not None else torch.zeros(())
