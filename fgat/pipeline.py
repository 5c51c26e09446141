"""``python -m fgat pipeline``: the static then the dynamic stage (Fig. S3), per channel.

The dynamic config (``--config``) names the data, the dynamic stage's trainer and its
``fgat.modules.DynamicModule``; the static config (``--static``) is laid over it for the static
stage (its trainer settings and its ``fgat.modules.StaticModule``). Stages run under
``<root>/[ch<c>/]static`` and ``.../dynamic`` (``<root>``: the dynamic config's
``trainer.default_root_dir``). A finished stage is skipped and a killed one resumes from its
``last.ckpt``. MLflow runs are named ``static[-ch<c>]`` and ``dynamic[-ch<c>]``. Multi-channel
data (``(T, C, H, W)``) runs both stages per channel and merges the channels' volume series into
``<root>/volumes.ome.tif`` ``(T, C, Z, Y, X)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from fgat.io import atomic_path, read_series, read_voxel_size, write_tiff

DONE = "stage.done"


def _config(path: str) -> dict:
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f"pipeline: config {path} does not exist")
    return yaml.safe_load(file.read_text()) or {}


def data_channels(config: dict, source: str) -> int:
    """Channels of the config's measurement: ``C`` of a ``(T, C, H, W)`` TIFF, else 1."""
    data = (config.get("data") or {}).get("init_args") or {}
    if "measurement" not in data:
        return 1
    import tifffile

    with tifffile.TiffFile(data["measurement"]) as tif:
        shape = tif.series[0].shape
    if len(shape) not in (2, 3, 4):
        raise ValueError(f"{source}: data.measurement {data['measurement']} has shape {shape}; expected "
                         "(H, W), (T, H, W) or (T, C, H, W)")
    return shape[1] if len(shape) == 4 else 1


def parse_channels(text: str | None, available: int) -> list[int | None]:
    """``None`` (single-channel data), ``"all"`` or ``"0,2"`` -> channel list."""
    if text is None:
        if available > 1:
            raise ValueError(f"the data has {available} channels: pass --channels all (or a list such as 0,2)")
        return [None]
    channels = list(range(available)) if text == "all" else [int(c) for c in text.split(",") if c.strip()]
    bad = [c for c in channels if not 0 <= c < available]
    if not channels or bad:
        raise ValueError(f"--channels {text!r}: the data has channels 0..{available - 1}")
    return channels


def latest_result(stage_root: Path, name: str) -> Path:
    """The newest ``results/<run>/<name>`` of a stage."""
    found = sorted((stage_root / "results").glob(f"*/{name}"), key=lambda p: p.stat().st_mtime)
    if not found:
        raise FileNotFoundError(f"no {name} under {stage_root / 'results'}: did the stage finish?")
    return found[-1]


def run_stage(label: str, stage_root: Path, args: list[str]) -> None:
    """``fit`` a stage unless it finished before; resume from its ``last.ckpt`` when one exists."""
    from fgat.lightning_cli import run

    if (stage_root / DONE).is_file():
        print(f"fgat pipeline: {label} finished before ({stage_root / DONE}): skipped")
        return
    checkpoint = stage_root / "checkpoints" / "last.ckpt"
    resume = ["--ckpt_path", str(checkpoint)] if checkpoint.is_file() else []
    print(f"fgat pipeline: {label} -> {stage_root}" + (f" (resuming from {checkpoint})" if resume else ""))
    run(["fit", *args, f"--trainer.default_root_dir={stage_root}", *resume])
    stage_root.mkdir(parents=True, exist_ok=True)
    with atomic_path(stage_root / DONE) as temporary:
        temporary.write_text("finished\n")


def run_pipeline(config: str, static: str, channels: str | None = None, extra: list[str] | None = None) -> Path:
    """Both stages for every channel; returns the result (merged for several channels)."""
    dynamic_config = _config(config)
    _config(static)
    root = Path((dynamic_config.get("trainer") or {}).get("default_root_dir") or "runs/fgat")
    chosen = parse_channels(channels, data_channels(dynamic_config, config))
    extra = list(extra or [])
    named = any(word.startswith("--mlflow.run_name") for word in extra)
    series = []
    for channel in chosen:
        folder = root if channel is None else root / f"ch{channel}"
        select = [] if channel is None else [f"--data.init_args.channel={channel}"]
        tag = "" if channel is None else f" (channel {channel})"
        suffix = "" if channel is None else f"-ch{channel}"
        run_stage(f"static stage{tag}", folder / "static", ["--config", config, "--config", static, *select, *extra]
                  + ([] if named else [f"--mlflow.run_name=static{suffix}"]))
        checkpoint = folder / "static" / "checkpoints" / "last.ckpt"
        run_stage(f"dynamic stage{tag}", folder / "dynamic",
                  ["--config", config, *select, f"--model.init_args.static={checkpoint}", *extra]
                  + ([] if named else [f"--mlflow.run_name=dynamic{suffix}"]))
        series.append(latest_result(folder / "dynamic", "volumes.ome.tif"))
    if len(series) == 1:
        print(f"fgat pipeline: volumes (T, Z, Y, X) -> {series[0]}")
        return series[0]
    merged = root / "volumes.ome.tif"
    volumes = np.stack([read_series(path) for path in series], axis=1)
    sizes = read_voxel_size(series[0])
    write_tiff(merged, volumes, axes="TCZYX", voxel_size_um=tuple(sizes.get(a, 1.0) for a in "ZYX"))
    print(f"fgat pipeline: channels {chosen} merged, {volumes.shape} (T, C, Z, Y, X) -> {merged}")
    return merged


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "pipeline", help="static then dynamic stage (per channel), merged result",
        description=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Other options (e.g. --trainer.accelerator=cpu) are passed to both stages.")
    parser.add_argument("--config", required=True, help="the dynamic stage's LightningCLI config (with the data)")
    parser.add_argument("--static", required=True, help="the static stage's config, laid over --config")
    parser.add_argument("--channels", help="'all' or a list (0,2) for (T, C, H, W) data")
    parser.set_defaults(run=_run, forwards_unknown=True)


def _run(args) -> int:
    run_pipeline(args.config, args.static, args.channels, args.extra)
    return 0
