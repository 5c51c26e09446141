"""The napari widgets against the command line, and how fast Cancel stops them.

On a simulated measurement (``configs/simulate/realistic37.yaml``: 37 lenslets, a 360 x 400
sensor, 25 planes) each widget runs with the inputs of a command-line run, in a napari viewer
(the widgets' runs go through napari's thread workers as a user's do):

- round trips: Calibrate against ``fgat calibrate`` (largest centre difference, px), Deconvolve
  against ``fgat deconvolve`` (SHB, ``--iterations``) and Fit against ``fgat fit`` (the static
  stage of ``configs/measured.yaml`` for ``--steps`` steps), each volume's largest difference
  over its maximum;
- cancel latency: seconds from Cancel to the end of the run (the result handed back to the
  viewer) for a 2,000-iteration deconvolution and a 20,000-step fit cancelled ``--wait`` s after
  they start, ``--repeats`` times each, beside one iteration's and one step's time (the
  difference of two runs' wall times over their difference in iterations or steps).

Needs the napari extra and a screen (``xvfb-run`` on a headless machine)::

    xvfb-run -a python benchmarks/napari_widgets.py [--repeats 3] [--wait 4]
        [--out benchmarks/results/napari_widgets.json]
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from fgat.app.cli import main as fgat
from fgat.app.recipes.benchmark import parser, write_json
from fgat.instrument.centres import read_centers
from fgat.io.images import read_tiff

ROOT = Path(__file__).resolve().parents[1]
DEPTHS = "-4:4:25"
CONFIGS = [ROOT / "configs/base/common.yaml", ROOT / "configs/measured.yaml"]
FIT_OPTIONS = (
    "--data.init_args.truth=null --trainer.val_check_interval={steps} --trainer.max_steps={steps} "
    "--model.init_args.n_gaussians=200 --trainer.callbacks=[] --trainer.enable_progress_bar=false "
    "--trainer.default_root_dir={root} --mlflow.tracking_uri=sqlite:///{root}/mlflow.db"
)


def measurement(folder: Path) -> dict[str, Path]:
    """The simulated measurement and its command-line calibration."""
    sim, calib = folder / "sim", folder / "calib"
    config = ROOT / "configs/simulate/realistic37.yaml"
    assert fgat(["simulate", "--config", str(config), "--out", str(sim)]) == 0
    frames = ["--image", str(sim / "flat.ome.tif"), "--flat", str(sim / "flat.ome.tif")]
    frames += ["--dark", str(sim / "dark.ome.tif"), "--system", "small37"]
    assert fgat(["calibrate", *frames, "--out", str(calib)]) == 0
    return {"sim": sim, "calib": calib, "sensor": sim / "sensor.ome.tif"}


def finish(app, widget, timeout_s: float = 1800.0) -> float:
    """Let the viewer's event loop run until ``widget``'s run has ended; the seconds it took."""
    start = time.perf_counter()
    while widget.running and time.perf_counter() - start < timeout_s:
        app.processEvents()
        time.sleep(0.005)
    if widget.running:
        raise SystemExit(f"{type(widget).__name__} did not end within {timeout_s:.0f} s")
    return time.perf_counter() - start


def timed_run(app, widget) -> float:
    """Wall time (s) of one run of ``widget`` from its Run button to its result."""
    start = time.perf_counter()
    widget.start()
    finish(app, widget)
    if widget.outcome != ("done", None):
        raise SystemExit(f"{type(widget).__name__}: {widget.outcome}")
    return time.perf_counter() - start


def cancelled(app, widget, wait_s: float) -> dict:
    """Start ``widget``, press Cancel after ``wait_s`` s: its latency (s) and the line it ended
    with."""
    widget.start()
    start = time.perf_counter()
    while time.perf_counter() - start < wait_s:
        app.processEvents()
        time.sleep(0.005)
    widget.cancel()
    finish(app, widget)
    kind, line = widget.outcome
    if kind != "cancelled":
        raise SystemExit(f"{type(widget).__name__} was not cancelled: {widget.outcome}")
    return {"latency_s": round(widget.cancel_latency_s, 3), "line": line}


def deconvolve_words(data: dict, iterations: int, out: Path) -> list[str]:
    words = ["deconvolve", "--measurement", str(data["sensor"]), "--system", "small37"]
    words += [f"--depths-um={DEPTHS}", "--calibration", str(data["calib"])]
    return [*words, "--iterations", str(iterations), "--out", str(out), "--overwrite"]


def fit_words(data: dict, steps: int, root: Path) -> list[str]:
    words = ["fit", *(word for path in CONFIGS for word in ("--config", str(path)))]
    words += [f"--data.init_args.measurement={data['sensor']}"]
    words += [f"--data.init_args.calibration={data['calib']}", "--data.init_args.system=small37"]
    words += [f"--data.init_args.depths_um={DEPTHS}", "--model.init_args.optics.estimate=none"]
    return words + FIT_OPTIONS.format(steps=steps, root=root).split()


def relative_difference(found: np.ndarray, expected: np.ndarray) -> float:
    return float(np.abs(found - expected).max() / max(float(np.abs(expected).max()), 1e-30))


def main() -> None:
    options = parser(
        __doc__, "benchmarks/results/napari_widgets.json", "10 iterations and steps, 1 repeat"
    )
    options.add_argument("--iterations", type=int, default=30, help="SHB iterations compared")
    options.add_argument("--steps", type=int, default=30, help="fit steps compared")
    options.add_argument("--wait", type=float, default=4.0, help="seconds before Cancel")
    options.set_defaults(repeats=3)
    args = options.parse_args()
    if args.quick:
        args.iterations, args.steps, args.repeats = 10, 10, 1
    import napari  # the extra: loaded when the benchmark runs
    from qtpy.QtWidgets import QApplication

    from fgat.napari.widgets import CalibrateWidget, DeconvolveWidget, FitWidget

    with tempfile.TemporaryDirectory(prefix="fgat-napari-bench-") as work:
        work = Path(work)
        data = measurement(work)
        viewer = napari.Viewer(show=False)
        app = QApplication.instance()
        sensor = viewer.open(data["sensor"], plugin="napari")[0]
        flat = viewer.open(data["sim"] / "flat.ome.tif", plugin="napari")[0]
        dark = viewer.open(data["sim"] / "dark.ome.tif", plugin="napari")[0]

        calibrate = CalibrateWidget(viewer)
        viewer.window.add_dock_widget(calibrate)
        calibrate.reset_choices()
        calibrate.image.value, calibrate.flat.value, calibrate.dark.value = flat, flat, dark
        calibrate.out.value = work / "calib_widget"
        calibrate_s = timed_run(app, calibrate)
        centres = read_centers(work / "calib_widget" / "centers.csv")
        centre_difference = float(
            np.abs(centres - read_centers(data["calib"] / "centers.csv")).max()
        )

        deconvolve = DeconvolveWidget(viewer)
        viewer.window.add_dock_widget(deconvolve)
        deconvolve.reset_choices()
        deconvolve.measurement.value, deconvolve.calibration.value = sensor, data["calib"]
        deconvolve.overwrite.value = True
        runs = {}
        for iterations in (args.iterations, 2 * args.iterations):
            deconvolve.iterations.value = iterations
            deconvolve.out.value = work / f"shb_widget_{iterations}.ome.tif"
            runs[iterations] = timed_run(app, deconvolve)
        assert fgat(deconvolve_words(data, args.iterations, work / "shb_cli.ome.tif")) == 0
        shb_difference = relative_difference(
            read_tiff(work / f"shb_widget_{args.iterations}.ome.tif"),
            read_tiff(work / "shb_cli.ome.tif"),
        )
        iteration_s = (runs[2 * args.iterations] - runs[args.iterations]) / args.iterations
        deconvolve.iterations.value, deconvolve.out.value = 2000, work / "long.ome.tif"
        deconvolve_cancels = [cancelled(app, deconvolve, args.wait) for _ in range(args.repeats)]

        fit = FitWidget(viewer)
        viewer.window.add_dock_widget(fit)
        fit.reset_choices()
        fit.measurement.value, fit.configs.value = sensor, CONFIGS
        fit.calibration.value, fit.depths.value = data["calib"], DEPTHS
        fit_runs = {}
        runs_of = (("warm-up", args.steps), ("short", args.steps), ("long", 2 * args.steps))
        for label, steps in runs_of:  # the first loads what a fit loads once
            fit.overrides.value = FIT_OPTIONS.format(steps=steps, root=work / f"fit_{label}")
            fit_runs[label] = timed_run(app, fit)
        (widget_volume,) = (work / "fit_short" / "results").iterdir()
        assert fgat(fit_words(data, args.steps, work / "fit_cli")) == 0
        (cli_volume,) = (work / "fit_cli" / "results").iterdir()
        fit_difference = relative_difference(
            read_tiff(widget_volume / "volume.ome.tif"), read_tiff(cli_volume / "volume.ome.tif")
        )
        step_s = (fit_runs["long"] - fit_runs["short"]) / args.steps
        fit_cancels = []
        for repeat in range(args.repeats):
            fit.overrides.value = FIT_OPTIONS.format(steps=20000, root=work / f"long_{repeat}")
            fit_cancels.append(cancelled(app, fit, args.wait))
        viewer.close()
    result = {
        "scene": "configs/simulate/realistic37.yaml (37 views, 360 x 400 sensor, 25 planes)",
        "round_trips": {
            "calibrate": {
                "seconds": round(calibrate_s, 2),
                "max_centre_difference_px": centre_difference,
            },
            "deconvolve": {
                "iterations": args.iterations,
                "seconds": round(runs[args.iterations], 2),
                "max_relative_difference": shb_difference,
            },
            "fit": {
                "steps": args.steps,
                "seconds": round(fit_runs["short"], 2),
                "max_relative_difference": fit_difference,
            },
        },
        "cancel": {
            "deconvolve": {
                "iteration_s": round(iteration_s, 4),
                "latency_s": [row["latency_s"] for row in deconvolve_cancels],
                "median_latency_s": statistics.median(r["latency_s"] for r in deconvolve_cancels),
                "lines": [row["line"] for row in deconvolve_cancels],
            },
            "fit": {
                "step_s": round(step_s, 4),
                "latency_s": [row["latency_s"] for row in fit_cancels],
                "median_latency_s": statistics.median(r["latency_s"] for r in fit_cancels),
                "lines": [row["line"] for row in fit_cancels],
            },
        },
    }
    write_json(args.out, result)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
