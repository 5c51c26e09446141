"""``python -m fgat pipeline``: the static then the dynamic stage (Fig. S3), per channel.

The configs (``--config``) name what both stages share: the data, the MLflow experiment and the
run folder. The static configs (``--static``) are laid over them for the static stage, the
dynamic ones (``--dynamic``) for the dynamic stage (its trainer settings and its
``fgat.modules.DynamicModule``). Each option may be repeated, the files laid in order as
LightningCLI lays several ``--config`` (a base, then the recipe: ``--config
configs/base/common.yaml --config configs/dynamic_quick.yaml``). Stages run under
``<root>/[ch<c>/]static`` and ``.../dynamic``, where ``<root>`` is ``--trainer.default_root_dir``
when given on the command line, else the configs'. Each
stage folder belongs to one configuration (``fingerprint.json``: the resolved config and the
contents of its input files, see ``fgat.app.fingerprint``): a stage that finished with the same
fingerprint is skipped, a killed one resumes from its ``last.ckpt``, and a stage whose folder
holds another configuration runs in ``<stage>-<fingerprint>`` beside it (the fields that differ
are printed). MLflow runs are named ``static[-ch<c>]`` and ``dynamic[-ch<c>]`` and tagged with
their fingerprint.

Multi-channel data (``(T, C, H, W)``) runs both stages per channel and merges the channels'
volume series into the OME-Zarr image ``<root>/volumes.ome.zarr`` ``(T, C, Z, Y, X)``, one time
point at a time (memory holds one frame of every channel, however long the series). The
channels run at once on Ray with ``--parallel``, and the whole pipeline on a Ray cluster with
``--address`` (see ``fgat.app.trials``). Ctrl-C or SIGTERM stops it with exit code 130 or 143, the
stage under way KILLED in MLflow and resumable from its ``last.ckpt``.
"""

from __future__ import annotations

import signal
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fgat.app.fingerprint import fingerprint, read_record, resume_checkpoint, run_folder
from fgat.app.signals import Interrupted, StopSignals
from fgat.app.trials import (
    Fanout,
    Trial,
    add_fanout_arguments,
    check_cluster_store,
    checked_store,
    fanout_from,
    mark_killed,
    now_ms,
    require_finished,
    run_trials,
)
from fgat.io.images import read_time_interval, read_voxel_size, series_frames, volume_metadata
from fgat.io.yaml_files import read_yaml
from fgat.io.zarr_series import ZarrSeriesWriter, channel_name

ROOT_OPTION = "--trainer.default_root_dir"


def _config(path: str) -> dict:
    config = read_yaml(path, f"config {path}") or {}
    if not isinstance(config, dict):
        raise ValueError(
            f"config {path}: expected a mapping of LightningCLI fields, got {type(config).__name__}"
        )
    return config


def merged_config(paths: Sequence[str]) -> dict:
    """The YAML mappings of ``paths`` (each checked by :func:`_config`) merged in order: a mapping
    merges key by key into the one before it, any other value replaces it. LightningCLI lays
    several ``--config`` files the same way for the fields read here (``trainer.default_root_dir``,
    ``data.init_args.measurement``)."""
    merged: dict = {}
    for path in paths:
        merged = _merge(merged, _nested(_config(path)))
    return merged


def _nested(config: dict) -> dict:
    """Dotted keys (``trainer.default_root_dir: runs/x``, as LightningCLI reads them) as nested
    mappings."""
    result: dict = {}
    for key, value in config.items():
        *parents, last = str(key).split(".")
        node = result
        for parent in parents:
            node = node.setdefault(parent, {})
        node[last] = (
            _merge(node[last], value)
            if isinstance(node.get(last), dict) and isinstance(value, dict)
            else value
        )
    return result


def _merge(base: dict, over: dict) -> dict:
    result = dict(base)
    for key, value in over.items():
        nested = isinstance(result.get(key), dict) and isinstance(value, dict)
        result[key] = _merge(result[key], value) if nested else value
    return result


def _paths(given: str | Path | Sequence[str | Path]) -> list[str]:
    return [str(given)] if isinstance(given, (str, Path)) else [str(path) for path in given]


