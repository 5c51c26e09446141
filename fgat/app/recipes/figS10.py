"""Fig. S10: Zernike-coefficient trajectories of one Fig. S9 trial during the static stage.

Reads the MLflow metric histories ``zernike/c{j}`` (one value per JPGM event) of the run
``rms1.0-seed0`` of the ``figS9`` experiment (``rms0.1-seed0`` of ``figS9_quick`` with
``--quick``, the same trial at the quick sweep's scale) and draws one panel per Noll index:
the estimate against the static step, the truth (``zernike_gt/c{j}``) dashed, and
Delta_final = c_j(final) - c_j(GT) in waves in the title. Writes ``figS10.png`` and
``trajectories.csv`` (j, step, estimate, truth).

    python reproduce/figS10.py [--quick] [--experiment figS9] [--run rms1.0-seed0]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from fgat.io.files import write_csv
from fgat.recon import names
from fgat.viz.figures import pyplot, save_figure


def trajectories(client, run_id: str) -> dict[int, dict]:
    """``{j: {"steps": [...], "values": [...], "truth": c_gt}}`` for every logged
    ``zernike/c{j}``."""
    run = client.get_run(run_id)
    indices = sorted(
        int(name.rsplit("/c", 1)[1]) for name in run.data.metrics if name.startswith("zernike/c")
    )
    if not indices:
        raise SystemExit(
            f"run {run.info.run_name!r} logged no zernike/c<j> metrics "
            "(was optics.estimate zernike "
            "or joint?)"
        )
    result = {}
    for j in indices:
        history = sorted(
            client.get_metric_history(run_id, names.zernike_name(j)), key=lambda m: m.step
        )
        result[j] = {
            "steps": [m.step for m in history],
            "values": [m.value for m in history],
            "truth": run.data.metrics.get(f"zernike_gt/c{j}", math.nan),
        }
    return result


def plot_trajectories(curves: dict[int, dict], path: Path, *, title: str) -> Path:
    """One panel per index: estimate (solid), truth (dashed), Delta_final in the title."""
    plt = pyplot()
    columns = 6
    rows = math.ceil(len(curves) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(2.6 * columns, 2.1 * rows), squeeze=False)
    colours = plt.get_cmap("tab20")
    for axis, (k, (j, curve)) in zip(axes.ravel(), enumerate(curves.items())):
        axis.plot(curve["steps"], curve["values"], color=colours(k % 20), lw=1.5)
        axis.axhline(curve["truth"], color="black", ls="--", lw=1)
        delta = curve["values"][-1] - curve["truth"]
        axis.set_title(f"j = {j}: $\\Delta_{{final}}$ = {delta:+.3f} $\\lambda$", fontsize=8)
        axis.tick_params(labelsize=7)
    for axis in axes.ravel()[len(curves) :]:
        axis.axis("off")
    for axis in axes[-1]:
        axis.set_xlabel("static step", fontsize=8)
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="the figS9_quick trial rms0.1-seed0")
    parser.add_argument("--experiment", default=None)
    parser.add_argument("--run", default=None, help="run name")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", default=None, help="default: reproduce/results/<experiment>")
    args = parser.parse_args(argv)
    import mlflow  # MLflow loaded when used: keeps start-up fast

    from fgat.app.lightning_cli import tracking_uri  # imported when used: keeps start-up fast

    experiment = args.experiment or ("figS9_quick" if args.quick else "figS9")
    name = args.run or ("rms0.1-seed0" if args.quick else "rms1.0-seed0")
    client = mlflow.MlflowClient(tracking_uri(args.tracking_uri))
    found = client.get_experiment_by_name(experiment)
    runs = (
        []
        if found is None
        else client.search_runs(
            [found.experiment_id],
            filter_string=f"attributes.status = 'FINISHED' and tags.mlflow.runName = '{name}'",
            order_by=["attributes.start_time DESC"],
            max_results=1,
        )
    )
    if not runs:
        raise SystemExit(
            f"no finished run {name!r} in MLflow experiment {experiment!r}: "
            "run reproduce/figS9.sh first"
        )
    curves = trajectories(client, runs[0].info.run_id)
    out = Path(args.out or f"reproduce/results/{experiment}")
    out.mkdir(parents=True, exist_ok=True)
    write_csv(
        out / "trajectories.csv",
        ["j", "step", "estimate", "truth"],
        [
            [j, step, value, curve["truth"]]
            for j, curve in curves.items()
            for step, value in zip(curve["steps"], curve["values"])
        ],
    )
    plot_trajectories(
        curves, out / "figS10.png", title=f"Zernike coefficients of {experiment} / {name}"
    )
    for j, curve in curves.items():
        print(
            f"j = {j:>2}: final {curve['values'][-1]:+.3f}  truth {curve['truth']:+.3f}  "
            f"delta {curve['values'][-1] - curve['truth']:+.3f} waves"
        )
    print(f"figure -> {out / 'figS10.png'}")
