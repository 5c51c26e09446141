"""Helpers shared by the benchmark scripts (``benchmarks/*.py``): timing, command line, JSON
results with their provenance, the static stage of a recipe. Importing it gives the process the
host-memory policy of ``python -m fgat`` (:func:`fgat._core.heap.retain_freed_memory`), so that
benchmarks time what the CLI runs."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from fgat._core.heap import retain_freed_memory
from fgat.app.modules.shell import flat_settings, settings
from fgat.gaussians.densify import Densification
from fgat.io.files import atomic_path
from fgat.recon import StaticReconstruction, StaticSettings
from fgat.recon.estimation import OpticsEstimation

retain_freed_memory()


def synchronize(device: torch.device | None) -> None:
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(
    function, repeats: int, device: torch.device | None = None, statistic=statistics.median
) -> float:
    """Median (or ``statistic``) wall time (s) of ``function()`` over ``repeats`` runs after one
    warm-up."""
    function()
    synchronize(device)
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        synchronize(device)
        samples.append(time.perf_counter() - start)
    return statistic(samples)


def profile_table(function, calls: int, device: torch.device) -> str:
    """``torch.profiler``'s table of ``calls`` runs of ``function()`` after one warm-up:
    operations sorted by their own GPU time (CPU time on a CPU), with each one's host time and
    calls, and the profiler's totals."""
    function()
    synchronize(device)
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as profile:
        for _ in range(calls):
            function()
        synchronize(device)
    sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    return profile.key_averages().table(sort_by=sort, row_limit=25, max_name_column_width=60)


def parser(
    doc: str, default_out: str, quick_help: str, tiny_help: str | None = None
) -> argparse.ArgumentParser:
    """The benchmarks' common options: ``--quick``, ``--repeats``, ``--out``, and ``--tiny``
    where the benchmark has a tiny case (``tiny_help``: seconds on a CPU, a check that the
    script runs rather than a timing, as ``benchmarks/gpu_checks.sh --dry-run`` uses it)."""
    result = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    result.add_argument("--quick", action="store_true", help=quick_help)
    if tiny_help is not None:
        result.add_argument("--tiny", action="store_true", help=tiny_help)
    result.add_argument("--repeats", type=int, default=5, help="repeats of each timing")
    result.add_argument("--out", default=default_out, help="result JSON")
    return result


def commit() -> str:
    """The git commit of the checkout that holds this fgat package (empty outside one)."""
    result = subprocess.run(
        ["git", "rev-parse", "HEAD"],
        cwd=Path(__file__).resolve().parent,
        capture_output=True,
        text=True,
        check=False,
    )
    return result.stdout.strip()


def provenance(command: str, **machine) -> dict:
    """The header of a committed result file: date (UTC), machine (platform, processor, CPUs,
    Python, and ``machine``'s extra fields), commit and the command that wrote it."""
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            **machine,
        },
        "commit": commit(),
        "command": command,
    }


def write_text(path: str | Path, text: str) -> None:
    """Write results atomically and say where."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        temporary.write_text(text)
    print(f"\nresults -> {path}")


def write_json(path: str | Path, payload: dict) -> None:
    """:func:`write_text` of ``payload`` as indented JSON, headed by its :func:`provenance`
    (the command line that ran, unless ``payload`` carries its own)."""
    if "commit" not in payload:
        payload = {**provenance(shlex.join(["python", *sys.argv])), **payload}
    write_text(path, json.dumps(payload, indent=2))


def static_engine(
    scene, model: dict, optics: dict, steps: int, device: torch.device | str = "cpu"
) -> StaticReconstruction:
    """The static stage on ``scene`` as a recipe's resolved ``model.init_args`` (``model``) sets
    it, with the :class:`~fgat.recon.estimation.OpticsEstimation` fields ``optics``, for
    ``steps`` steps on ``device``."""
    return StaticReconstruction(
        scene,
        flat_settings(StaticSettings, model),
        settings(Densification, "model.densification", model["densification"]),
        settings(OpticsEstimation, "model.optics", optics),
        total_steps=steps,
        device=device,
    )
