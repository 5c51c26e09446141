"""The estimated optics as logged numbers: the JPGM parameters, their standard errors at the end of
a fit (:func:`identifiability`) and, on phantoms, their errors."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from fgat.optics.crossinfo import cross_information, estimated_blocks
from fgat.optics.operator import operator_memory
from fgat.optics.psf import JPGM
from fgat.recon import names
from fgat.recon.estimation import psf_errors, remove_scene_gauge


def parameter_metrics(
    indices, coefficients: Tensor, intercepts: Tensor, slopes: Tensor
) -> dict[str, float]:
    """``zernike/c{j}`` (waves), ``shift/b{v}_y``, ``shift/b{v}_x``, ``shift/s{v}_y``,
    ``shift/s{v}_x`` (pixels)."""
    metrics = {
        names.zernike_name(j): float(c) for j, c in zip(indices, coefficients.detach().tolist())
    }
    for kind, values in (("b", intercepts), ("s", slopes)):
        for v, (row, col) in enumerate(values.detach().tolist()):
            metrics[names.shift_name(kind, v, "y")], metrics[names.shift_name(kind, v, "x")] = (
                row,
                col,
            )
    return metrics


def optics_metrics(jpgm: JPGM) -> dict[str, float]:
    """:func:`parameter_metrics` of a JPGM's current parameters."""
    return parameter_metrics(
        jpgm.zernike_indices, jpgm.zernike_coefficients, jpgm.intercepts, jpgm.slopes
    )


def optics_errors(
    jpgm: JPGM, truth: tuple[Tensor, Tensor, Tensor], psf: Tensor, true_psf: Tensor
) -> dict[str, float]:
    """Distance of the estimated optics to the truth ``(c (K,), b (V, 2), s (V, 2))``:
    ``zernike/residual_normalized`` ``||c - c_gt|| / ||c_gt||`` (sigma of Fig. S9a; NaN without
    aberration), the largest intercept and slope errors (pixels), also without the part a moved
    scene explains (:func:`~fgat.recon.estimation.remove_scene_gauge`), and the relative errors
    of the PSF stack ``psf`` to ``true_psf`` (:func:`~fgat.recon.estimation.psf_errors`)."""
    coefficients, intercepts, slopes = (t.to(jpgm.intercepts) for t in truth)
    norm = coefficients.norm()  # no aberration (Fig. S5): sigma undefined
    residual = (
        (jpgm.zernike_coefficients.detach() - coefficients).norm() / norm if norm > 0 else math.nan
    )
    metrics = {names.ZERNIKE_RESIDUAL: float(residual)}
    offsets = jpgm.centers - jpgm.centers[:1]
    errors = iter(names.SHIFT_ERRORS)  # (intercept, intercept gauge-free, slope, slope gauge-free)
    for estimate, true in ((jpgm.intercepts, intercepts), (jpgm.slopes, slopes)):
        difference = estimate.detach() - true
        metrics[next(errors)] = float(difference.abs().max())
        metrics[next(errors)] = float(remove_scene_gauge(difference, offsets).abs().max())
    return {**metrics, **psf_errors(psf, true_psf, names.PSF_ERROR)}


STDERR_GROUPS = ("zernike", "intercepts", "slopes")
"""Groups of :meth:`~fgat.optics.crossinfo.CrossInformation.standard_errors`, in the order of the
JPGM parameters (coefficients, intercepts, slopes)."""

IDENTIFIABILITY_COLUMNS = (
    "parameter",
    "estimate",
    "stderr",
    "stderr_noise",
    "correction",
    "relative_stderr",
    "flagged",
)
TRUTH_COLUMNS = ("truth", "error", "within_2se")


