"""Fig. S9 summary: aberration estimation and reconstruction fidelity against the aberration RMS.

Reads the finished runs of a ``reproduce/figS9.sh`` sweep from MLflow (``mlflow.search_runs``;
each run's ``simulation/aberrations/rms`` and ``simulation/aberrations/seed`` parameters say which
trial it is; a repeated trial counts once, its latest run) and writes under ``--out``:

* ``runs.csv``: one row per trial (rms, seed, sigma, volume PSNR and SSIM, x-y MIP SSIM of
  4DGAT, and those of the SHB baseline with the ideal PSF);
* ``summary.csv``: per RMS level the number of trials and the mean and s.d. of each metric;
* ``figS9_metrics.png``: panels a-d, mean +/- s.d. against the RMS (waves), SHB dashed;
* ``figS9_wavefronts.png``: panel e, estimated and true wavefronts of every trial (rows: RMS,
  columns: seeds) on the colour scale of the largest RMS row.

    python reproduce/figS9_summary.py --experiment figS9_quick [--tracking-uri sqlite:///mlflow.db]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fgat.io.files import write_csv
from fgat.optics.zernike import wavefront_map
from fgat.recon import names
from fgat.viz.figures import pyplot, save_figure

RMS, SEED = "params.simulation/aberrations/rms", "params.simulation/aberrations/seed"
METRICS = {
    "sigma": names.ZERNIKE_RESIDUAL,
    "psnr": names.PSNR,
    "ssim": names.SSIM,
    "ssim_xy": names.SSIM_XY,
}
BASELINE = ("psnr_shb", "ssim_shb", "ssim_xy_shb")
LABELS = {
    "sigma": "a  normalized residual sigma",
    "psnr": "b  volume PSNR (dB)",
    "ssim": "c  volume SSIM",
    "ssim_xy": "d  x-y MIP SSIM",
}


def sweep_runs(experiment: str, tracking_uri: str) -> list[dict]:
    """One record per (rms, seed) trial: its metrics and its estimated and true Zernike
    coefficients."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    frame = mlflow.search_runs(
        experiment_names=[experiment],
        filter_string="attributes.status = 'FINISHED'",
        order_by=["attributes.start_time ASC"],
    )
    if frame.empty:
        raise SystemExit(f"no finished runs in MLflow experiment {experiment!r} at {tracking_uri}")
    for column in (RMS, SEED):
        if column not in frame:
            raise SystemExit(
                f"experiment {experiment!r}: runs lack the parameter {column.split('.', 1)[1]!r} "
                "(run them with reproduce/figS9.sh)"
            )
    trials = {}
    for _, row in frame.iterrows():
        if row[RMS] is None or row[SEED] is None:
            continue
        trials[(float(row[RMS]), int(row[SEED]))] = row  # the latest run of a trial wins
    records = []
    for (rms, seed), row in sorted(trials.items()):
        indices = sorted(
            int(c.rsplit("/c", 1)[1])
            for c in row.index
            if c.startswith("metrics.zernike/c") and np.isfinite(row[c])
        )
        baseline = {
            f"{k}_shb": float(row.get(f"metrics.{m}{names.SHB}", np.nan))
            for k, m in METRICS.items()
            if k != "sigma"
        }
        records.append(
            {
                "rms": rms,
                "seed": seed,
                **{k: float(row[f"metrics.{m}"]) for k, m in METRICS.items()},
                **baseline,
                "indices": indices,
                "estimated": [float(row[f"metrics.zernike/c{j}"]) for j in indices],
                "truth": [float(row.get(f"metrics.zernike_gt/c{j}", np.nan)) for j in indices],
            }
        )
    return records


def summarize(records: list[dict]) -> list[dict]:
    """Mean and sample standard deviation (0 for a single trial) of every metric per RMS level."""
    rows = []
    for rms in sorted({r["rms"] for r in records}):
        group = [r for r in records if r["rms"] == rms]
        row = {"rms": rms, "trials": len(group)}
        for key in [*METRICS, *BASELINE]:
            values = np.array([r[key] for r in group], dtype=np.float64)
            row[f"{key}_mean"] = float(values.mean())
            row[f"{key}_sd"] = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        rows.append(row)
    return rows


