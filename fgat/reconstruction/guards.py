"""What both stages do around an optimisation step: stop on non-finite numbers, step, and wait for
the GPU before reading a clock."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def check_loss_terms(terms: dict[str, Tensor], where: str) -> dict[str, float]:
    """Raise ``FloatingPointError`` naming ``where`` (e.g. ``"step 12"``) and the first non-finite
    term; return every term as a float. All terms come to the host in one read (on a GPU each
    read waits for every kernel queued before it)."""
    return _finite_terms(dict(zip(terms, _host_values(terms.values()))), where)


def check_gradients(named_parameters, step: int) -> None:
    """Raise ``FloatingPointError`` naming the first parameter whose gradient has NaN/Inf values.
    One read of the host for all gradients (the largest magnitude of each, NaN where any is
    NaN); the offending parameter is looked for only when there is one."""
    named = _gradients(named_parameters)
    _finite_gradients(named, _host_values(_largest(named)), step)


def _host_values(tensors) -> list[float]:
    """Zero-dimensional tensors as floats (in their promoted dtype), in one read of the host
    (stacked outside autograd: one operation, where detaching each costs two)."""
    tensors = list(tensors)
    if not tensors:
        return []
    with torch.no_grad():
        return torch.stack(tensors).tolist()


def _gradients(named_parameters) -> list[tuple[str, Tensor]]:
    return [(name, p.grad) for name, p in named_parameters if p.grad is not None]


def _largest(named: list[tuple[str, Tensor]]) -> list[Tensor]:
    """The largest magnitude of each gradient (NaN where any entry is NaN)."""
    if not named:
        return []
    return list(torch._foreach_norm([gradient for _, gradient in named], ord=math.inf))


def _finite_terms(values: dict[str, float], where: str) -> dict[str, float]:
    for name, value in values.items():
        if not math.isfinite(value):
            raise FloatingPointError(
                f"{where}: loss term '{name}' is {value}; lower the learning rates or check the "
                "measurement"
            )
    return values


def _finite_gradients(named: list[tuple[str, Tensor]], largest: list[float], step: int) -> None:
    if all(math.isfinite(value) for value in largest):
        return
    for name, gradient in named:
        if not torch.isfinite(gradient).all():
            raise FloatingPointError(f"step {step}: the gradient of '{name}' has NaN/Inf values")


def synchronize(device: torch.device) -> None:
    """Wait for queued CUDA work (timings); nothing on a CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def descend(
    terms: dict[str, Tensor], named_parameters, optimizer, where: str, step: int, before_step=None
) -> dict[str, float]:
    """Back-propagate ``terms["total"]`` and take one optimizer step, refusing non-finite loss
    terms (as :func:`check_loss_terms`, naming ``where``) and gradients (as
    :func:`check_gradients`) before the step; ``before_step()`` runs between the checks and the
    step (gradient statistics). The terms and the gradients' largest magnitudes come to the host
    together, after the backward pass: one read a step, where a GPU would otherwise wait for its
    queue twice. Returns the terms as floats."""
    terms["total"].backward()
    named = _gradients(named_parameters)
    read = _host_values([*terms.values(), *_largest(named)])
    values = _finite_terms(dict(zip(terms, read)), where)
    _finite_gradients(named, read[len(terms) :], step)
    if before_step is not None:
        before_step()
    optimizer.step()
    return values