@dataclass(frozen=True, eq=False)
class Identifiability:
    """Standard errors of the estimated optics at the end of a fit, and the flagged terms.

    Attributes
    ----------
    names : tuple of str
        Logged names of the estimated parameters, in :func:`parameter_metrics` order
        (``zernike/c5``, ..., ``shift/b0_y``, ``shift/b0_x``, ..., ``shift/s0_y``, ...).
    estimates : numpy.ndarray
        Their values (waves for Zernike terms, pixels for shifts).
    noise_stderrs : numpy.ndarray
        Their standard errors under the noise with the volume held fixed (Note S4), each
        pixel's variance from its residual (the sandwich estimate).
    corrections : numpy.ndarray
        The optics part of the joint Gauss-Newton step with the volume free
        (:func:`~fgat.recon.joint_step.joint_correction`): how far the data still pull
        each parameter from where the alternating fit stopped.
    noise_sigma : float
        The residual's uniform noise level (:func:`noise_level`), normalised view units.
    n_pixels, n_parameters : int
        Pixels of the data fit and parameters it estimated (the residual's degrees of freedom
        are their difference).
    tolerance : float
        A term is flagged when its standard error exceeds this fraction of ``|estimate|``.
    truth : numpy.ndarray or None
        The true values on phantoms.
    """

    names: tuple[str, ...]
    estimates: np.ndarray
    noise_stderrs: np.ndarray
    corrections: np.ndarray
    noise_sigma: float
    n_pixels: int
    n_parameters: int
    tolerance: float
    truth: np.ndarray | None = None

    @property
    def stderrs(self) -> np.ndarray:
        """The standard errors reported: ``sqrt(noise_stderrs^2 + corrections^2)``, the noise's
        share and the distance to the joint optimum the fit has not covered."""
        return np.hypot(self.noise_stderrs, self.corrections)

    @property
    def flagged(self) -> np.ndarray:
        """Whether each standard error exceeds ``tolerance * |estimate|`` (an estimate of
        exactly 0 is flagged)."""
        return self.stderrs > self.tolerance * np.abs(self.estimates)

    @property
    def within_2se(self) -> np.ndarray | None:
        """Whether each true error ``|estimate - truth|`` is at most two standard errors
        (``None`` without a truth)."""
        if self.truth is None:
            return None
        return np.abs(self.estimates - self.truth) <= 2 * self.stderrs

    def metrics(self) -> dict[str, float]:
        """``<group>/stderr_<name>`` per parameter
        (:func:`~fgat.recon.names.stderr_name`), the noise level, the number of flagged
        terms and, with a truth, the fraction of true errors within two standard errors."""
        metrics = {names.stderr_name(n): float(s) for n, s in zip(self.names, self.stderrs)}
        metrics[names.NOISE_SIGMA] = self.noise_sigma
        metrics[names.FLAGGED] = float(self.flagged.sum())
        if self.truth is not None:
            metrics[names.WITHIN_2SE] = float(self.within_2se.mean())
        return metrics

    def columns(self) -> tuple[str, ...]:
        """The columns of :meth:`rows` (the truth's with a truth)."""
        return IDENTIFIABILITY_COLUMNS + (TRUTH_COLUMNS if self.truth is not None else ())

    def rows(self) -> list[dict]:
        """One row per parameter: estimate, standard error, ``stderr / |estimate|``, flagged
        (0/1) and, with a truth, the truth, ``estimate - truth`` and whether it is within two
        standard errors (0/1)."""
        magnitude = np.abs(self.estimates)
        relative = np.divide(
            self.stderrs, magnitude, out=np.full_like(self.stderrs, np.inf), where=magnitude > 0
        )
        rows = []
        for k, name in enumerate(self.names):
            row = {
                "parameter": name,
                "estimate": float(self.estimates[k]),
                "stderr": float(self.stderrs[k]),
                "stderr_noise": float(self.noise_stderrs[k]),
                "correction": float(self.corrections[k]),
                "relative_stderr": float(relative[k]),
                "flagged": int(self.flagged[k]),
            }
            if self.truth is not None:
                row["truth"] = float(self.truth[k])
                row["error"] = float(self.estimates[k] - self.truth[k])
                row["within_2se"] = int(self.within_2se[k])
            rows.append(row)
        return rows


def noise_level(residual: Tensor, mask: Tensor | None, n_parameters: int) -> tuple[float, int]:
    """The pixel noise standard deviation of a least-squares fit from its residual.

    ``sigma^2 = sum m r^2 / (sum m - P)``: the squared residuals ``r`` over the used pixels
    (mask ``m``; all without one) divided by their number less the ``P`` estimated parameters.

    Parameters
    ----------
    residual : Tensor
        ``(V, Y, X)`` prediction minus data.
    mask : Tensor, optional
        Pixel mask broadcastable to ``residual`` (1 = used).
    n_parameters : int
        Parameters the fit estimated.

    Returns
    -------
    (float, int)
        ``sigma`` in the residual's units and the number of used pixels.

    Raises
    ------
    ValueError
        No more used pixels than parameters.
    """
    residual = residual.detach()
    used = torch.ones_like(residual) if mask is None else mask.to(residual).expand_as(residual)
    n_pixels = int(used.sum())
    if n_pixels <= n_parameters:
        raise ValueError(
            f"the noise level needs more used pixels ({n_pixels}) than estimated parameters "
            f"({n_parameters})"
        )
    squares = torch.where(used > 0, residual, 0.0).square()
    return float((squares.sum() / (n_pixels - n_parameters)).sqrt()), n_pixels


