"""Check the cost estimate printed before a run against the run: time and peak memory.

Each case runs in its own process (``python -m fgat`` as a user runs it, from Python so that
the estimate can be read back): a deconvolution (``fgat deconvolve``) and short fits
(``fgat fit``) with the optics fixed and estimated. The estimate
(:func:`fgat.recon.costs.deconvolution_cost`, :func:`fgat.recon.costs.static_fit_cost`) is compared
with the wall time from the start of the command (deconvolution) or of the trainer (fit) to
its end, and with the process's peak resident memory (``ru_maxrss``, which sees torch's
allocations). The goal is a ratio estimate / measured within [0.5, 2]. The estimate is that of
the machine to itself (its calibration keeps the fastest of repeated times): on a machine
shared with other work (see the load averages recorded with each case) runs take longer.

    python benchmarks/cost_estimate.py [--quick] [--out benchmarks/results/cost_estimate.json]
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from fgat.app.recipes.benchmark import parser, provenance, write_json

ROOT = Path(__file__).resolve().parent.parent
MARK = "COST_ESTIMATE_RESULT "

SIMULATION = {
    "system": "small",
    "depths_um": "-12:12:9",
    "view_size": 48,
    "phantom": {
        "kind": "beads",
        "n_beads": 20,
        "sigma": 1.0,
        "min_spacing": 6,
        "margin": [1, 6, 6],
    },
    "photons": 800.0,
    "background": 50.0,
    "read_noise": 1.5,
    "seed": 3,
}


def child(case: dict) -> None:
    """Run one case in this process and print its estimate and measurements as one JSON line."""
    import fgat.recon.costs as costs
    from fgat._core.heap import retain_freed_memory

    retain_freed_memory()  # as python -m fgat
    captured = {}

    def capture(function):
        def wrapped(*args, **kwargs):
            estimate = function(*args, **kwargs)
            captured.update(estimate=estimate, at=time.perf_counter())
            return estimate

        return wrapped

    for name in ("deconvolution_cost", "static_fit_cost", "dynamic_fit_cost"):
        setattr(costs, name, capture(getattr(costs, name)))
    start = time.perf_counter()
    if case["kind"] == "deconvolve":
        from fgat.app.cli import main

        assert main(case["args"]) == 0
    else:
        from fgat.app.lightning_cli import run

        run(case["args"])
    end = time.perf_counter()
    estimate = captured["estimate"]
    setup = estimate.seconds.get("setup", 0.0)
    if case["kind"] == "deconvolve":
        measured = end - start - (captured["at"] - start - setup)  # the calibration left out
    else:
        measured = setup + end - captured["at"]
    usage = resource.getrusage(resource.RUSAGE_SELF)
    peak = usage.ru_maxrss * 1024
    print(
        MARK
        + json.dumps(
            {
                "estimate_s": estimate.total_seconds,
                "estimate_parts_s": estimate.seconds,
                "estimate_peak_bytes": estimate.peak_bytes,
                "estimate_memory_parts_bytes": estimate.memory,
                "calibration_s": captured["at"] - start - setup,
                "measured_s": measured,
                "measured_peak_bytes": peak,
                "measured_cpu_s": usage.ru_utime + usage.ru_stime,
                "load_average_after": os.getloadavg()[0],
                "printed": estimate.lines(),
            }
        ),
        flush=True,
    )


def run_case(name: str, case: dict, folder: Path) -> dict:
    """The case in a fresh process; its row with the ratios."""
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": ""}
    load = os.getloadavg()[0]
    started = time.perf_counter()
    result = subprocess.run(
        [sys.executable, __file__, "--child", json.dumps(case)],
        cwd=folder,
        capture_output=True,
        text=True,
        env=environment,
    )
    if result.returncode != 0:
        raise RuntimeError(f"case {name} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    line = next(line for line in result.stdout.splitlines() if line.startswith(MARK))
    row = {"case": name, "command": case["args"], **json.loads(line[len(MARK) :])}
    row["process_s"] = time.perf_counter() - started
    row["load_average_before"] = load
    row["time_ratio"] = row["estimate_s"] / row["measured_s"]
    row["memory_ratio"] = row["estimate_peak_bytes"] / row["measured_peak_bytes"]
    row["within_2x"] = all(0.5 <= row[k] <= 2.0 for k in ("time_ratio", "memory_ratio"))
    print(
        f"{name}: estimate {row['estimate_s']:.1f} s, measured {row['measured_s']:.1f} s "
        f"(x{row['time_ratio']:.2f}); peak {row['estimate_peak_bytes'] / 1e6:.0f} MB vs "
        f"{row['measured_peak_bytes'] / 1e6:.0f} MB (x{row['memory_ratio']:.2f}); calibration "
        f"{row['calibration_s']:.1f} s",
        flush=True,
    )
    return row


def fit_args(folder: Path, steps: int, optics: str, extra: list[str]) -> list[str]:
    """``fgat fit`` on a bead phantom of the small system, no MLflow logger, no progress bar."""
    configs = ["configs/base/common.yaml"]
    if optics != "none":
        configs += ["configs/base/optics_quick.yaml", "configs/figS6.yaml"]
    args = ["fit"]
    for config in configs:
        args += ["--config", str(ROOT / config)]
    return args + [
        f"--trainer.max_steps={steps}",
        f"--trainer.default_root_dir={folder / 'run'}",
        "--trainer.logger=false",
        "--trainer.enable_progress_bar=false",
        f"--trainer.val_check_interval={steps}",
        f"--model.init_args.optics.estimate={optics}",
        *extra,
    ]


def cases(folder: Path, quick: bool) -> dict[str, dict]:
    """The deconvolutions of a simulated sensor image and the short fits."""
    sim = folder / "sim"
    deconvolve = [
        "deconvolve",
        "--measurement",
        str(sim / "sensor.ome.tif"),
        "--centers",
        str(sim / "centers.csv"),
        "--background",
        "50",
        "--device",
        "cpu",
    ]
    planes = 15 if quick else 61
    steps = 120 if quick else 400
    return {
        "deconvolve_9_planes": {
            "kind": "deconvolve",
            "args": deconvolve
            + ["--psf", str(sim / "psf.ome.tif"), "--iterations", "60"]
            + ["--out", str(folder / "a.ome.tif")],
        },
        f"deconvolve_{planes}_planes": {
            "kind": "deconvolve",
            "args": deconvolve
            + ["--system", "small", f"--depths-um=-12:12:{planes}", "--iterations", "40"]
            + ["--view-size", "64", "--out", str(folder / "b.ome.tif")],
        },
        "fit_optics_fixed": {
            "kind": "fit",
            "args": fit_args(
                folder / "fixed", steps, "none", ["--model.init_args.n_gaussians=1500"]
            ),
        },
        "fit_optics_estimated": {
            "kind": "fit",
            "args": fit_args(
                folder / "estimated",
                80 if quick else steps,
                "zernike",
                ["--model.init_args.optics.start=40", "--model.init_args.optics.every=40"],
            ),
        },
    }


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        child(json.loads(sys.argv[2]))
        return
    args = parser(
        __doc__, "benchmarks/results/cost_estimate.json", "small sizes (< 3 min)"
    ).parse_args()
    from fgat.app.cli import main as fgat_main

    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        config = folder / "sim.yaml"
        config.write_text(yaml.safe_dump(SIMULATION))
        assert fgat_main(["simulate", "--config", str(config), "--out", str(folder / "sim")]) == 0
        rows = [run_case(name, case, folder) for name, case in cases(folder, args.quick).items()]
    write_json(
        args.out,
        {
            **provenance("python benchmarks/cost_estimate.py" + (" --quick" if args.quick else "")),
            "cases": rows,
            "all_within_2x": all(row["within_2x"] for row in rows),
        },
    )


if __name__ == "__main__":
    main()
