"""What both stages do around an optimisation step: stop on non-finite numbers, log the loss
terms, wait for the GPU before reading a clock; and the checks of their settings, which run in
the constructors so that a nonsense value stops a run before anything is computed."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from fgat.io import check_fields


def require(ok: bool, field: str, value, expected: str) -> None:
    """Raise ``ValueError("<field> must be <expected>, got <value>")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"{field} must be {expected}, got {value!r}")


def require_positive(prefix: str, **values: float) -> None:
    """Every value finite and > 0 (learning rates, scales)."""
    for name, value in values.items():
        require(math.isfinite(value) and value > 0, f"{prefix}.{name}", value, "a positive number")


def require_non_negative(prefix: str, **values: float) -> None:
    """Every value finite and >= 0 (loss weights, iteration counts)."""
    for name, value in values.items():
        require(math.isfinite(value) and value >= 0, f"{prefix}.{name}", value, "a non-negative number")


def dataclass_options(field: str, cls: type, options: dict | None):
    """``cls(**options)`` for a dict-valued setting, naming ``field`` and the valid keys when a key
    is unknown."""
    check_fields(field, cls, options)
    return cls(**(options or {}))


def check_loss_terms(terms: dict[str, Tensor], where: str) -> float:
    """Raise ``FloatingPointError`` naming ``where`` (e.g. ``"step 12"``) and the first non-finite
    term; return the total as a float."""
    for name, value in terms.items():
        if not torch.isfinite(value):
            raise FloatingPointError(f"{where}: loss term '{name}' is {float(value.detach())}; lower the learning "
                                     "rates or check the measurement")
    return float(terms["total"].detach())


def check_gradients(named_parameters, step: int) -> None:
    """Raise ``FloatingPointError`` naming the first parameter whose gradient has NaN/Inf values."""
    for name, parameter in named_parameters:
        if parameter.grad is not None and not torch.isfinite(parameter.grad).all():
            raise FloatingPointError(f"step {step}: the gradient of '{name}' has NaN/Inf values")


def log_loss_terms(module, terms: dict[str, Tensor]) -> None:
    """``loss/<term>`` for every term and ``loss`` (the total) on the progress bar."""
    module.log_dict({f"loss/{name}": value.detach() for name, value in terms.items()}, prog_bar=False)
    module.log("loss", terms["total"].detach(), prog_bar=True)


def synchronize(device: torch.device) -> None:
    """Wait for queued CUDA work (timings); nothing on a CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