def identifiability(
    jpgm: JPGM,
    volume: Tensor,
    measurement: Tensor,
    estimate: str,
    *,
    operator: Callable[[Tensor], object],
    n_parameters: int,
    tolerance: float,
    mask: Tensor | None = None,
    truth: tuple[Tensor, Tensor, Tensor] | None = None,
    correction: Callable[..., dict[str, Tensor]] | None = None,
    chunk_size: int | None = 8,
    depth_chunk: int | None = None,
) -> Identifiability:
    """Gauss-Newton standard errors of the estimated optics from the local cross-information
    (Note S4) at the point ``(jpgm, volume)``.

    The noise part is the least-squares covariance in the pixel-L2 metric (the mask as diagonal
    weights), whatever loss the fit used (its pixel loss may be L1), with the volume held fixed
    (Eq. S37) and each pixel's noise variance taken from its residual: the sandwich
    ``H^-1 J^T diag(r^2) J H^-1``
    (:meth:`~fgat.optics.crossinfo.CrossInformation.sandwich_errors`), ``H`` being ``A`` when
    only the Zernike terms were estimated, ``D`` for the shifts alone and the whole Hessian for a
    joint fit (whose blocks of ``H^-1`` are the inverse Schur complements of Eqs. S49-S50). Photon
    noise is largest on the bright pixels that carry the information, so this is about 1.8x the
    standard error under one uniform ``sigma`` (:func:`noise_level`, reported beside it).

    The noise alone leaves out the error of a fit that stopped short of the joint optimum of
    volume and optics (the alternating fit crawls along the directions where the two trade off),
    which dominates on the Fig. S6 quick trials: half of the true errors lie within two noise
    standard errors there. So the reported standard error adds, in quadrature, ``correction``:
    the optics part of the joint Gauss-Newton step with the volume free
    (:func:`~fgat.recon.joint_step.joint_correction`); with it, 91% of them do
    (``reproduce/identifiability_coverage.py``).

    Parameters
    ----------
    jpgm : JPGM
        The estimated optics (float64 recommended: its dtype is the computation's).
    volume : Tensor
        The object on the operator's grid, held fixed.
    measurement : Tensor
        ``(V, Y, X)`` data, in the units of the predicted views.
    estimate : {"zernike", "shifts", "joint"}
        The groups the fit estimated.
    operator : callable
        ``operator(psf_stack)`` with ``.forward(volume) -> (V, Y, X)``: the fit's forward model.
    n_parameters : int
        Every parameter the fit estimated (Gaussians, optics, gains): :func:`noise_level`.
    tolerance : float
        :attr:`Identifiability.tolerance`.
    mask : Tensor, optional
        Pixel mask of the data fit, broadcastable to ``(V, Y, X)``.
    truth : (Tensor, Tensor, Tensor), optional
        The true ``(c (K,), b (V, 2), s (V, 2))`` on phantoms.
    correction : callable, optional
        ``correction(jacobians=(J_P, J_G)) -> {JPGM parameter name: its joint Gauss-Newton
        step}``, given the Jacobians computed here (e.g.
        :func:`~fgat.recon.joint_step.joint_correction` with its other arguments
        bound); default none (zero steps).
    chunk_size : int or None
        Jacobian columns per batched pass (:func:`~fgat.optics.crossinfo.cross_information`).
    depth_chunk : int, optional
        Planes per pass (default all; :func:`identifiability_plan` picks both to fit memory).

    Returns
    -------
    Identifiability

    Raises
    ------
    ValueError
        A block of the Hessian that is not positive definite, or too few used pixels.
    """
    dtype = jpgm.zernike_coefficients.dtype
    measurement = measurement.to(dtype)
    volume = volume.detach().to(dtype)
    weights = None if mask is None else mask.to(measurement).expand_as(measurement).reshape(-1)
    information = cross_information(
        jpgm,
        volume,
        weights=weights,
        operator=operator,
        chunk_size=chunk_size,
        blocks=estimated_blocks(estimate),
        depth_chunk=depth_chunk,
    )
    with torch.no_grad():
        residual = operator(jpgm()).forward(volume) - measurement
    sigma, n_pixels = noise_level(residual, mask, n_parameters)
    errors = information.sandwich_errors(residual, estimate, weights)
    parameters = ("zernike_coefficients", "intercepts", "slopes")
    values = dict(zip(STDERR_GROUPS, (getattr(jpgm, name) for name in parameters)))
    jacobians = (information.jacobian_pupil, information.jacobian_geometry)
    correction = {} if correction is None else correction(jacobians=jacobians)
    steps = {
        group: correction.get(name, torch.zeros_like(values[group]))
        for group, name in zip(STDERR_GROUPS, parameters)
    }

    def flat(tensors: dict[str, Tensor]) -> np.ndarray:
        """The estimated groups' entries of ``tensors``, concatenated in row-major order."""
        return np.concatenate(
            [tensors[g].detach().cpu().double().reshape(-1).numpy() for g in errors]
        )

    return Identifiability(
        tuple(name for group in errors for name in group_names(jpgm, group)),
        flat(values),
        flat(errors),
        flat(steps),
        sigma,
        n_pixels,
        int(n_parameters),
        float(tolerance),
        None if truth is None else flat(dict(zip(STDERR_GROUPS, truth))),
    )