def data_channels(config: dict, source: str) -> int:
    """Channels of the config's measurement: ``C`` of a ``(T, C, H, W)`` TIFF, else 1."""
    data = (config.get("data") or {}).get("init_args") or {}
    if "measurement" not in data:
        return 1
    import tifffile  # loaded when a file is read or written: keeps start-up fast

    with tifffile.TiffFile(data["measurement"]) as tif:
        shape = tif.series[0].shape
    if len(shape) not in (2, 3, 4):
        raise ValueError(
            f"{source}: data.measurement {data['measurement']} has shape {shape}; expected "
            "(H, W), (T, H, W) or (T, C, H, W)"
        )
    return shape[1] if len(shape) == 4 else 1


def parse_channels(text: str | None, available: int) -> list[int | None]:
    """``None`` (single-channel data), ``"all"`` or ``"0,2"`` -> channel list."""
    if text is None:
        if available > 1:
            raise ValueError(
                f"the data has {available} channels: pass --channels all (or a list such as 0,2)"
            )
        return [None]
    expected = f"expected all or channel numbers in 0..{available - 1}, e.g. 0,2"
    words = [word.strip() for word in text.split(",") if word.strip()]
    if text != "all" and not all(word.isdigit() for word in words):
        raise ValueError(f"--channels {text!r}: {expected}")
    channels = list(range(available)) if text == "all" else [int(word) for word in words]
    bad = [c for c in channels if not 0 <= c < available]
    if not channels or bad:
        raise ValueError(f"--channels {text!r}: the data has channels 0..{available - 1}")
    if len(set(channels)) < len(channels):
        raise ValueError(f"--channels {text!r}: a channel is given twice")
    return channels


def split_root(extra: list[str], config: dict) -> tuple[Path, list[str]]:
    """The pipeline's root (``--trainer.default_root_dir`` among the command-line options, else the
    config's, else ``runs/fgat``) and the options without it (each stage gets its own folder)."""
    root, rest, words = None, [], iter(extra)
    for word in words:
        if word == ROOT_OPTION:
            root = next(words, None)
            if root is None:
                raise ValueError(f"{ROOT_OPTION} needs a folder")
        elif word.startswith(f"{ROOT_OPTION}="):
            root = word.split("=", 1)[1]
        else:
            rest.append(word)
    return Path(root or (config.get("trainer") or {}).get("default_root_dir") or "runs/fgat"), rest


def run_stage(label: str, base: Path, args: list[str]) -> Path:
    """Fit a stage in its folder (see the module's notes) unless a run with the same fingerprint
    finished there; resume a killed one from its ``last.ckpt``. Returns the stage's folder."""
    from fgat.app.lightning_cli import (  # imported when used: keeps start-up fast
        resolved_config,
        run,
    )

    fp = fingerprint(resolved_config(["fit", *args]))
    folder, taken = run_folder(base, fp)
    if taken:
        print(f"fgat pipeline: {taken}: this {label} runs in {folder}")
    record = read_record(folder)
    if record is not None and record["fingerprint"] != fp.digest:
        record = None  # a run of another configuration: its checkpoint is not this one's
    if (
        record is not None
        and record.get("status") == "finished"
        and Path(record.get("results", "")).is_dir()
    ):
        print(
            f"fgat pipeline: {label} finished before with this configuration "
            f"(fingerprint {fp.short}, {folder}): skipped"
        )
        return folder
    checkpoint = resume_checkpoint(folder, fp)
    resume = [] if checkpoint is None else ["--ckpt_path", str(checkpoint)]
    print(
        f"fgat pipeline: {label} -> {folder}" + (f" (resuming from {checkpoint})" if resume else "")
    )
    run(["fit", *args, f"{ROOT_OPTION}={folder}", *resume])
    return folder


def stage_result(folder: Path, *names: str) -> Path:
    """The first of the files ``names`` among the results of the finished run recorded in
    ``folder``."""
    record = read_record(folder) or {}
    results = Path(record.get("results", folder / "results"))
    found = [results / name for name in names if (results / name).exists()]
    if record.get("status") != "finished" or not found:
        raise FileNotFoundError(
            f"no {' or '.join(names)} in the results of {folder}: the stage did not finish"
        )
    return found[0]


@dataclass(frozen=True)
class PipelineResult:
    """What :func:`run_pipeline` made: ``volumes``, the ``(T, Z, Y, X)`` series of one channel or
    the merged ``(T, C, Z, Y, X)`` file, and the ``(static, dynamic)`` stage folders of every
    channel."""

    volumes: Path
    stages: list[tuple[Path, Path]]


def option_words(option: str, paths: Sequence[str]) -> list[str]:
    """``option`` before each of ``paths``: ``--config A --config B`` lays them in order."""
    return [word for path in paths for word in (option, path)]


