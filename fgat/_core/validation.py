"""Validation helpers: arrays, numbers and required fields checked with one-line errors
naming the field and what was expected; parsing of list-valued and override options.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np


def validate_array(
    array: np.ndarray,
    *,
    source: str,
    ndim: int | Sequence[int] | None = None,
    axes: str | None = None,
    nonnegative: bool = False,
) -> np.ndarray:
    """Check an array read from ``source``: dimensionality, finiteness and sign.

    Parameters
    ----------
    array : numpy.ndarray
        The data.
    source : str
        What to name in errors (a file, or a file and a field).
    ndim : int or sequence of int, optional
        Allowed numbers of dimensions.
    axes : str, optional
        Axis names for the error message, e.g. ``"(Z, Y, X)"``.
    nonnegative : bool
        Reject negative values (photon counts, intensities).
    """
    array = np.asarray(array)
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if array.ndim not in allowed:
            expected = " or ".join(f"{n}D" for n in allowed) + (f" {axes}" if axes else "")
            raise ValueError(
                f"{source}: expected {expected}, got {array.ndim}D data of shape {array.shape}"
            )
    if array.size == 0:
        raise ValueError(f"{source}: the data is empty (shape {array.shape})")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise ValueError(f"{source}: expected real numbers, got dtype {array.dtype}")
    if np.issubdtype(array.dtype, np.floating):
        bad = ~np.isfinite(array)
        if bad.any():
            raise ValueError(
                f"{source}: {int(bad.sum())} NaN/Inf value(s), first at index "
                f"{tuple(int(i) for i in np.argwhere(bad)[0])}"
            )
    if nonnegative and array.min() < 0:
        raise ValueError(
            f"{source}: expected non-negative values (intensities), minimum is {array.min()}"
        )
    return array


def check_number(
    name: str,
    value,
    *,
    minimum: float | None = None,
    above: float | None = None,
    maximum: float | None = None,
    integer: bool = False,
) -> float | int:
    """``value`` as a finite number within bounds, or one ``ValueError`` naming ``name``.

    Parameters
    ----------
    name : str
        What to call the value in the error (an option or a field).
    value
        A number, or text that reads as one.
    minimum, maximum : float, optional
        Inclusive bounds.
    above : float, optional
        Exclusive lower bound.
    integer : bool
        Require a whole number (``1e8`` is accepted as ``100000000``) and return an ``int``.
    """
    words = ["an integer" if integer else "a finite number"]
    if above is not None:
        words.append(f"> {above:g}")
    if minimum is not None and maximum is not None:
        words.append(f"in [{minimum:g}, {maximum:g}]")
    elif minimum is not None:
        words.append(f">= {minimum:g}")
    elif maximum is not None:
        words.append(f"<= {maximum:g}")
    try:
        number = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        number = math.nan
    valid = (
        math.isfinite(number)
        and (not integer or number.is_integer())
        and (above is None or number > above)
        and (minimum is None or number >= minimum)
        and (maximum is None or number <= maximum)
    )
    if not valid:
        raise ValueError(f"{name} must be {' '.join(words)}, got {value!r}")
    return int(number) if integer else number


def parse_values(spec, what: str = "value", *, distinct: bool = False) -> list[float]:
    """Finite numbers from a list, ``"-30,0,30"``, or ``"start:stop:count"`` (inclusive, evenly
    spaced); ``distinct`` also refuses a value given twice. Errors name ``what`` and ``spec``."""
    ranged = isinstance(spec, str) and len(spec.split(":")) == 3
    try:
        if ranged:
            start, stop, count = spec.split(":")
            start, stop, count = float(start), float(stop), int(count)
        else:
            values = [
                float(v)
                for v in (spec.split(",") if isinstance(spec, str) else spec)
                if not isinstance(v, str) or v.strip()
            ]
    except (TypeError, ValueError):
        raise ValueError(
            f"{what}s {spec!r}: expected numbers (a,b,c) or start:stop:count"
        ) from None
    if ranged:
        if count < 1:
            raise ValueError(f"{what} count must be positive in {spec!r}")
        values = np.linspace(start, stop, count).tolist() if count > 1 else [start]
    if not all(np.isfinite(values)):
        raise ValueError(f"{what}s {spec!r}: every {what} must be a finite number")
    if distinct and len(set(values)) != len(values):
        repeated = sorted({v for v in values if values.count(v) > 1})
        raise ValueError(f"{what}s {spec!r}: {what} {repeated[0]:g} is given more than once")
    return values


def parse_scalar(text: str):
    """A command-line scalar: ``"50"`` -> 50, ``"1e-3"`` -> 0.001, ``"false"`` -> False,
    ``"null"`` -> None; anything else stays text."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    if lowered in ("null", "none", "~"):
        return None
    for convert in (int, float):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


def parse_overrides(value):
    """Apply :func:`parse_scalar` to every string inside nested dicts and lists (config dicts
    whose entries were overridden on the command line arrive as text)."""
    if isinstance(value, str):
        return parse_scalar(value)
    if isinstance(value, dict):
        return {
            parse_overrides(key)
            if isinstance(key, str) and key.isdigit()
            else key: parse_overrides(item)
            for key, item in value.items()
        }
    if isinstance(value, (list, tuple)):
        return type(value)(parse_overrides(item) for item in value)
    return value


def coerce_fields(instance) -> None:
    """Give a dataclass's fields the type of their defaults when set from text.

    Command-line overrides of a config dict arrive as strings (``"50"``, ``"false"``); they are
    read with :func:`parse_scalar` and cast to the default's type (int, float, bool). A value that
    does not convert (text, a boolean for a number or a number for a boolean, a fraction for an
    integer, NaN or infinity) raises ``ValueError`` naming the field. ``None`` is left alone.
    """
    for field in dataclasses.fields(instance):
        default = field.default
        value = getattr(instance, field.name)
        if (
            not field.init
            or default is dataclasses.MISSING
            or not isinstance(default, (bool, int, float))
        ):
            continue
        if isinstance(value, str):
            value = parse_scalar(value)
        if value is None:
            setattr(instance, field.name, None)
            continue
        expected = {bool: "true or false", int: "an integer", float: "a finite number"}[
            type(default)
        ]
        if isinstance(default, bool) != isinstance(value, bool):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        if isinstance(default, int) and isinstance(value, float) and not value.is_integer():
            raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        try:
            converted = type(default)(value)
        except (TypeError, ValueError):
            raise ValueError(f"{field.name} must be {expected}, got {value!r}") from None
        setattr(instance, field.name, converted)


def require(ok: bool, field: str, value, expected: str) -> None:
    """Raise ``ValueError("<field> must be <expected>, got <value>")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"{field} must be {expected}, got {value!r}")


def require_positive(prefix: str, **values: float) -> None:
    """Every value finite and > 0 (learning rates, scales)."""
    for name, value in values.items():
        require(
            math.isfinite(value) and value > 0,
            f"{prefix}.{name}".lstrip("."),
            value,
            "a positive number",
        )


def require_non_negative(prefix: str, **values: float) -> None:
    """Every value finite and >= 0 (loss weights, iteration counts)."""
    for name, value in values.items():
        require(
            math.isfinite(value) and value >= 0,
            f"{prefix}.{name}".lstrip("."),
            value,
            "a non-negative number",
        )
