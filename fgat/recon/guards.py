"""What both stages do around an optimisation step: stop on non-finite numbers, step, and wait for
the GPU before reading a clock."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from fgat.recon.outcome import FitFailed


def check_step(
    terms: dict[str, Tensor], named_parameters, where: str, step: int
) -> dict[str, float]:
    """Raise ``FloatingPointError`` naming ``where`` (e.g. ``"step 12"``) and the first
    non-finite loss term, or else naming ``step`` and the first parameter whose gradient has
    NaN/Inf values (frozen parameters, with no gradient, are skipped); return every term as a
    float. The terms and the largest magnitude of each gradient (NaN where any entry is NaN) come
    to the host in one read (on a GPU each read waits for every kernel queued before it); the
    offending parameter is looked for only when there is one."""
    named = [(name, p.grad) for name, p in named_parameters if p.grad is not None]
    read = _host_values([*terms.values(), *_largest(named)])
    values = dict(zip(terms, read))
    for name, value in values.items():
        if not math.isfinite(value):
            raise FloatingPointError(
                f"{where}: loss term '{name}' is {value}; lower the learning rates or check the "
                "measurement"
            )
    if all(math.isfinite(value) for value in read[len(terms) :]):
        return values
    for name, gradient in named:
        if not torch.isfinite(gradient).all():
            raise FloatingPointError(f"step {step}: the gradient of '{name}' has NaN/Inf values")
    return values


def _host_values(tensors) -> list[float]:
    """Zero-dimensional tensors as floats (in their promoted dtype), in one read of the host
    (stacked outside autograd: one operation, where detaching each costs two)."""
    tensors = list(tensors)
    if not tensors:
        return []
    with torch.no_grad():
        return torch.stack(tensors).tolist()


def _largest(named: list[tuple[str, Tensor]]) -> list[Tensor]:
    """The largest magnitude of each gradient (NaN where any entry is NaN)."""
    if not named:
        return []
    return list(torch._foreach_norm([gradient for _, gradient in named], ord=math.inf))


def synchronize(device: torch.device) -> None:
    """Wait for queued CUDA work (timings); nothing on a CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def descend(
    terms: dict[str, Tensor], named_parameters, optimizer, where: str, step: int, before_step=None
) -> dict[str, float]:
    """Back-propagate ``terms["total"]`` and take one optimizer step, refusing non-finite loss
    terms and gradients (:func:`check_step`, after the backward pass and before the step: one
    read of the host a step, where a GPU would otherwise wait for its queue twice);
    ``before_step()`` runs between the check and the step (gradient statistics). Returns the
    terms as floats.

    Raises
    ------
    FitFailed
        The loss depends on no parameter any more: every Gaussian has left the grid (or been
        pruned), so nothing is left to fit (the same failure :func:`~fgat.recon.outcome.
        check_fit` reports for an empty volume, named here at the step it happened).
    FloatingPointError
        A non-finite loss term or gradient (:func:`check_step`).
    """
    if not terms["total"].requires_grad:
        raise FitFailed(
            f"the fit failed at {where}: no Gaussian is left inside the grid, so the loss "
            "depends on none of the parameters; lower the learning rates (model.lr_means) or "
            "check the measurement"
        )
    terms["total"].backward()
    values = check_step(terms, named_parameters, where, step)
    if before_step is not None:
        before_step()
    optimizer.step()
    return values