def pipeline_tracking(
    configs: Sequence[str],
    statics: Sequence[str],
    extra: Sequence[str],
    fanout: Fanout | None = None,
) -> tuple[str, str]:
    """The tracking URI and experiment of a pipeline (its static stage's, whose configuration
    is resolved and checked here: a store a Ray cluster (``fanout.address``) cannot log to, by
    :func:`fgat.app.trials.check_cluster_store`, then the store by
    :func:`fgat.app.trials.checked_store`)."""
    from fgat.app.lightning_cli import (  # imported when used: keeps start-up fast
        resolved_config,
        tracking_uri,
    )

    static = resolved_config(["fit", *option_words("--config", [*configs, *statics]), *extra])
    uri, experiment = tracking_uri(static["mlflow"]["tracking_uri"]), static["mlflow"]["experiment"]
    if fanout is not None:
        check_cluster_store([uri], fanout)
    checked_store(uri, experiment)
    return uri, experiment


def pipeline_trial(
    name: str,
    configs: Sequence[str],
    statics: Sequence[str],
    dynamics: Sequence[str],
    extra: Sequence[str],
    root: Path,
    tracking: tuple[str, str],
    channel: int | None = None,
) -> Trial:
    """``fgat pipeline`` over ``root`` (one ``channel`` of it, or all of the data's) as a
    :class:`fgat.app.trials.Trial` logging where ``tracking`` says (:func:`pipeline_tracking`).
    ``extra`` holds no ``--trainer.default_root_dir``."""
    words = [
        "pipeline",
        *option_words("--config", configs),
        *option_words("--static", statics),
        *option_words("--dynamic", dynamics),
        *([] if channel is None else ["--channels", str(channel)]),
        *extra,
        f"{ROOT_OPTION}={root}",
    ]
    folder = root if channel is None else root / f"ch{channel}"
    return Trial(name, tuple(words), folder, *tracking)


def run_pipeline(
    config: str | Sequence[str],
    static: str | Sequence[str],
    channels: str | None = None,
    extra: list[str] | None = None,
    dynamic: str | Sequence[str] = (),
    fanout: Fanout | None = None,
) -> PipelineResult:
    """Both stages for every channel (each skipped when it finished with the same fingerprint).
    ``config`` (both stages), ``static`` and ``dynamic`` (one stage each) are a path or several,
    laid in order. The tracking store is checked first. With a parallel ``fanout`` and several
    channels, or a Ray cluster (``fanout.address``), the channels run as
    :func:`fgat.app.trials.run_trials` trials first (this process then finds their stages finished
    and merges them).

    Raises
    ------
    fgat.app.signals.Interrupted
        SIGINT or SIGTERM stopped it (no stage starts after it; a stage's MLflow run stopped
        before its fit could end it is marked KILLED).
    """
    configs, statics, dynamics = _paths(config), _paths(static), _paths(dynamic)
    dynamic_config = merged_config(configs)
    merged_config(statics + dynamics)
    root, extra = split_root(list(extra or []), dynamic_config)
    chosen = parse_channels(channels, data_channels(dynamic_config, " + ".join(configs)))
    tracking = pipeline_tracking(configs, statics, extra, fanout)
    started_ms, stop = now_ms(), StopSignals()
    try:
        with stop:
            if fanout is not None and (
                fanout.address is not None or (not fanout.serial and len(chosen) > 1)
            ):
                trials = [
                    pipeline_trial(
                        "pipeline" if c is None else f"channel {c}",
                        configs,
                        statics,
                        dynamics,
                        extra,
                        root,
                        tracking,
                        c,
                    )
                    for c in chosen
                ]
                require_finished(run_trials(trials, fanout, "fgat pipeline"))
            return _run_stages(configs, statics, dynamics, extra, root, chosen)
    except Interrupted as stopped:
        if stop.number is None:  # a stage's fit or the trials stopped themselves and said so
            raise
        killed = mark_killed(
            Trial("pipeline", (), root, *tracking), started_ms, ("RUNNING", "FAILED")
        )
        marked = f"; MLflow run {', '.join(killed)} marked KILLED" if killed else ""
        raise Interrupted(
            stopped.number,
            f"stopped by {signal.Signals(stopped.number).name}{marked}; no further stage "
            "started. The same command goes on: finished stages are skipped, a stopped one "
            "resumes from its last.ckpt",
        ) from None


