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
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

PREDICTION_FLOOR = 1e-10


def momentum(k: int) -> float:
    """Heavy-ball coefficient ``beta_k = max(0, (k - 1) / (k + 2))`` of Algorithm S1 (line 6)."""
    return max(0.0, (k - 1) / (k + 2))


def poisson_cost(measurement: Tensor, prediction: Tensor) -> float:
    """Poisson negative log-likelihood ``<1, A V> - sum_i I_i log (A V)_i`` (Eq. S54).

    The logarithm is guarded by the ``1e-10`` floor of Algorithm S1.
    """
    return float(
        prediction.sum() - (measurement * torch.log(prediction.clamp(min=PREDICTION_FLOOR))).sum()
    )


@dataclass
class DeconvolutionStep:
    """One iteration: index ``k`` (0-based), the estimate ``V^{k+1}`` in measurement units
    ``(Z, Y, X)`` (formed when first read), and the Poisson cost (Eq. S54) of the point whose
    prediction the step used (``V^k`` for RL, the extrapolated ``p^k`` for SHB), in the
    normalised units of the iteration."""

    k: int
    normalized: Tensor
    scale: float
    cost: float

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
) -> Iterator[DeconvolutionStep]:
    """Run Algorithm S1 (``method="shb"``) or plain Richardson-Lucy (``"rl"``), yielding each step.

    Parameters
    ----------
    measurement : Tensor
        Per-view images ``(V, Y, X)`` in the operator's output space (photon counts or any
        intensity unit, with a constant ``background`` offset).
    operator
        Linear FLFM operator with ``forward`` ``(Z, Y, X) -> (V, Y, X)`` and ``adjoint``.
    iterations : int
        Number of iterations ``K``.
    method : {"shb", "rl"}
        Scaled heavy-ball RL (Algorithm S1) or plain RL (``beta = 0``).
    init : Tensor, optional
        Initial estimate ``(Z, Y, X)`` in measurement units; default uniform (line 2).
    background : float
        Constant offset subtracted from the measurement before the iteration.
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
    image_scale = float(image.max())
    if image_scale <= 0:
        raise ValueError(
            f"measurement is zero everywhere after subtracting the background ({background})"
        )
    image = image / image_scale
    with torch.no_grad():
        sensitivity = operator.adjoint(torch.ones_like(image))  # A^T 1
        operator_scale = float(sensitivity.max())
        if operator_scale <= 0:
            raise ValueError("the operator's adjoint of ones is not positive: check the PSF stack")
        to_measurement_units = image_scale / operator_scale
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
            update = (
                point.mul_(operator.adjoint(ratio)).div_(operator_scale).clamp_(min=0)
            )  # line 10
            cost = poisson_cost(image, prediction)
            previous, estimate = estimate, update  # line 11
            yield DeconvolutionStep(k, estimate, to_measurement_units, cost)


def deconvolve(
    measurement: Tensor,
    operator,
    iterations: int,
    method: str = "shb",
    init: Tensor | None = None,
    background: float = 0.0,
    callback: Callable[[int, Tensor], None] | None = None,
    tol: float | None = None,
) -> Tensor:
    """Deconvolve FLFM views into a volume by SHB (Algorithm S1) or Richardson-Lucy.

    See :func:`iterate_deconvolution` for the parameters. ``callback(k, estimate)`` runs after
    every iteration with the estimate in measurement units. With ``tol``, the iteration stops
    early once the relative change of the Poisson cost (Eq. S54) between two iterations falls
    below ``tol``; callers that want the cost itself iterate :func:`iterate_deconvolution`.

    Returns
    -------
    Tensor
        ``(Z, Y, X)`` non-negative volume with ``A V ~ measurement - background``.
    """
    if tol is not None and not tol > 0:
        raise ValueError(f"tol must be positive, got {tol!r}")
    last_cost = None
    for step in iterate_deconvolution(
        measurement, operator, iterations, method=method, init=init, background=background
    ):
        estimate = step.estimate
        if callback is not None:
            callback(step.k, estimate)
        if tol is not None and last_cost is not None:
            if abs(step.cost - last_cost) <= tol * max(abs(step.cost), 1e-30):
                break
        last_cost = step.cost
    return estimate
