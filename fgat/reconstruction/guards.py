"""What both stages do around an optimisation step: stop on non-finite numbers, step, and wait for
the GPU before reading a clock."""

from __future__ import annotations

import torch
from torch import Tensor


def check_loss_terms(terms: dict[str, Tensor], where: str) -> float:
    """Raise ``FloatingPointError`` naming ``where`` (e.g. ``"step 12"``) and the first non-finite
    term; return the total as a float."""
    for name, value in terms.items():
        if not torch.isfinite(value):
            raise FloatingPointError(
                f"{where}: loss term '{name}' is {float(value.detach())}; lower the learning "
                "rates or check the measurement"
            )
    return float(terms["total"].detach())


def check_gradients(named_parameters, step: int) -> None:
    """Raise ``FloatingPointError`` naming the first parameter whose gradient has NaN/Inf values."""
    for name, parameter in named_parameters:
        if parameter.grad is not None and not torch.isfinite(parameter.grad).all():
            raise FloatingPointError(f"step {step}: the gradient of '{name}' has NaN/Inf values")


def synchronize(device: torch.device) -> None:
    """Wait for queued CUDA work (timings); nothing on a CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def descend(
    terms: dict[str, Tensor], named_parameters, optimizer, where: str, step: int, before_step=None
) -> None:
    """Back-propagate ``terms["total"]`` and take one optimizer step, refusing non-finite loss
    terms (:func:`check_loss_terms`, naming ``where``) and gradients (:func:`check_gradients`);
    ``before_step()`` runs between the backward pass and the step (gradient statistics)."""
    check_loss_terms(terms, where)
    terms["total"].backward()
    check_gradients(named_parameters, step)
    if before_step is not None:
        before_step()
    optimizer.step()
