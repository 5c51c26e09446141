"""Regularisers of the HexPlane planes (Note S3.5.3, Eqs. S30-S32).

Planes are ``(1, C, R_a, R_b)`` tensors (:mod:`fgat.dynamics.hexplane`); the spatio-temporal ones
have time along the last axis. The dynamic loss (Eq. S29) weighs them by lambda_TV = 1e-4,
lambda_sm = 1e-3 and lambda_l1 = 1e-4 unless configured otherwise.

The three terms run together (:func:`plane_regularisers`): planes of one shape are stacked once,
whichever terms they enter, and each term is a few operations on that stack (each sum of squared
differences one ``mse_loss``), not a few per plane and term. A step of the dynamic stage on a GPU
waits for the host to launch its operations, so their number, not their arithmetic, is what
these terms cost there; there the three run as one Triton kernel per plane each way
(:mod:`fgat.dynamics.regularizers_triton`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from fgat._core.devices import functorch_wrapped, triton_fits

TERMS = ("tv", "sm", "l1")
"""Eq. S30 (``tv``, every plane), Eq. S31 (``sm``) and Eq. S32 (``l1``, spatio-temporal planes)."""


def _squared_first_differences(planes: Tensor) -> Tensor:
    """Sum of the squared first differences of ``(..., R_a, R_b)`` along both plane axes
    (``mse_loss``: one operation and one backward per axis)."""
    rows = F.mse_loss(planes[..., 1:, :], planes[..., :-1, :], reduction="sum")
    return rows + F.mse_loss(planes[..., 1:], planes[..., :-1], reduction="sum")


def _squared_second_differences(planes: Tensor) -> Tensor:
    """Sum of the squared second differences of ``(..., R_a, R_b)`` along the last axis (time,
    for a spatio-temporal plane), ``(P[t + 1] + P[t - 1]) - 2 P[t]`` as one ``mse_loss``."""
    outer = planes[..., 2:] + planes[..., :-2]
    return F.mse_loss(outer, 2 * planes[..., 1:-1], reduction="sum")


def _group_terms(stack: Tensor, tv: range, temporal: range, terms: Sequence[str]) -> dict:
    """Each term's sum over the planes of one shape stacked, ``stack`` ``(G, ..., R_a, R_b)``:
    Eq. S30 on the planes ``tv``, Eqs. S31-S32 on the planes ``temporal``."""
    sums = {}
    if "tv" in terms and tv:
        sums["tv"] = _squared_first_differences(_rows(stack, tv))
    if "sm" in terms and temporal and stack.shape[-1] > 2:
        sums["sm"] = _squared_second_differences(_rows(stack, temporal))
    if "l1" in terms and temporal:
        sums["l1"] = (1 - _rows(stack, temporal)).abs().sum()
    return sums


def _rows(stack: Tensor, rows: range) -> Tensor:
    """``stack[rows]``, without a slice (nor its backward) when ``rows`` span the stack."""
    return stack if len(rows) == len(stack) else stack[rows.start : rows.stop]


def _by_shape(
    planes: Sequence[Tensor], spatiotemporal: Sequence[Tensor]
) -> dict[tuple[int, ...], tuple[list[Tensor], int, int]]:
    """Planes grouped by shape, each group ordered spatio-temporal only, both, Eq. S30's only,
    so that Eq. S30 runs on ``group[start:]`` and Eqs. S31-S32 on ``group[:stop]``: per shape
    ``(group, start, stop)``."""
    in_tv = {id(plane) for plane in planes}
    in_temporal = {id(plane) for plane in spatiotemporal}
    ordered = [p for p in spatiotemporal if id(p) not in in_tv]
    ordered += [p for p in spatiotemporal if id(p) in in_tv]
    ordered += [p for p in planes if id(p) not in in_temporal]
    groups: dict[tuple[int, ...], list[Tensor]] = {}
    for plane in ordered:
        groups.setdefault(tuple(plane.shape), []).append(plane)
    return {
        shape: (
            group,
            sum(id(p) not in in_tv for p in group),
            sum(id(p) in in_temporal for p in group),
        )
        for shape, group in groups.items()
    }


def plane_regularisers(
    planes: Sequence[Tensor],
    spatiotemporal: Sequence[Tensor] = (),
    terms: Sequence[str] = TERMS,
    *,
    backend: str = "auto",
) -> dict[str, Tensor]:
    """Eqs. S30-S32 together, each summed over its planes of ``term(P) / |P|`` (|P|: the
    plane's number of elements).

    Parameters
    ----------
    planes : sequence of Tensor
        The planes of Eq. S30 (all of a HexPlane's), each ``(..., R_a, R_b)``.
    spatiotemporal : sequence of Tensor
        The planes of Eqs. S31-S32, time along the last axis (the same tensors as in ``planes``
        where a plane enters both).
    terms : sequence of str
        Which of ``"tv"``, ``"sm"``, ``"l1"`` to compute.
    backend : {"auto", "torch", "triton"}
        ``torch``: the stacked PyTorch operations (any device and type). ``triton``: one kernel
        per plane each way (:mod:`fgat.dynamics.regularizers_triton`; float32 planes on a GPU or
        in Triton's interpreter). ``auto``: ``triton`` where it applies. The two agree to
        float32 rounding (tested).

    Returns
    -------
    dict of str to Tensor
        Each requested term, a scalar (0 where it has no planes).
    """
    unknown = set(terms) - set(TERMS)
    if unknown:
        raise ValueError(f"unknown plane regularisers {sorted(unknown)}; expected {TERMS}")
    every = list({id(p): p for p in (*planes, *spatiotemporal)}.values())
    if every and triton_fits(
        backend,
        every[0],
        "planes",
        "the Triton plane regularisers",
        lambda: {
            "float32 planes on one device": all(
                p.dtype == torch.float32 and p.device == every[0].device for p in every
            ),
            "no functorch transform": not functorch_wrapped(*every),
        },
    ):
        from fgat.dynamics.regularizers_triton import (  # Triton: only on the GPU path
            plane_terms,
        )

        in_tv, in_temporal = {id(p) for p in planes}, {id(p) for p in spatiotemporal}
        memberships = [
            (
                "tv" in terms and id(p) in in_tv,
                "sm" in terms and id(p) in in_temporal,
                "l1" in terms and id(p) in in_temporal,
            )
            for p in every
        ]
        totals = plane_terms(every, memberships).unbind()
        return {name: totals[TERMS.index(name)] for name in terms}
    totals: dict[str, Tensor] = {}
    for shape, (group, start, stop) in _by_shape(planes, spatiotemporal).items():
        tv, temporal = range(start, len(group)), range(stop)
        for name, value in _group_terms(torch.stack(group), tv, temporal, terms).items():
            scale = 1 / math.prod(shape)
            totals[name] = totals[name].add(value, alpha=scale) if name in totals else value * scale
    return {name: totals[name] if name in totals else torch.zeros(()) for name in terms}


def plane_tv(planes: Sequence[Tensor]) -> Tensor:
    """Eq. S30: summed over planes, the squared first differences along both plane axes divided
    by the plane's number of elements."""
    return plane_regularisers(planes, terms=("tv",))["tv"]


def temporal_smoothness(planes: Sequence[Tensor]) -> Tensor:
    """Eq. S31: summed over the spatio-temporal planes, the squared second differences along
    time (the last axis) divided by the plane's number of elements."""
    return plane_regularisers((), planes, terms=("sm",))["sm"]


def plane_l1_to_one(planes: Sequence[Tensor]) -> Tensor:
    """Eq. S32: summed over the spatio-temporal planes, ``mean |1 - P|`` (zero for the identity)."""
    return plane_regularisers((), planes, terms=("l1",))["l1"]