def _run_stages(
    configs: list[str],
    statics: list[str],
    dynamics: list[str],
    extra: list[str],
    root: Path,
    chosen: list[int | None],
) -> PipelineResult:
    """Both stages of every channel of ``chosen`` in this process, then the merge."""
    layers = option_words("--config", configs)
    static_layers = layers + option_words("--config", statics)
    dynamic_layers = layers + option_words("--config", dynamics)
    named = any(word.startswith("--mlflow.run_name") for word in extra)
    series, stages = [], []
    for channel in chosen:
        folder = root if channel is None else root / f"ch{channel}"
        select = [] if channel is None else [f"--data.init_args.channel={channel}"]
        tag = "" if channel is None else f" (channel {channel})"
        suffix = "" if channel is None else f"-ch{channel}"
        static_folder = run_stage(
            f"static stage{tag}",
            folder / "static",
            [*static_layers, *select, *extra]
            + ([] if named else [f"--mlflow.run_name=static{suffix}"]),
        )
        checkpoint = static_folder / "checkpoints" / "last.ckpt"
        dynamic_folder = run_stage(
            f"dynamic stage{tag}",
            folder / "dynamic",
            [*dynamic_layers, *select, f"--model.init_args.static={checkpoint}", *extra]
            + ([] if named else [f"--mlflow.run_name=dynamic{suffix}"]),
        )
        series.append(stage_result(dynamic_folder, "volumes.ome.tif", "volumes.ome.zarr"))
        stages.append((static_folder, dynamic_folder))
    if len(series) == 1:
        print(f"fgat pipeline: volumes (T, Z, Y, X) -> {series[0]}")
        return PipelineResult(series[0], stages)
    merged = merge_channels(series, root / "volumes.ome.zarr", chosen)
    print(f"fgat pipeline: channels {chosen} merged -> {merged}")
    return PipelineResult(merged, stages)


def merge_channels(
    series: Sequence[Path], merged: Path, channels: Sequence[int] | None = None
) -> Path:
    """Merge one ``(T, Z, Y, X)`` series per channel (OME-TIFF or OME-Zarr) into the OME-Zarr
    image ``merged`` ``(T, C, Z, Y, X)``, one time point at a time: memory holds one frame of
    every channel, however long the series. Voxel size, time interval and volume entries are
    the first channel's; the channels are named ``"channel c"`` by their index ``c`` in the
    data (``channels``, one per series; default their position); an existing ``merged`` is
    replaced once the new one is whole."""
    channels = range(len(series)) if channels is None else channels
    if len(channels) != len(series):
        raise ValueError(f"{len(channels)} channel indices for {len(series)} series")
    counts, frames = zip(*(series_frames(path) for path in series))
    if len(set(counts)) > 1:
        raise ValueError(
            f"the channels' series have {list(counts)} time points; expected one count"
        )
    sizes = read_voxel_size(series[0])
    first = [next(channel) for channel in frames]
    with ZarrSeriesWriter(
        merged,
        (len(series), *first[0].shape),
        voxel_size_um=tuple(sizes.get(a, 1.0) for a in "ZYX"),
        time_interval_s=read_time_interval(series[0]),
        overwrite=True,
        metadata=volume_metadata(series[0]),
        channel_names=[channel_name(c) for c in channels],
    ) as writer:
        writer.append(first)
        del first  # one time point of every channel at a time, and no more
        for _ in range(counts[0] - 1):
            writer.append([next(channel) for channel in frames])
    return merged


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "pipeline",
        help="static then dynamic stage (per channel), merged result",
        description=__doc__.split("\n\n", 1)[1],
        epilog="Other options (e.g. --trainer.accelerator=cpu) are passed to both stages.",
    )
    parser.add_argument(
        "--config",
        required=True,
        action="append",
        help="a LightningCLI config both stages share (the data); repeat it to lay several files "
        "in order, e.g. a base then the recipe",
    )
    parser.add_argument(
        "--static",
        required=True,
        action="append",
        help="the static stage's config, laid over the --config files; may be repeated too",
    )
    parser.add_argument(
        "--dynamic",
        action="append",
        default=[],
        help="the dynamic stage's config (its trainer and model), laid over the --config files; "
        "may be repeated too",
    )
    parser.add_argument("--channels", help="'all' or a list (0,2) for (T, C, H, W) data")
    add_fanout_arguments(parser)
    parser.set_defaults(run=_run, forwards_unknown=True)


def _run(args) -> int:
    run_pipeline(
        args.config, args.static, args.channels, args.extra, args.dynamic, fanout_from(args)
    )
    return 0
