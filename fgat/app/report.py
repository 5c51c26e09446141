"""What a reconstruction reports about its fit to the data: the relative data residual
(:func:`fgat.recon.metrics.relative_residual`) and whether it converged, as lines and as a JSON file
beside the results (``deconvolve``: ``<volume>.residual.json``; ``fit``: ``residual.json`` in
the results folder)."""

from __future__ import annotations

from pathlib import Path

from fgat.io.files import write_json
from fgat.recon.metrics import residual_summary

RESIDUAL_FILE = "residual.json"


def residual_report(
    residual: dict[str, object], *, converged: bool, stopped: str, **fields
) -> dict[str, object]:
    """The report of a run: ``relative_residual`` and ``relative_residual_views`` (from
    :func:`~fgat.recon.metrics.relative_residual`), ``converged`` (it met a stopping rule, not only
    its step or iteration budget), ``stopped`` (the sentence that says how it ended) and the
    caller's ``fields`` (iterations, steps, final loss, ...)."""
    return {
        "relative_residual": residual["overall"],
        "relative_residual_views": list(residual["views"]),
        "converged": bool(converged),
        "stopped": stopped,
        **fields,
    }


def report_lines(report: dict[str, object]) -> str:
    """``<residual summary>; <how it stopped>``."""
    residual = {"overall": report["relative_residual"], "views": report["relative_residual_views"]}
    return f"{residual_summary(residual)}; {report['stopped']}"


def write_report(path: str | Path, report: dict[str, object]) -> Path:
    """Write ``report`` as JSON (NaN as ``null``) to ``path``, atomically; the path."""
    return write_json(path, report)


def report_path(volume: str | Path) -> Path:
    """``<name>.residual.json`` beside a volume file ``<name>.ome.tif`` (or ``.tif``, ...)."""
    volume = Path(volume)
    name = volume.name
    for suffix in (".ome.tiff", ".ome.tif", ".tiff", ".tif"):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    return volume.with_name(f"{name}.{RESIDUAL_FILE}")


def deconvolution_ending(
    done: int, iterations: int, tol: float | None, holdout: float | None
) -> tuple[bool, str]:
    """Whether a deconvolution that ran ``done`` of its ``iterations`` converged, and the
    sentence that says how it stopped: by ``tol`` (the Poisson cost's relative change), by the
    held-out pixels' rule (``holdout``), or by its iteration budget. A rule met at the very last
    iteration reads as the budget."""
    if done < iterations and holdout is not None:
        return True, (
            f"stopped after {done} of {iterations} iterations by the held-out pixels' rule "
            "(their Poisson cost stopped falling; the volume is the iterate of its minimum)"
        )
    if done < iterations:
        return True, (
            f"converged: the Poisson cost changed by less than tol = {tol:g} after {done} of "
            f"{iterations} iterations"
        )
    rules = [name for name, value in (("--tol", tol), ("--holdout", holdout)) if value is not None]
    if not rules:
        return False, (
            f"ran its {iterations} iterations; convergence not tested (no --tol or --holdout)"
        )
    return False, (
        f"stopped by its iteration budget (--iterations {iterations}) rather than converged "
        f"({' and '.join(rules)} not met)"
    )
