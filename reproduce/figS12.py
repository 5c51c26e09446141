"""Fig. S12: continuous temporal interpolation of a beating shell with 4DGAT.

Runs (or, when they finished with the same configuration, finds) the static then dynamic stage of
``python -m fgat pipeline`` on the beating-shell phantom (``--config``, ``--static`` and
``--dynamic``, each repeated to lay several files in order; other options go to both stages, as
with the pipeline),
renders the dynamic run at ``--factor`` times the frame rate with ``python -m fgat predict`` and
compares, against the phantom's truth at those timestamps:

* frames: the reconstruction at the acquired frames, held until the next one (1x);
* cubic: cubic-spline interpolation in time of those per-frame volumes (image-space upsampling);
* 4DGAT: the learned deformation field queried at the dense timestamps.

Writes ``figS12.png`` (a: kymographs along a horizontal line through the centre of the x-y MIP,
PSNR of each kymograph in its title, and the volume PSNR against time; b: a boxed region of the
kymographs enlarged) and ``figS12.csv``
(per dense timestamp: volume PSNR of the three and whether it is an acquired frame).

    python reproduce/figS12.py [--config configs/base/common.yaml
                                --config configs/dynamic_quick.yaml]
                               [--static configs/dynamic_quick_static.yaml]
                               [--dynamic configs/dynamic_quick_dynamic.yaml]
                               [--factor 10] [--span 0:1] [pipeline options]

(the defaults are shown: the quick CPU recipe; ``configs/figS12.yaml`` names the paper-size one).

``--span`` restricts the comparison to the frames within a normalised time window (the dense
volumes and the truth are held in memory: at the paper's 384 x 384 x 101, 60 MB per timestamp).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fgat.analysis import cubic_interpolation, kymograph, sample_and_hold
from fgat.app.datamodules import PhantomDataModule
from fgat.app.lightning_cli import resolved_config, run
from fgat.app.pipeline import option_words, run_pipeline
from fgat.app.process import run_recipe
from fgat.io.files import write_csv
from fgat.io.images import read_tiff
from fgat.recon.metrics import compare_volumes, max_normalize, psnr
from fgat.viz.figures import pyplot, save_figure

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("frames", "cubic", "4DGAT")


def plot(
    kymographs: dict[str, np.ndarray],
    scores: dict[str, np.ndarray],
    times: np.ndarray,
    is_frame: np.ndarray,
    path: Path,
    title: str,
) -> Path:
    """Row a: kymographs (PSNR against the truth's in the titles) and volume PSNR over time; row b:
    the boxed region (first half of the time axis, x from a tenth to half the width) enlarged."""
    plt = pyplot()
    columns = len(kymographs) + 1
    figure, axes = plt.subplots(2, columns, figsize=(3.0 * columns + 1, 6.6), squeeze=False)
    truth = max_normalize(kymographs["truth"])
    width = truth.shape[1]
    box = (times[0], times[len(times) // 2], width // 10, width // 2)  # t0, t1, x0, x1
    for column, (name, image) in enumerate(kymographs.items()):
        image = max_normalize(image)
        label = name if name == "truth" else f"{name}: {float(psnr(image, truth, 1.0)):.1f} dB"
        for row, (t0, t1, x0, x1) in enumerate(((times[0], times[-1], 0, width), box)):
            axis = axes[row, column]
            shown = image[(times >= t0) & (times <= t1), x0:x1]
            axis.imshow(
                shown.T, cmap="magma", aspect="auto", vmin=0, vmax=1, extent=(t0, t1, x1, x0)
            )
            axis.set_title(label if row == 0 else f"{name} (box)", fontsize=9)
            axis.set_xlabel("normalised time", fontsize=8)
            axis.tick_params(labelsize=7)
        axes[0, column].add_patch(
            plt.Rectangle(
                (box[0], box[2]),
                box[1] - box[0],
                box[3] - box[2],
                fill=False,
                edgecolor="white",
                lw=1,
                ls="--",
            )
        )
    for row in range(2):
        axes[row, 0].set_ylabel("x (voxels)", fontsize=8)
    curve = axes[0, -1]
    for name in METHODS:
        curve.plot(
            times, scores[name], label=f"{name} (mean {np.mean(scores[name]):.1f} dB)", lw=1.2
        )
    curve.plot(times[is_frame], scores["4DGAT"][is_frame], "k.", ms=4, label="acquired frames")
    curve.set_xlabel("normalised time", fontsize=8)
    curve.set_ylabel("volume PSNR (dB)", fontsize=8)
    curve.legend(fontsize=7)
    curve.tick_params(labelsize=7)
    axes[1, -1].axis("off")
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--config",
        action="append",
        help="the configs both stages share, laid in order (default: "
        "configs/base/common.yaml, configs/dynamic_quick.yaml)",
    )
    parser.add_argument(
        "--static",
        action="append",
        help="the static stage's configs, laid over them (default: "
        "configs/dynamic_quick_static.yaml)",
    )
    parser.add_argument(
        "--dynamic",
        action="append",
        help="the dynamic stage's configs, laid over them (default: "
        "configs/dynamic_quick_dynamic.yaml)",
    )
    parser.add_argument("--factor", type=int, default=10, help="temporal upsampling factor")
    parser.add_argument(
        "--span", default="0:1", help="normalised time window START:STOP (default all frames)"
    )
    parser.add_argument("--out", default=str(ROOT / "reproduce" / "results" / "figS12"))
    args, extra = parser.parse_known_args(argv)
    configs = args.config or [
        str(ROOT / "configs" / "base" / "common.yaml"),
        str(ROOT / "configs" / "dynamic_quick.yaml"),
    ]
    statics = args.static or [str(ROOT / "configs" / "dynamic_quick_static.yaml")]
    dynamics = args.dynamic or [str(ROOT / "configs" / "dynamic_quick_dynamic.yaml")]
    layers = option_words("--config", configs + dynamics)
    ((static, dynamic),) = run_pipeline(configs, statics, None, extra, dynamics).stages
    data = PhantomDataModule(**resolved_config(["fit", *layers, *extra])["data"]["init_args"])
    data.setup()
    scene = data.scene
    if scene.truth_at is None:
        raise SystemExit(
            f"{' + '.join(configs)}: Fig. S12 needs a dynamic phantom (its truth between frames)"
        )
    start, stop = (float(value) for value in args.span.split(":"))
    frame_times = scene.times[(scene.times >= start - 1e-9) & (scene.times <= stop + 1e-9)]
    if len(frame_times) < 2:
        raise SystemExit(
            f"--span {args.span} holds {len(frame_times)} frame(s); it needs two or more"
        )
    count = args.factor * (len(frame_times) - 1) + 1
    times = np.linspace(frame_times[0], frame_times[-1], count)
    is_frame = np.arange(count) % args.factor == 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dense = out / "volumes_dense.ome.tif"
    run(
        [
            "predict",
            *layers,
            f"--model.init_args.static={static / 'checkpoints' / 'last.ckpt'}",
            "--ckpt_path",
            str(dynamic / "checkpoints" / "last.ckpt"),
            "--times",
            f"{times[0]}:{times[-1]}:{count}",
            "--out",
            str(dense),
            "--overwrite",
            "--trainer.logger=false",
            "--trainer.enable_progress_bar=false",
            *extra,
        ]
    )
    volumes = {"4DGAT": read_tiff(dense, ndim=4)}
    frames = volumes["4DGAT"][is_frame]
    volumes.update(
        {
            "frames": sample_and_hold(frames, frame_times, times),
            "cubic": cubic_interpolation(frames, frame_times, times),
        }
    )
    truth = scene.truth_at(times)
    scores = {
        name: np.array([compare_volumes(v, t)["psnr"] for v, t in zip(volumes[name], truth)])
        for name in METHODS
    }
    write_csv(
        out / "figS12.csv",
        ["time", "acquired_frame", *(f"psnr_volume_{name}" for name in METHODS)],
        [
            [float(t), bool(f), *(float(scores[name][k]) for name in METHODS)]
            for k, (t, f) in enumerate(zip(times, is_frame))
        ],
    )
    kymographs = {"truth": kymograph(truth), **{name: kymograph(volumes[name]) for name in METHODS}}
    plot(
        kymographs,
        scores,
        times,
        is_frame,
        out / "figS12.png",
        f"{scene.name}: {len(frame_times)} frames, queried at {args.factor}x",
    )
    between = ~is_frame
    for name in METHODS:
        print(
            f"{name:>7}: volume PSNR {scores[name].mean():.2f} dB over {count} timestamps, "
            f"{scores[name][between].mean():.2f} dB between frames"
        )
    print(f"-> {out / 'figS12.png'}, {out / 'figS12.csv'}")


if __name__ == "__main__":
    run_recipe(main, "figS12")
