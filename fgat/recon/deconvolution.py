"""Richardson-Lucy and scaled-heavy-ball (SHB) deconvolution for FLFM (Note S6, Algorithm S1).

Both work with any linear operator that has ``forward`` and ``adjoint`` (an
:class:`~fgat.optics.operator.FLFMOperator`). Internally the measurement is background
subtracted, clipped to be non-negative and divided by its maximum, and the operator is used with
the standard normalisation ``A^T 1 = 1``: its scale ``c = max(A^T 1)`` is divided out, which
leaves the multiplicative iteration unchanged and puts the estimate in the measurement's
intensity units, ``A V ~ I``. Algorithm S1 then runs exactly: uniform initialisation,
``beta_k = max(0, (k - 1) / (k + 2))``, the extrapolation floor
``epsilon = max(mean(I) 1e-6, 1e-8)``, the ``1e-10`` floor of the prediction and
non-negativity.

A real acquisition adds pixel weights ``w`` ``(V, Y, X)`` (a mask: 1 = use, 0 = ignore, e.g.
hot pixels) and reconstructs on a grid padded by a guard band (an operator with
``guard_px > 0``, :class:`~fgat.optics.acquisition.MeasuredOperator`), whose border voxels see
fewer pixels than the central ones. Either way ``A^T w`` is far from uniform, and the scalar
normalisation is replaced by the voxel-wise sensitivity of the Poisson maximum-likelihood RL
(EM) update for the weighted likelihood ``C_w(V) = sum_i w_i ((A V)_i - I_i log (A V)_i)``::

    V^{k+1} = P_+[ p^k * A^T(w * I / max(A p^k, 1e-10)) / max(A^T w, floor) ]

(``w = 1`` without weights), with the same momentum, floors and initialisation; ``A`` is still
divided by ``c = max(A^T w)``, so the sensitivity is at most 1, and ``floor = 1e-6`` lets voxels
that see less than a millionth of the best-seen voxel's weighted light decay instead of growing
without bound. Masked pixels take no part: neither in the update, the intensity scale nor the
reported cost (``C_w``). Without weights and guard band the iteration is Algorithm S1 exactly.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from fgat.recon.holdout import holdout_split

PREDICTION_FLOOR = 1e-10
SENSITIVITY_FLOOR = 1e-6  # of max(A^T w): the voxel-wise normalisation's floor


def momentum(k: int) -> float:
    """Heavy-ball coefficient ``beta_k = max(0, (k - 1) / (k + 2))`` of Algorithm S1 (line 6)."""
    return max(0.0, (k - 1) / (k + 2))


def poisson_cost(measurement: Tensor, prediction: Tensor, weights: Tensor | None = None) -> float:
    """Poisson negative log-likelihood ``<1, A V> - sum_i I_i log (A V)_i`` (Eq. S54), or with
    pixel ``weights`` ``w`` the weighted ``sum_i w_i ((A V)_i - I_i log (A V)_i)``.

    The logarithm is guarded by the ``1e-10`` floor of Algorithm S1.
    """
    terms = prediction - measurement * torch.log(prediction.clamp(min=PREDICTION_FLOOR))
    return float(terms.sum() if weights is None else (weights * terms).sum())


@dataclass
class DeconvolutionStep:
    """One iteration: index ``k`` (0-based), the estimate ``V^{k+1}`` in measurement units
    ``(Z, Y, X)`` (formed when first read), and the Poisson cost (Eq. S54) of the point whose
    prediction the step used (``V^k`` for RL, the extrapolated ``p^k`` for SHB), in the
    normalised units of the iteration; ``prediction`` ``(V, Y, X)`` is that point's prediction
    in the same units, the measurement (background subtracted) divided by ``image_scale``."""

    k: int
    normalized: Tensor
    scale: float
    cost: float
    prediction: Tensor
    image_scale: float

    @cached_property
    def estimate(self) -> Tensor:
        return self.normalized * self.scale


def iterate_deconvolution(
    measurement: Tensor,
    operator,
    iterations: int,
    *,
    method: str = "shb",
    init: Tensor | None = None,
    background: float = 0.0,
    weights: Tensor | None = None,
) -> Iterator[DeconvolutionStep]:
    """Run Algorithm S1 (``method="shb"``) or plain Richardson-Lucy (``"rl"``), yielding each step.

    Parameters
    ----------
    measurement : Tensor
        Per-view images ``(V, Y, X)`` in the operator's output space (photon counts or any
        intensity unit, with a constant ``background`` offset).
    operator
        Linear FLFM operator with ``forward`` ``(Z, Y', X') -> (V, Y, X)`` and ``adjoint`` (an
        :class:`~fgat.optics.operator.FLFMOperator`, ``Y' = Y``, or a
        :class:`~fgat.optics.acquisition.MeasuredOperator` on its padded grid).
    iterations : int
        Number of iterations ``K``.
    method : {"shb", "rl"}
        Scaled heavy-ball RL (Algorithm S1) or plain RL (``beta = 0``).
    init : Tensor, optional
        Initial estimate on the operator's grid ``(Z, Y', X')`` in measurement units; default
        uniform (line 2).
    background : float
        Constant offset subtracted from the measurement before the iteration.
    weights : Tensor, optional
        Pixel weights broadcastable to ``(V, Y, X)``, non-negative (a mask: 1 = use, 0 =
        ignore); with weights, or an operator with ``guard_px > 0``, the update uses the
        voxel-wise sensitivity ``A^T w`` (module docstring).
    """
    if method not in ("shb", "rl"):
        raise ValueError(f"method must be 'shb' or 'rl', got {method!r}")
    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
    dtype = getattr(operator, "dtype", torch.float32)
    device = getattr(operator, "device", measurement.device)
    image = torch.as_tensor(measurement, dtype=dtype, device=device)
    if not torch.isfinite(image).all():
        raise ValueError("measurement contains NaN or Inf values")
    image = (image - background).clamp(min=0)
    weights = pixel_weights(weights, image)
    voxelwise = weights is not None or getattr(operator, "guard_px", 0) > 0
    if weights is not None:  # masked pixels are gone: from the scale, the update and the cost
        image = torch.where(weights > 0, image, 0.0)
    image_scale = float(image.max())
    if image_scale <= 0:
        raise ValueError(
            f"measurement is zero everywhere after subtracting the background ({background})"
            + (" and masking" if weights is not None else "")
        )
    image = image / image_scale
    with torch.no_grad():
        # A^T w (A^T 1 without weights)
        sensitivity = operator.adjoint(torch.ones_like(image) if weights is None else weights)
        operator_scale = float(sensitivity.max())
        if operator_scale <= 0:
            raise ValueError("the operator's adjoint of ones is not positive: check the PSF stack")
        to_measurement_units = image_scale / operator_scale
        normalizer = (
            sensitivity.div_(operator_scale).clamp_(min=SENSITIVITY_FLOOR) if voxelwise else None
        )
        shape = sensitivity.shape
        if init is None:
            estimate = torch.ones(shape, dtype=dtype, device=device)  # line 2
        else:
            estimate = torch.as_tensor(init, dtype=dtype, device=device)
            if estimate.shape != shape:
                raise ValueError(f"init has shape {tuple(estimate.shape)}, expected {tuple(shape)}")
            if not torch.isfinite(estimate).all() or estimate.min() < 0:
                raise ValueError("init must be finite and non-negative")
            estimate = estimate / to_measurement_units
        previous = estimate.clone()  # line 3
        epsilon = max(float(image.mean()) * 1e-6, 1e-8)  # line 4
        for k in range(iterations):
            beta = momentum(k) if method == "shb" else 0.0
            if beta > 0:  # line 7
                point = torch.add(estimate, estimate - previous, alpha=beta).clamp_(min=epsilon)
            else:
                point = estimate.clamp(min=epsilon)
            prediction = operator.forward(point).div_(operator_scale)  # line 8
            ratio = image / prediction.clamp(min=PREDICTION_FLOOR)  # line 9
            if weights is not None:
                ratio.mul_(weights)
            update = point.mul_(operator.adjoint(ratio)).div_(operator_scale)  # line 10
            if normalizer is not None:
                update.div_(normalizer)
            update.clamp_(min=0)
            cost = poisson_cost(image, prediction, weights)
            previous, estimate = estimate, update  # line 11
            yield DeconvolutionStep(
                k, estimate, to_measurement_units, cost, prediction, image_scale
            )


def pixel_weights(weights: Tensor | None, image: Tensor) -> Tensor | None:
    """``weights`` as a tensor of ``image``'s shape, dtype and device (``None`` stays ``None``),
    checked: finite, non-negative and not all zero."""
    if weights is None:
        return None
    weights = torch.as_tensor(weights, dtype=image.dtype, device=image.device)
    try:
        weights = weights.expand_as(image)
    except RuntimeError:
        raise ValueError(
            f"weights of shape {tuple(weights.shape)} do not broadcast to the measurement's "
            f"{tuple(image.shape)}"
        ) from None
    if not torch.isfinite(weights).all() or weights.min() < 0 or weights.max() <= 0:
        raise ValueError("weights must be finite, non-negative and not all zero")
    return weights


def deconvolve(
    measurement: Tensor,
    operator,
    iterations: int,
    method: str = "shb",
    init: Tensor | None = None,
    background: float = 0.0,
    callback: Callable[[int, Tensor], None] | None = None,
    tol: float | None = None,
    weights: Tensor | None = None,
    holdout: float | None = None,
    patience: int = 20,
    seed: int = 0,
) -> Tensor:
    """Deconvolve FLFM views into a volume by SHB (Algorithm S1) or Richardson-Lucy.

    See :func:`iterate_deconvolution` for the parameters. ``callback(k, estimate)`` runs after
    every iteration with the estimate in measurement units. With ``tol``, the iteration stops
    early once the relative change of the Poisson cost (Eq. S54) between two iterations falls
    below ``tol``; callers that want the cost itself iterate :func:`iterate_deconvolution`.

    RL and SHB fit the noise once the object is resolved (the volume's error grows again while
    the cost keeps falling). With ``holdout``, that share of the pixels (drawn with ``seed``) is
    left out of the update, their Poisson cost under each step's prediction is watched, and the
    iteration stops ``patience`` iterations after that cost's minimum and returns the estimate
    of the minimum: a stopping rule that needs no truth.

    Returns
    -------
    Tensor
        ``(Z, Y', X')`` non-negative volume on the operator's grid with
        ``A V ~ measurement - background`` (on the unmasked pixels).
    """
    if tol is not None and not tol > 0:
        raise ValueError(f"tol must be positive, got {tol!r}")
    held = None
    if holdout is not None:
        if not 0 < holdout <= 0.5:
            raise ValueError(f"holdout must be a share of the pixels in (0, 0.5], got {holdout!r}")
        if not isinstance(patience, int) or patience < 1:
            raise ValueError(f"patience must be a positive integer, got {patience!r}")
        image = torch.as_tensor(measurement)
        mask = None if weights is None else pixel_weights(weights, image.to(torch.float32))
        weights, held = holdout_split(mask, tuple(image.shape), holdout, seed, image.device)
        held_image = (image - background).clamp(min=0)
    last_cost, best, best_cost, best_k = None, None, math.inf, -1
    for step in iterate_deconvolution(
        measurement,
        operator,
        iterations,
        method=method,
        init=init,
        background=background,
        weights=weights,
    ):
        estimate = step.estimate
        if callback is not None:
            callback(step.k, estimate)
        if held is not None:
            if step.k == 0:  # the iteration's units, dtype and device (its scale is fixed)
                held_image = held_image.to(step.prediction) / step.image_scale
                held = held.to(step.prediction)
            cost = poisson_cost(held_image, step.prediction, held)
            if cost < best_cost:
                best, best_cost, best_k = estimate, cost, step.k
            elif step.k - best_k >= patience:
                return best
        if tol is not None and last_cost is not None:
            if abs(step.cost - last_cost) <= tol * max(abs(step.cost), 1e-30):
                break
        last_cost = step.cost
    return estimate if held is None else best
