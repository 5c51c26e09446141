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
    values = dict(
        zip(terms, torch.cat([value.detach().reshape(1) for value in terms.values()]).tolist())
    )
    for name, value in values.items():
        if not math.isfinite(value):
            raise FloatingPointError(
                f"{where}: loss term '{name}' is {value}; lower the learning rates or check the "
                "measurement"
            )
    return values


def check_gradients(named_parameters, step: int) -> None:
    """Raise ``FloatingPointError`` naming the first parameter whose gradient has NaN/Inf values.
    One read of the host for all gradients (the largest magnitude of each, NaN where any is
    NaN); the offending parameter is looked for only when there is one."""
    named = [(name, p.grad) for name, p in named_parameters if p.grad is not None]
    if not named:
        return
    largest = torch._foreach_norm([gradient for _, gradient in named], ord=math.inf)
    if bool(torch.isfinite(torch.stack(largest)).all()):
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
    terms (:func:`check_loss_terms`, naming ``where``) and gradients (:func:`check_gradients`);
    ``before_step()`` runs between the backward pass and the step (gradient statistics).
    Returns the terms as floats (read from the device once, by the check)."""
    values = check_loss_terms(terms, where)
    terms["total"].backward()
    check_gradients(named_parameters, step)
    if before_step is not None:
        before_step()
    optimizer.step()
    return values