def plot_metrics(summary: list[dict], path: Path) -> Path:
    """Panels a-d: mean +/- s.d. (shaded) against the RMS."""
    plt = pyplot()
    rms = np.array([row["rms"] for row in summary])
    figure, axes = plt.subplots(1, len(METRICS), figsize=(3.4 * len(METRICS), 3.0))
    for axis, key in zip(axes, METRICS):
        mean = np.array([row[f"{key}_mean"] for row in summary])
        sd = np.array([row[f"{key}_sd"] for row in summary])
        axis.plot(rms, mean, "o-", color="tab:orange", label="4DGAT")
        axis.fill_between(rms, mean - sd, mean + sd, color="tab:orange", alpha=0.25)
        if f"{key}_shb_mean" in summary[0]:
            axis.plot(
                rms,
                [row[f"{key}_shb_mean"] for row in summary],
                "s--",
                color="gray",
                label="SHB (ideal PSF)",
            )
            axis.legend(fontsize=7)
        axis.set_xlabel("aberration RMS (waves)")
        axis.set_title(LABELS[key], fontsize=9, loc="left")
        axis.tick_params(labelsize=8)
    figure.tight_layout()
    return save_figure(figure, path)


def plot_wavefronts(records: list[dict], path: Path, size: int = 64) -> Path:
    """Panel e: estimated | true wavefront per trial, one colour scale set by the largest RMS."""
    plt = pyplot()
    levels = sorted({r["rms"] for r in records})
    seeds = sorted({r["seed"] for r in records})
    maps = {
        (r["rms"], r["seed"]): (
            wavefront_map(r["indices"], r["estimated"], size).numpy(),
            wavefront_map(r["indices"], r["truth"], size).numpy(),
        )
        for r in records
    }
    top = [m for (rms, _), pair in maps.items() if rms == levels[-1] for m in pair]
    limit = max(float(np.nanmax(np.abs(m))) for m in top)
    figure, axes = plt.subplots(
        len(levels),
        2 * len(seeds),
        figsize=(1.3 * 2 * len(seeds) + 1, 1.4 * len(levels)),
        squeeze=False,
    )
    image = None
    for i, rms in enumerate(levels):
        for k, seed in enumerate(seeds):
            for half, label in enumerate(("4DGAT", "GT")):
                axis = axes[i, 2 * k + half]
                axis.axis("off")
                if (rms, seed) in maps:
                    image = axis.imshow(
                        maps[(rms, seed)][half], cmap="twilight_shifted", vmin=-limit, vmax=limit
                    )
                if i == 0:
                    axis.set_title(f"seed {seed} {label}", fontsize=7)
        axes[i, 0].text(
            -0.15,
            0.5,
            f"RMS {rms:g}",
            transform=axes[i, 0].transAxes,
            rotation=90,
            va="center",
            ha="right",
            fontsize=8,
        )
    figure.colorbar(image, ax=axes.ravel().tolist(), shrink=0.8, label="waves")
    figure.suptitle("e  estimated and ground-truth pupil wavefronts", fontsize=10)
    return save_figure(figure, path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--experiment", default="figS9")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", default=None, help="default: reproduce/results/<experiment>")
    args = parser.parse_args(argv)
    import mlflow  # MLflow loaded when used: keeps start-up fast

    from fgat.app.lightning_cli import tracking_uri  # imported when used: keeps start-up fast

    uri = tracking_uri(args.tracking_uri)
    mlflow.set_tracking_uri(uri)
    records = sweep_runs(args.experiment, uri)
    summary = summarize(records)
    out = Path(args.out or f"reproduce/results/{args.experiment}")
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "runs.csv", ["rms", "seed", *METRICS, *BASELINE], records)
    write_csv(out / "summary.csv", list(summary[0]), summary)
    plot_metrics(summary, out / "figS9_metrics.png")
    plot_wavefronts(records, out / "figS9_wavefronts.png")
    print(f"{'RMS':>5} {'n':>2} {'sigma':>13} {'PSNR (dB)':>13} {'SSIM':>13} {'SSIM x-y':>13}")
    for row in summary:
        cells = " ".join(f"{row[f'{k}_mean']:>6.3f}+-{row[f'{k}_sd']:<5.3f}" for k in METRICS)
        print(f"{row['rms']:>5g} {row['trials']:>2} {cells}")
    print(f"summary -> {out}")