def identifiability_memory(
    jpgm: JPGM,
    volume_shape: tuple[int, int, int],
    guard_px: int = 0,
    chunk_size: int = 8,
    estimate: str = "joint",
    depth_chunk: int | None = None,
) -> int:
    """Bytes of :func:`identifiability` at the JPGM's dtype, an upper bound from the shapes.

    With ``P`` Jacobian columns (``K`` Zernike terms, ``4V`` shifts or both, as ``estimate``
    says) and ``N = V Y X`` predicted pixels: the Jacobian three times (the accumulated
    columns, one pass's and the transposed result; the joint step's weighted copy comes after
    the first two are freed: ``3 P N e``), and a forward pass of the JPGM
    (:meth:`~fgat.optics.psf.JPGM.memory_bytes`) and of the forward model
    (:func:`~fgat.recon.operator_memory`, views ``volume_shape[1:]``, guard band
    ``guard_px``) on ``depth_chunk`` planes (default all), with ``chunk_size`` tangents of the
    same size beside it (the vectorised Jacobian-vector products share the primal pass). On a
    37-view stack of 121 planes of 127 px crops these passes are tens of GB at eight columns
    over the whole stack, against a few GB for the Jacobian itself: hence
    :func:`identifiability_plan`.
    """
    item = jpgm.zernike_coefficients.element_size()
    n_views = jpgm.n_views
    planes = jpgm.n_depths if depth_chunk is None else min(int(depth_chunk), jpgm.n_depths)
    columns = identifiability_columns(jpgm, estimate)
    pixels = n_views * volume_shape[1] * volume_shape[2]
    side = 2 * jpgm.radius + 1
    forward = jpgm.memory_bytes(planes) + operator_memory(
        (n_views, planes, side, side),
        (planes, *volume_shape[1:]),
        itemsize=item,
        adjoint=False,
        guard_px=guard_px,
    )
    return 3 * columns * pixels * item + (1 + min(chunk_size, columns)) * forward


def identifiability_columns(jpgm: JPGM, estimate: str) -> int:
    """Jacobian columns of :func:`identifiability`: ``K`` Zernike terms and/or ``4V`` shifts."""
    blocks = estimated_blocks(estimate)
    return len(jpgm.zernike_indices) * ("pupil" in blocks) + 4 * jpgm.n_views * (
        "geometry" in blocks
    )


@dataclass(frozen=True)
class IdentifiabilityPlan:
    """How :func:`identifiability` is split to fit in memory: ``chunk_size`` Jacobian columns
    and ``depth_chunk`` planes per pass, and its estimated peak ``nbytes``."""

    chunk_size: int
    depth_chunk: int
    nbytes: int


def identifiability_plan(
    jpgm: JPGM,
    volume_shape: tuple[int, int, int],
    guard_px: int = 0,
    estimate: str = "joint",
    available: int | None = None,
    *,
    chunk_size: int = 8,
    fraction: float = 0.8,
) -> IdentifiabilityPlan:
    """The largest passes of :func:`identifiability` within ``fraction`` of ``available``
    bytes (:func:`identifiability_memory`): all planes and ``chunk_size`` columns when they
    fit, else the planes halved, then the columns, down to one of each (whose bytes the caller
    checks against the machine: the Jacobian itself must fit). ``available=None``: no limit."""
    budget = None if available is None else fraction * available
    planes, columns = (
        jpgm.n_depths,
        max(1, min(chunk_size, identifiability_columns(jpgm, estimate))),
    )

    def size(columns: int, planes: int) -> int:
        return identifiability_memory(jpgm, volume_shape, guard_px, columns, estimate, planes)

    while budget is not None and size(columns, planes) > budget and planes > 1:
        planes = -(-planes // 2)
    while budget is not None and size(columns, planes) > budget and columns > 1:
        columns = -(-columns // 2)
    return IdentifiabilityPlan(columns, planes, size(columns, planes))


def group_names(jpgm: JPGM, group: str) -> list[str]:
    """Logged names of a parameter group of :data:`STDERR_GROUPS` in row-major order:
    ``zernike/c{j}``, or ``shift/b{v}_y``, ``shift/b{v}_x`` (``s`` for the slopes)."""
    if group == "zernike":
        return [names.zernike_name(j) for j in jpgm.zernike_indices]
    kind = {"intercepts": "b", "slopes": "s"}[group]
    return [names.shift_name(kind, v, axis) for v in range(jpgm.n_views) for axis in ("y", "x")]
