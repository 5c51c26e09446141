"""``python -m fgat fit|validate|test|predict``: LightningCLI with fgat's defaults.

* Model and data classes come from the config (``model.class_path``, ``data.class_path``);
  every field can be overridden on the command line (``--model.init_args.lr_means=0.01``).
  Configs are parsed in omegaconf+ mode: interpolations see command-line overrides.
* MLflow is the logger unless the config sets ``trainer.logger``: experiment
  ``--mlflow.experiment``, tracking URI ``--mlflow.tracking_uri``, else ``MLFLOW_TRACKING_URI``,
  else ``sqlite:///mlflow.db``.
* Checkpoints go to ``<trainer.default_root_dir>/checkpoints`` (``last.ckpt`` every
  ``--checkpoint_every`` steps and at the end, written under a temporary name and renamed when
  whole; a full disk ends the fit with one line and its MLflow run FAILED), so ``--ckpt_path
  last`` resumes a killed or finished run. Without a checkpoint there (a fit killed before its
  first), ``--ckpt_path last`` says so in one line and starts from scratch. A checkpoint holds
  the fingerprint of its run: resuming with another configuration (only the training length
  may change) is refused, naming the fields that differ, for ``last`` and a path alike.
* A fit holds ``<trainer.default_root_dir>/fit.lock`` (its PID and host) while it runs: a second
  fit into the folder is refused, naming the PID; a lock left by a killed process is taken
  over. The folder's ``fingerprint.json`` keeps the PID of a running fit, so the MLflow run of a
  fit killed by SIGKILL is marked KILLED when the folder is next used.
* The artifact callbacks are always attached.
* ``predict`` renders a dynamic run at ``--times`` (normalised sequence times: 0 the first
  frame, 1 the last; ``start:stop:count`` or a comma list; default the frames' times) into one
  OME-TIFF ``(T, Z, Y, X)`` at ``--out`` (default
  ``<default_root_dir>/predictions/volumes.ome.tif``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import importlib
import inspect
import logging
import math
import os
import re
import shutil
import signal
import sys
import time
import typing
import warnings
from pathlib import Path

from jsonargparse import ActionYesNo, ArgumentError, DefaultHelpFormatter
from lightning.fabric.plugins import TorchCheckpointIO
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch import Callback, LightningDataModule, LightningModule
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.utilities import rank_zero_info

from fgat._core.resources import check_memory, format_bytes
from fgat._core.validation import parse_values, require
from fgat.app.arguments import LIGHTNING_COMMANDS, PlainHelpFormatter, describe
from fgat.app.callbacks import (
    MLflowResume,
    MLflowSaveConfig,
    MonitorStop,
    ReconstructionArtifacts,
    SignalStop,
    StepCheckpoint,
    VolumeSeriesWriter,
)
from fgat.app.callbacks.interrupt import STOP_SIGNALS
from fgat.app.callbacks.mlflow import (
    FINGERPRINT,
    HOST,
    PID,
    RUN_FOLDER,
    check_tracking_uri,
    delete_run,
    end_orphaned_run,
    mark_killed,
    mlflow_loggers,
    results_folder,
)
from fgat.app.fingerprint import (
    TRAINING_LENGTH,
    Fingerprint,
    canonical,
    differing_fields,
    differing_keys,
    fingerprint,
    lock_folder,
    orphaned,
    process_fields,
    read_record,
    unlock_folder,
    write_record,
)
from fgat.app.signals import Interrupted, set_handler
from fgat.app.tracking_server import sqlite_file
from fgat.io.checkpoints import load_torch_file, save_torch_file
from fgat.io.files import check_output_file, check_writable_folder
from fgat.io.yaml_files import check_config_files, load_yaml
from fgat.recon import costs

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"
DEFAULT_ROOT = "runs/fgat"  # trainer.default_root_dir when the config gives none


def tracking_uri(configured: str | None) -> str:
    """The config's URI, else ``MLFLOW_TRACKING_URI``, else a SQLite file in the working
    directory."""
    return configured or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_TRACKING_URI


CHECKPOINT_EVERY = 100  # --checkpoint_every: steps between two saves of last.ckpt

DETAILS = {
    "fit": """Several --config files are laid in order (--config configs/base/common.yaml --config
configs/quickstart.yaml); any field can be overridden on the command line
(--model.init_args.lr_means=0.01). The run folder is --trainer.default_root_dir (default
runs/fgat); last.ckpt is saved there (checkpoints/) every --checkpoint_every steps and at the
end, and --ckpt_path last resumes the run. MLflow logs the run (--mlflow.*).""",
    "validate": """Give the fit's --config files and its checkpoint (--ckpt_path
<root>/checkpoints/last.ckpt).""",
    "test": """Give the fit's --config files and its checkpoint (--ckpt_path
<root>/checkpoints/last.ckpt).""",
    "predict": """Renders the dynamic model of --ckpt_path (a DynamicModule fit, given with its
--config files) at --times into one OME-TIFF (T, Z, Y, X) at --out (default
<trainer.default_root_dir>/predictions/volumes.ome.tif).""",
}
"""What each LightningCLI subcommand's ``--help`` says after its one-line summary."""

GROUP_TITLES = {
    "trainer": "Trainer (Lightning): where the run computes, how long, what it logs",
    "model": "Model: an fgat module (fgat.modules.StaticModule or DynamicModule) and its init_args",
    "data": "Data: an fgat datamodule (fgat.datamodules.*) and its init_args",
}
"""Titles of the option groups, in place of the first lines of Lightning's docstrings."""

OPTION_HELP = {
    "seed_everything": "seed of torch, numpy and random before the model and data are built "
    "(fgat's configs set 0); true: a random one, recorded in the run's config",
    "trainer.accelerator": "where the run computes: cpu, gpu (CUDA), mps, or auto (a GPU "
    "when there is one)",
    "trainer.devices": "devices of the accelerator: a count, a list of indices, or auto (all of "
    "them)",
    "trainer.precision": "floating-point precision of the run (null: 32-true, the float32 fgat's "
    "models compute in)",
    "trainer.max_steps": "stop after this many training steps, one model update each (-1: no "
    "step limit)",
    "trainer.max_epochs": "stop after this many epochs (-1: no limit; null: Lightning's 1000 "
    "when max_steps is -1 too); a static fit is one endless epoch, bounded by max_steps",
    "trainer.val_check_interval": "validate (the volume metrics) every this many training steps "
    "(an int), or at this fraction of an epoch (a float)",
    "trainer.check_val_every_n_epoch": "validate every this many epochs; null: every "
    "val_check_interval steps across epochs (fgat's static configs)",
    "trainer.log_every_n_steps": "log the training metrics every this many steps (null: 50)",
    "trainer.num_sanity_val_steps": "validation batches run before training starts (null: 2; "
    "fgat's configs set 0)",
    "trainer.enable_progress_bar": "show the progress bar (null: true)",
    "trainer.enable_model_summary": "print the model's layer summary before the fit (null: true; "
    "fgat's configs set false)",
    "trainer.enable_checkpointing": "fgat always saves last.ckpt (every --checkpoint_every steps "
    "and at the end), so false is refused (null: true)",
    "trainer.default_root_dir": "the run folder: checkpoints/, results/, fingerprint.json "
    f"(default {DEFAULT_ROOT})",
    "trainer.logger": "loggers; null (default) or true: MLflow, as --mlflow.* say; false: none",
    "trainer.callbacks": "callbacks added to fgat's own (checkpoints, artifacts, MLflow), e.g. "
    "fgat.callbacks.PlateauStopping",
    "trainer.model_registry": "Lightning model registry name for --ckpt_path registry (not used "
    "by fgat)",
    "weights_only": "checkpoints are read as weights only (true); false is refused: unpickling "
    "other objects can run code",
}
"""Help of the options whose Lightning docstring misleads or says nothing of fgat."""

CHECKPOINT_HELP = {
    "fit": "resume from this checkpoint: last (the newest last.ckpt in "
    "<trainer.default_root_dir>/checkpoints; none there: start afresh) or a file of a fit with "
    "the same configuration (only the training length may change)",
    "predict": "the checkpoint of a dynamic fit (<root>/checkpoints/last.ckpt); required",
}
"""``--ckpt_path`` per subcommand; the others: :data:`CHECKPOINT_LOADED`."""

CHECKPOINT_LOADED = "the checkpoint to evaluate: a fit's <root>/checkpoints/last.ckpt, or last"

PREDICT_ONLY = ("--times", "--out", "--overwrite")


class FGATHelpFormatter(PlainHelpFormatter, DefaultHelpFormatter):
    """jsonargparse's help (types and defaults shown) as plain text: Lightning's reST
    docstrings without their markup."""


def add_predict_arguments(parser) -> None:
    """``predict``'s own options: ``--times``, ``--out``, ``--overwrite``."""
    parser.add_argument(
        "--times",
        type=str | None,
        default=None,
        help="normalised times (0 = first frame, 1 = last), start:stop:count or a comma list "
        "(default: the frames' times)",
    )
    parser.add_argument(
        "--out",
        type=str | None,
        default=None,
        help="OME-TIFF of the rendered volumes (T, Z, Y, X) (default "
        "<trainer.default_root_dir>/predictions/volumes.ome.tif)",
    )
    parser.add_argument(
        "--overwrite", action=ActionYesNo, default=False, help="replace an existing --out file"
    )


def retitle(parser, subcommand: str) -> None:
    """Give a subcommand parser's option groups and the options of :data:`OPTION_HELP` and
    ``--ckpt_path`` fgat's help in place of Lightning's docstrings."""
    for key, group in parser.groups.items():
        if key in GROUP_TITLES:
            group.title = GROUP_TITLES[key]
        elif key == subcommand:
            group.title = "Checkpoint and loop"
    helps = OPTION_HELP | {"ckpt_path": CHECKPOINT_HELP.get(subcommand, CHECKPOINT_LOADED)}
    for action in parser._actions:
        if action.dest in helps:
            action.help = helps[action.dest]


class FGATCLI(LightningCLI):
    def _prepare_subcommand_parser(self, klass, subcommand: str, **kwargs):
        """A subcommand's parser with its one-line description and only its own options:
        predict's ``--times``, ``--out`` and ``--overwrite`` are predict's alone."""
        kwargs["description"] = describe(LIGHTNING_COMMANDS[subcommand], DETAILS[subcommand])
        parser = super()._prepare_subcommand_parser(klass, subcommand, **kwargs)
        if subcommand == "predict":
            add_predict_arguments(parser)
        retitle(parser, subcommand)
        return parser

    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument(
            "--mlflow.experiment", type=str, default="fgat", help="MLflow experiment name"
        )
        parser.add_argument(
            "--mlflow.tracking_uri",
            type=str | None,
            default=None,
            help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)",
        )
        parser.add_argument(
            "--mlflow.run_name",
            type=str | None,
            default=None,
            help="MLflow run name (default <subcommand>-<static|dynamic>-<date>-<time>)",
        )
        parser.add_argument(
            "--checkpoint_every",
            type=int,
            default=CHECKPOINT_EVERY,
            help="fit: save last.ckpt every N steps (the other subcommands accept it, as they "
            "read the fit's configs)",
        )

    fingerprint: Fingerprint | None = None
    lock: Path | None = None  # the run folder's lock file, while this fit holds it
    uri: str | None = None  # the MLflow tracking URI of the run
    recorded = False  # whether the run's record (fingerprint.json) says it is running

    new_root: Path | None = None  # the run folder, when this run created it
    new_artifacts: Path | None = None  # MLflow's artifact folder, when this run created it

    def __init__(self, *args, **kwargs) -> None:
        """Parse, build and run; the run folder's lock (:meth:`before_instantiate_classes`) is
        released however that ends, and a run that fails before its first step leaves none of
        the files and folders it created (:meth:`_remove_created`)."""
        try:
            super().__init__(*args, **kwargs)
        except Exception as error:
            self._unlock()
            if not isinstance(error, Interrupted):
                self._remove_created()
            raise
        finally:
            self._unlock()

    def _unlock(self) -> None:
        if self.lock is not None:
            unlock_folder(self.lock)
            self.lock = None

    def _remove_created(self) -> None:
        """Remove what this run created (its run folder, its part of a new artifact folder) when
        it failed before any step: a refused fit leaves no litter. A fit that ran keeps its
        files, its record and its FAILED run. The tracking database stays (MLflow keeps it open
        in this process) with the experiment; the refused run is deleted from it (MLflow's
        deleted stage: out of the UI and searches, restorable)."""
        trainer = getattr(self, "trainer", None)
        if trainer is not None and trainer.global_step > 0:
            return
        run = self._run_id() if trainer is not None else None
        if self.new_root is not None and self.new_root.is_dir():
            shutil.rmtree(self.new_root, ignore_errors=True)
        if self.new_artifacts is not None and self.new_artifacts.is_dir():
            remove_run_artifacts(self.new_artifacts, run)  # other runs may have started there
        if run is not None and self.uri is not None:
            delete_run(self.uri, run)

    def _parse_ckpt_path(self) -> None:
        """Lightning replaces the model's settings by those a ``--ckpt_path`` file was saved
        with, silently; a fit keeps the configuration given, which :func:`check_resume` then
        compares with the checkpoint's (other subcommands build their model Lightning's way)."""
        if self.config.get("subcommand") != "fit":
            super()._parse_ckpt_path()

    def resolved(self) -> dict:
        """The subcommand's resolved configuration as a plain dict (what ``config.yaml`` holds)."""
        return load_yaml(
            self._parser(self.subcommand).dump(self.config[self.subcommand], skip_none=False),
            f"the resolved {self.subcommand} configuration",
        )

    def before_instantiate_classes(self) -> None:
        """A fit takes its run folder's lock (:func:`fgat.app.fingerprint.lock_folder`) before
        anything is built, and ends the MLflow run of a fit there that was killed before it
        could (:meth:`_end_orphan`)."""
        if self.subcommand != "fit":
            return
        settings = self.config["fit"]
        root = Path(settings["trainer"]["default_root_dir"] or DEFAULT_ROOT)
        existed = root.exists()
        self.lock, note = lock_folder(root)
        self.new_root = None if existed else root  # once held: never a folder another fit holds
        if note:
            rank_zero_info(f"fgat: {note}")
        self._end_orphan(root)

    def _end_orphan(self, root: Path) -> None:
        """``root``'s record says a fit is running, but its process is dead (killed by SIGKILL
        before it could end its run): mark its MLflow run KILLED and its record killed."""
        record = read_record(root)
        if not orphaned(record):
            return
        uri = record.get("tracking_uri") or tracking_uri(
            self.config["fit"]["mlflow"]["tracking_uri"]
        )
        run = record.get("run_id")
        ended = run is not None and end_orphaned_run(uri, run)
        write_record(
            root,
            Fingerprint(record["fingerprint"], record.get("config", {})),
            **{key: value for key, value in record.items() if key not in ("fingerprint", "config")}
            | {"status": "killed"},
        )
        run_line = f"; its MLflow run {run} marked KILLED" if ended else ""
        rank_zero_info(
            f"fgat: the fit of PID {record['pid']} in {root} was killed before it ended{run_line}"
        )

    def before_fit(self) -> None:
        root = Path(self.trainer.default_root_dir)
        checkpoint = self.config["fit"]["ckpt_path"]
        if checkpoint == "last":  # an explicit file was checked as the trainer was built
            path = self._checkpoint_file(str(checkpoint))
            if path is None:
                folders = ", ".join(sorted({str(c.dirpath) for c in self._checkpointers()}))
                rank_zero_info(
                    f"fgat: --ckpt_path {checkpoint}: no checkpoint in {folders or root}; "
                    "starting from scratch"
                )
            else:
                check_resume(str(checkpoint), path, self.fingerprint)
            self.config_init["fit"]["ckpt_path"] = None if path is None else str(path)
        self._record("running", **process_fields())
        self.recorded = True

    def _checkpointers(self) -> list[ModelCheckpoint]:
        return [c for c in self.trainer.checkpoint_callbacks if getattr(c, "dirpath", None)]

    def _checkpoint_file(self, checkpoint: str) -> Path | None:
        """The file ``--ckpt_path`` names: ``last`` is the newest ``last*.ckpt`` in the
        checkpoint folders of the trainer (as Lightning resolves it), ``None`` when there is
        none; a path is itself."""
        if checkpoint != "last":
            return Path(checkpoint)
        found = [
            path
            for callback in self._checkpointers()
            for path in Path(callback.dirpath).glob("last*.ckpt")
        ]
        return max(found, key=lambda path: path.stat().st_mtime) if found else None

    def after_fit(self) -> None:
        """The run finished: its record says so and where its results are."""
        if self.trainer.interrupted:
            return
        self._record("finished", results=str(results_folder(self.trainer)))

    def _record(self, status: str, **fields) -> None:
        """Write the run folder's record (``fingerprint.json``): ``status``, the MLflow run, the
        tracking URI and ``fields``."""
        write_record(
            self.trainer.default_root_dir,
            self.fingerprint,
            status=status,
            run_id=self._run_id(),
            tracking_uri=self.uri,
            **fields,
        )

    def _run_subcommand(self, subcommand: str) -> None:
        """Run it; a fit stopped by SIGINT or SIGTERM (:class:`~fgat.callbacks.SignalStop`)
        ends its MLflow runs KILLED and raises :class:`~fgat.app.signals.Interrupted`."""
        handlers = {number: signal.getsignal(number) for number in STOP_SIGNALS}
        try:
            super()._run_subcommand(subcommand)
        except (KeyboardInterrupt, SystemExit):  # Lightning exits on both
            stop = next((c for c in self.trainer.callbacks if isinstance(c, SignalStop)), None)
            if stop is None or stop.signal is None:
                raise
            raise Interrupted(stop.signal, self._stopped(stop)) from None
        except Exception:
            if self.recorded:  # Lightning has ended its MLflow runs FAILED
                self._record("failed")
            raise
        finally:
            for number, handler in handlers.items():
                if handler is not None:
                    set_handler(number, handler)

    def _stopped(self, stop: SignalStop) -> str:
        """Mark the fit's MLflow runs KILLED and its record (``fingerprint.json``) killed; the
        line that says where it stopped."""
        runs = mark_killed(self.trainer)
        if self.fingerprint is not None:
            self._record(
                "killed", checkpoint=None if stop.checkpoint is None else str(stop.checkpoint)
            )
        name = signal.Signals(stop.signal).name
        where = (
            f"checkpoint {stop.checkpoint} (resume with the same command and --ckpt_path last)"
            if stop.checkpoint is not None
            else "no checkpoint of this step (the last periodic one, if any, resumes)"
        )
        killed = f"; MLflow run {', '.join(runs)} marked KILLED" if runs else ""
        return f"stopped by {name} at step {self.trainer.global_step}: {where}{killed}"

    def _run_id(self) -> str | None:
        loggers = mlflow_loggers(self.trainer)
        return loggers[0].run_id if loggers else None

    def before_predict(self) -> None:
        settings = self.config["predict"]
        if not getattr(self.model, "per_frame", False):
            raise ValueError(
                "predict renders a dynamic run (fgat.modules.DynamicModule); the config's model "
                f"is {type(self.model).__name__}"
            )
        if settings["times"] is not None:
            times = predict_times(settings["times"])
            self.datamodule.setup("predict")  # the scene: the size of each volume rendered
            shape = self.datamodule.scene.volume_shape
            writer = next(c for c in self.trainer.callbacks if isinstance(c, VolumeSeriesWriter))
            out = Path(settings["out"]) if settings["out"] else writer.target(self.trainer)
            check_times_memory(settings["times"], len(times), math.prod(shape) * 4)
            check_times_disk(settings["times"], len(times), shape, out)
            self.datamodule.predict_times = times
        for callback in self.trainer.callbacks:
            if isinstance(callback, VolumeSeriesWriter):
                callback.path, callback.overwrite = (
                    settings["out"] or callback.path,
                    settings["overwrite"],
                )

    def _instantiate_trainer(self, config, callbacks):
        settings = self.config[self.subcommand]
        root = Path(config.get("default_root_dir") or DEFAULT_ROOT)
        config["default_root_dir"] = str(root)
        if self.subcommand == "fit":  # the inputs' sizes were checked as the data was built
            self.fingerprint = fingerprint(self.resolved())
            checkpoint = settings["ckpt_path"]
            if explicit_checkpoint(checkpoint):  # before the tracking store is opened
                check_resume(str(checkpoint), Path(checkpoint), self.fingerprint)
        if config.get("logger") in (None, True):
            mlflow = settings["mlflow"]
            # seed_everything also seeds MLflow's random run names: every run would get the same one
            stage = "dynamic" if getattr(self.model, "per_frame", False) else "static"
            run_name = (
                mlflow["run_name"] or f"{self.subcommand}-{stage}-{time.strftime('%Y%m%d-%H%M%S')}"
            )
            uri = self.uri = tracking_uri(mlflow["tracking_uri"])
            artifacts = Path("mlruns").absolute()  # MLflow's default artifact root
            if sqlite_file(uri) is not None and not artifacts.exists():
                self.new_artifacts = artifacts
            check_tracking_uri(uri, mlflow["experiment"])
            tags = (
                None
                if self.fingerprint is None
                else {
                    FINGERPRINT: self.fingerprint.digest,
                    RUN_FOLDER: str(root.resolve()),
                    PID: str(os.getpid()),
                    HOST: process_fields()["host"],
                }
            )
            config["logger"] = MLFlowLogger(
                experiment_name=mlflow["experiment"],
                run_name=run_name,
                tracking_uri=uri,
                log_model=False,
                tags=tags,
            )
        given = list(config.get("callbacks") or []) + list(callbacks)
        present = [type(c) for c in given]
        if not any(isinstance(c, ModelCheckpoint) for c in given):
            callbacks.append(
                StepCheckpoint(
                    dirpath=root / "checkpoints",
                    every_n_train_steps=settings["checkpoint_every"],
                    save_last=True,
                    save_top_k=0,
                    # one last.ckpt per folder: a run started afresh there (a recipe's --refit)
                    # replaces it instead of leaving it beside a last-v1.ckpt for readers of
                    # last.ckpt to take
                    enable_version_counter=False,
                )
            )
        plugins = config.get("plugins") or []
        plugins = list(plugins) if isinstance(plugins, (list, tuple)) else [plugins]
        if not any(isinstance(plugin, TorchCheckpointIO) for plugin in plugins):
            config["plugins"] = [*plugins, AtomicCheckpointIO()]
        if self.fingerprint is not None:
            callbacks.append(CheckpointFingerprint(self.fingerprint))
        for extra in (
            FitCost,
            ReconstructionArtifacts,
            VolumeSeriesWriter,
            MLflowResume,
            SignalStop,
            MonitorStop,
        ):
            if extra not in present:
                callbacks.append(extra())
        return super()._instantiate_trainer(config, callbacks)


def remove_run_artifacts(artifacts: Path, run: str | None) -> None:
    """Remove ``artifacts/<experiment>/<run>`` of MLflow's artifact folder, then the folders
    that this leaves empty, ``artifacts`` included."""
    if run is not None:
        for folder in artifacts.glob(f"*/{run}"):
            shutil.rmtree(folder, ignore_errors=True)
    for folder in sorted(artifacts.glob("*"), reverse=True) + [artifacts]:
        with contextlib.suppress(OSError):
            folder.rmdir()


class FitCost(Callback):
    """Before the first step of a fit: its estimated time and peak memory
    (:func:`fgat.recon.costs.static_fit_cost`, :func:`fgat.recon.costs.dynamic_fit_cost`, calibrated
    on this machine), the options that reduce them, printed and logged as MLflow params
    (``cost/seconds``, ``cost/peak_bytes``, ...)."""

    def __init__(self) -> None:
        self.started = time.perf_counter()  # with the trainer: its set-up counts as the fit's

    def on_fit_start(self, trainer, pl_module) -> None:
        engine = getattr(pl_module, "engine", None)
        dynamic = getattr(pl_module, "per_frame", False)
        if engine is None or (dynamic and pl_module.scene.n_frames == 1):
            return
        total = trainer.max_steps if trainer.max_steps >= 0 else trainer.estimated_stepping_batches
        if not math.isfinite(total):
            return
        setup_s = time.perf_counter() - self.started
        estimate = (costs.dynamic_fit_cost if dynamic else costs.static_fit_cost)(
            engine, total, setup_s
        )
        for line in estimate.lines():
            rank_zero_info(f"fgat: {line}")
        for logger in mlflow_loggers(trainer):
            logger.log_hyperparams(estimate.params())


CHECKPOINT_KEYWORDS = ("last", "best", "hpc", "registry")
"""``--ckpt_path`` values Lightning resolves itself (to a checkpoint of the run's own folders)."""

FINGERPRINT_KEY = "fgat_fingerprint"
"""The entry of a checkpoint holding the fingerprint of the run that saved it (digest and
canonical configuration, :class:`~fgat.app.fingerprint.Fingerprint`)."""


class CheckpointFingerprint(Callback):
    """Store the run's fingerprint in every checkpoint it saves (``fgat_fingerprint``), so a
    resume from it is checked against the configuration it was made with
    (:func:`check_resume`), wherever the file has been copied."""

    def __init__(self, fp: Fingerprint) -> None:
        self.fp = fp

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        checkpoint[FINGERPRINT_KEY] = {"digest": self.fp.digest, "config": self.fp.config}


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer, through :func:`fgat.io.checkpoints.save_torch_file`: written
    under a temporary name and renamed when whole, a full disk ending the fit with one line
    (the file, the bytes it needs) and no partial file. Remote paths go Lightning's way."""

    def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
        if storage_options is not None or "://" in str(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        save_torch_file(checkpoint, path)


def previous_configuration(content: dict, path: Path) -> tuple[dict, str] | None:
    """The canonical configuration a checkpoint was saved with and where that was read: the
    checkpoint's own fingerprint (:class:`CheckpointFingerprint`), else the record of the run
    folder it lies in (``<folder>/checkpoints/<file>``), else ``None``."""
    stamp = content.get(FINGERPRINT_KEY)
    if isinstance(stamp, dict) and isinstance(stamp.get("config"), dict):
        return stamp["config"], "it was saved by a run that had"
    folder = path.resolve().parent.parent
    record = read_record(folder)
    if record is not None and isinstance(record.get("config"), dict):
        return record["config"], f"the run in {folder} had"
    return None


def hyperparameter_differences(content: dict, config: dict) -> list[str]:
    """The model arguments in which a checkpoint's ``hyper_parameters`` differ from those of a
    canonical configuration (fields only one of them has are left out): the check left for a
    checkpoint saved without a fingerprint."""
    saved = {
        key: value
        for key, value in (content.get("hyper_parameters") or {}).items()
        if not key.startswith("_")
    }
    wanted = (config.get("model") or {}).get("init_args") or {}
    return [
        f"model.init_args.{key} {old!r} -> {new!r}"
        for key, old, new in differing_keys(canonical(saved), wanted)
        if "<unset>" not in (old, new)
    ]


def explicit_checkpoint(checkpoint: str | None) -> bool:
    """Whether ``--ckpt_path`` names a file (not one of Lightning's keywords, nor a URL)."""
    return (
        checkpoint is not None
        and checkpoint not in CHECKPOINT_KEYWORDS
        and "://" not in str(checkpoint)
    )


def check_resume(option: str, path: Path, fp: Fingerprint) -> None:
    """Refuse to resume a fit of ``fp`` from the checkpoint ``path`` (``--ckpt_path option``:
    a file, or ``last`` resolved to one) of another configuration, naming the fields that
    differ; only the training length (:data:`~fgat.app.fingerprint.TRAINING_LENGTH`) may change."""
    content = load_torch_file(path, "--ckpt_path")
    previous = previous_configuration(content, path)
    if previous is not None:
        config, whose = previous
        differences = differing_fields(config, fp.config, ignore=TRAINING_LENGTH)
    else:
        whose = "it was saved by a run that had"
        differences = ", ".join(hyperparameter_differences(content, fp.config))
    if differences:
        named = option if option == str(path) else f"{option} ({path})"
        raise ValueError(
            f"--ckpt_path {named}: {whose} another configuration ({differences}); resume it "
            "with its own configuration (only the training length may change), or start afresh "
            "without --ckpt_path"
        )


class FGATArgumentParser(LightningArgumentParser):
    """LightningCLI's parser, its help as plain text (:class:`FGATHelpFormatter`); once a
    subcommand is parsed, :func:`check_settings` stops what a run would only trip over later,
    before anything is built or loaded."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", FGATHelpFormatter)
        super().__init__(*args, **kwargs)

    def parse_args(self, *args, **kwargs):
        config = super().parse_args(*args, **kwargs)
        if config.get("subcommand") is not None:
            check_settings(config["subcommand"], config[config["subcommand"]])
        return config


def check_settings(subcommand: str, settings) -> None:
    """Check a parsed subcommand's settings (a jsonargparse namespace) in place.

    * ``fit``: ``trainer.max_steps`` and ``trainer.max_epochs`` must let it train (positive, or
      -1: no limit); ``trainer.default_root_dir`` must be a folder fgat can write into.
    * Checkpoints are read as weights only: ``weights_only`` is set to true (false is refused);
      a ``--ckpt_path`` file must be a Lightning checkpoint of the config's model class
      (:func:`check_checkpoint`); ``predict`` needs one.
    * ``predict``: ``--times`` must be normalised times and ``--out`` a new file in an existing
      folder.
    """
    trainer = settings["trainer"]
    if subcommand == "fit":
        require(
            trainer["max_steps"] == -1 or trainer["max_steps"] >= 1,
            "trainer.max_steps",
            trainer["max_steps"],
            "a positive number of steps, or -1 (no limit)",
        )
        require(
            trainer["max_epochs"] in (None, -1) or trainer["max_epochs"] >= 1,
            "trainer.max_epochs",
            trainer["max_epochs"],
            "a positive number of epochs, or -1 (no limit)",
        )
    if trainer["default_root_dir"] is not None:
        check_run_root("trainer.default_root_dir", trainer["default_root_dir"])
    if settings.get("weights_only") is False:
        raise ValueError(
            "--weights_only false: fgat reads checkpoints as weights only, since unpickling other "
            "objects can run code"
        )
    if "weights_only" in settings:
        settings["weights_only"] = True
    checkpoint = settings.get("ckpt_path")
    model = settings.get("model")
    for section in ("model", "data"):
        check_groups_given(section, settings.get(section))
    if checkpoint is not None:
        check_checkpoint(str(checkpoint), model["class_path"] if model is not None else None)
    if subcommand == "predict":
        if checkpoint is None:
            raise ValueError(
                "predict needs --ckpt_path: the checkpoint of a dynamic run "
                "(<root>/checkpoints/last.ckpt)"
            )
        if settings["times"] is not None:
            predict_times(settings["times"])
        if settings["out"] is not None:
            check_output_file(settings["out"], overwrite=settings["overwrite"], option="--out")


def check_groups_given(section: str, component) -> None:
    """A setting of ``component`` (the model or data: class path and init args) that groups
    fields (a dataclass such as ``optics`` or ``densification``) must be a mapping: ``null``
    cannot build it, and switching a group off is one of its fields (``{enabled: false}``)."""
    kind = imported_class(component.get("class_path")) if component is not None else None
    if kind is None:
        return
    try:
        hints = typing.get_type_hints(kind.__init__)
    except (NameError, TypeError):  # an annotation that does not resolve: nothing to check
        return
    for name, value in (component.get("init_args") or {}).items():
        group = hints.get(name)
        if value is None and dataclasses.is_dataclass(group):
            fields = ", ".join(field.name for field in dataclasses.fields(group))
            raise ValueError(
                f"{section}.init_args.{name}: null; expected a mapping of {group.__name__}'s "
                f"fields ({fields})"
            )


def check_run_root(field: str, folder: str | Path) -> None:
    """``folder``, or the nearest folder above it that exists, must be a folder this process can
    write into (:func:`fgat.io.files.check_writable_folder`)."""
    folder = Path(folder)
    existing = next(path for path in (folder, *folder.absolute().parents) if path.exists())
    if not existing.is_dir():
        raise ValueError(f"{field} {folder}: {existing} is a file, not a folder")
    check_writable_folder(existing, f"{field} {folder}")


def check_checkpoint(path: str, model_class: str | None) -> None:
    """A ``--ckpt_path`` file: readable as weights only
    (:func:`fgat.io.checkpoints.load_torch_file`, no code in it runs), a Lightning checkpoint
    holding an fgat fit's state, and of
    ``model_class`` when it records its class. Lightning's keywords (``last``, ...) and URLs
    are left to Lightning."""
    if not explicit_checkpoint(path):
        return
    checkpoint = load_torch_file(path, "--ckpt_path")
    if (
        not isinstance(checkpoint.get("state_dict"), dict)
        or "pytorch-lightning_version" not in checkpoint
    ):
        raise ValueError(
            f"--ckpt_path {path}: not a Lightning checkpoint "
            "(no state_dict / pytorch-lightning_version)"
        )
    saved = (checkpoint.get("hyper_parameters") or {}).get("_class_path")
    fgat_model = str(saved or model_class or "").startswith("fgat.")
    if fgat_model and "reconstruction" not in checkpoint:
        raise ValueError(
            f"--ckpt_path {path}: no fgat reconstruction state in it (a checkpoint of another "
            "program, or one written by hand); give the last.ckpt of an fgat fit"
        )
    if saved is not None and model_class is not None and not same_class(saved, model_class):
        raise ValueError(
            f"--ckpt_path {path} holds a {saved} run, but the config's model is {model_class}: "
            "give a checkpoint of that model (its <root>/checkpoints/last.ckpt)"
        )


def same_class(first: str, second: str) -> bool:
    """Whether two class paths name the same class (``fgat.modules.StaticModule`` and
    ``fgat.app.modules.StaticModule`` do); paths that do not import are compared as text."""
    if first == second:
        return True
    cls = imported_class(first)
    return cls is not None and cls is imported_class(second)


def imported_class(class_path: str | None) -> type | None:
    """The class at the dotted ``class_path``, or ``None`` when it does not import."""
    module, _, name = (class_path or "").rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        return None


PREDICT_TIME_BYTES = 4096
"""Host memory one ``--times`` point costs a predict run besides its volume: its loader item,
the loop's record of it and its row of ``*_times.csv`` (about 2.1 kB measured, doubled for
Lightning's bookkeeping)."""


def times_count(text: str) -> int | None:
    """How many times ``--times`` asks for, read without building them: the count of
    ``start:stop:count``, the items of a comma list; ``None`` when it is neither."""
    parts = text.split(":")
    if len(parts) == 3:
        try:
            return int(parts[2])
        except ValueError:
            return None
    return len([item for item in text.split(",") if item.strip()])


def check_times_memory(text: str, count: int, volume_bytes: int = 0) -> None:
    """Refuse ``--times`` whose ``count`` points need more host memory than there is
    (:data:`PREDICT_TIME_BYTES` each, plus one rendered volume of ``volume_bytes``), before any
    is built."""
    check_memory(
        f"--times {text!r}: {count} time points",
        count * PREDICT_TIME_BYTES + volume_bytes,
        hint="fewer times, or several predict runs over parts of [0, 1]",
    )


def check_times_disk(text: str, count: int, volume_shape: tuple[int, ...], out: Path) -> None:
    """Refuse ``--times`` whose series of ``count`` float32 volumes ``volume_shape`` would not fit
    on the file system of ``out`` (written one volume at a time), before the first is rendered."""

    folder = next(path for path in (out.parent, *out.parent.absolute().parents) if path.exists())
    needed, free = count * math.prod(volume_shape) * 4, shutil.disk_usage(folder).free
    if needed > free:
        raise ValueError(
            f"--times {text!r}: {count} volumes {tuple(volume_shape)} (Z, Y, X) float32 need about "
            f"{format_bytes(needed)} in {out}; its file system has {format_bytes(free)} free "
            "(fewer times, or another --out)"
        )


def predict_times(text: str) -> list[float]:
    """``--times``: normalised times in [0, 1] (``start:stop:count`` or a comma list); their
    number is checked against the memory (:func:`check_times_memory`) before they are built."""
    expected = (
        f"--times {text!r}: expected normalised times in [0, 1] (0 = first frame, 1 = last) as "
        "start:stop:count or a comma list, e.g. 0:1:101"
    )
    count = times_count(text)
    if count is None or count < 1:
        raise ValueError(expected)
    check_times_memory(text, count)
    try:
        times = parse_values(text, "time")
    except ValueError:
        raise ValueError(expected) from None
    if not times or min(times) < 0 or max(times) > 1:
        raise ValueError(expected)
    return times


def parse_error_line(error: BaseException) -> str:
    """One line from jsonargparse's nested parse error: the option's full key, the innermost
    problem and, for an unknown option, the closest valid name."""
    chain = [error]
    while chain[-1].__cause__ is not None or chain[-1].__context__ is not None:
        chain.append(chain[-1].__cause__ or chain[-1].__context__)
    keys, owner = [], None
    for cause in chain:
        line = str(cause).strip().splitlines()[0] if str(cause).strip() else ""
        key = re.match(r'Parser key "([^"]+)":', line)
        given = re.fullmatch(r"Problem with given class_path '([^']+)':", line)
        if key and keys[-1:] != [key.group(1)]:
            keys.append(key.group(1))
        elif given and keys[-1:] != ["init_args"]:
            keys.append("init_args")
            owner = given.group(1)
    lines = [
        re.sub(r'^Parser key "[^"]+":', "", line).strip()
        for line in str(chain[-1]).strip().splitlines()
    ]
    problem = next(
        (line for line in lines if line and not line.startswith("Problem with given")), str(error)
    )
    option = re.fullmatch(r"Option '([^']+)' is not accepted", problem)
    unknown = re.fullmatch(r"unrecognized arguments: (--[\w.]+)\S*.*", problem)
    if option:
        keys.append(option.group(1))
        problem = f"unknown option of {owner}" + did_you_mean(
            option.group(1), class_parameters(owner)
        )
    elif unknown:
        name = unknown.group(1)
        if name in PREDICT_ONLY:
            return (
                f"{', '.join(PREDICT_ONLY[:-1])} and {PREDICT_ONLY[-1]} belong to 'predict' "
                f"(render a dynamic run at chosen times); {name} is no option of this subcommand"
            )
        trainer = [f"--trainer.{n}" for n in class_parameters("lightning.pytorch.Trainer")]
        candidates = trainer if name.startswith("--trainer.") else []
        return f"{name}: unknown option" + did_you_mean(name, candidates)
    elif isinstance(chain[-1], (ImportError, AttributeError)) and keys[-1:] == ["init_args"]:
        keys[-1] = "class_path"
        problem = f"cannot import {owner} ({problem})"
    else:
        problem = re.sub(r"<class '(?:[\w.]+\.)?(\w+)'>", r"\1", problem)
        problem = re.sub(r"^Expected an? ", "expected ", problem).replace(". Got value: ", ", got ")
    return f"--{'.'.join(keys)}: {problem}" if keys else problem


def class_parameters(class_path: str | None) -> list[str]:
    """The constructor parameters of the class at ``class_path`` (none if it does not import)."""
    cls = imported_class(class_path)
    if cls is None:
        return []
    return [
        p for p in inspect.signature(cls.__init__).parameters if p not in ("self", "args", "kwargs")
    ]


def did_you_mean(name: str, candidates: list[str]) -> str:
    """``"; did you mean <closest>?"``, or nothing when no candidate is close."""
    close = difflib.get_close_matches(name, candidates, n=1)
    return f"; did you mean {close[0]}?" if close else ""


def user_error(error: Exception) -> Exception:
    """The error to show for what stopped LightningCLI: a parse error as one line, the error a
    model or data class raised (jsonargparse wraps it in its "Union subtypes" report), a
    Lightning misconfiguration as a ValueError; anything else unchanged."""
    if isinstance(error, ArgumentError):
        return ValueError(parse_error_line(error))
    if isinstance(error, MisconfigurationException):
        return ValueError(str(error).strip().splitlines()[0])
    if isinstance(error, ValueError) and str(error).startswith(
        "Does not validate against any of the Union"
    ):
        inner = error
        while inner.__cause__ is not None:
            inner = inner.__cause__
        return inner
    return error


CLI_OPTIONS = {
    "subclass_mode_model": True,
    "subclass_mode_data": True,
    "save_config_callback": MLflowSaveConfig,
    "parser_class": FGATArgumentParser,
    "parser_kwargs": {
        "parser_mode": "omegaconf+",
        "prog": "python -m fgat",
        "exit_on_error": False,
    },
    "auto_configure_optimizers": False,
}


QUIET_WARNINGS = (
    # torch deprecates an API Lightning's own code still uses
    (FutureWarning, r"`isinstance\(treespec, LeafSpec\)` is deprecated"),
    # a checkpoint resumed from another folder: fgat keeps no best/top-k checkpoints to reload
    (UserWarning, r"The dirpath has changed from"),
    # predict serves a plain list of times; the writer needs no batch indices
    (UserWarning, r"Couldn't infer the batch indices"),
)
"""``(category, message regex)`` of library warnings the user can do nothing about."""

QUIET_LOGGERS = {
    "lightning.fabric.utilities.seed": logging.WARNING,  # "Seed set to 0": the config says it
    "mlflow.store.db.utils": logging.WARNING,  # "Creating initial MLflow database tables..."
}
"""Library loggers whose INFO lines tell the user nothing to do, with the level they keep."""


class _DropAdvert(logging.Filter):
    """Drop Lightning's "Tip: ... try installing litlogger" line (an advertisement)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "litlogger" not in str(record.msg)


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """A warning as one line, ``fgat: warning: <message> (<Category>)``, without the source line
    of the library that raised it."""
    text = " ".join(str(message).split())
    return f"fgat: warning: {text} ({category.__name__})\n"


def quiet_library_noise() -> None:
    """Silence what a clean run prints that the user cannot act on (:data:`QUIET_WARNINGS`,
    :data:`QUIET_LOGGERS`, Lightning's litlogger advertisement), each by its message or logger;
    every other warning still shows, as one line (:func:`_one_line_warning`)."""
    for category, message in QUIET_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category)
    for name, level in QUIET_LOGGERS.items():
        logging.getLogger(name).setLevel(level)
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        rank_zero = logging.getLogger(name)  # rank_zero_info logs to the one imported last
        if not any(isinstance(f, _DropAdvert) for f in rank_zero.filters):
            rank_zero.addFilter(_DropAdvert())
    warnings.formatwarning = _one_line_warning


def _cli(cli_class: type[FGATCLI], args: list[str] | None) -> None:
    """Build ``cli_class`` over ``args`` (``None``: ``sys.argv``) with fgat's options; bad settings
    end with one line (:func:`user_error`) before anything is built or computed."""
    quiet_library_noise()
    saved = sys.argv
    if args is not None:
        sys.argv = sys.argv[:1]  # a calling script's own options are not the CLI's
    try:
        check_config_files(saved[1:] if args is None else args)
        cli_class(LightningModule, LightningDataModule, args=args, **CLI_OPTIONS)
    except (ArgumentError, MisconfigurationException, ValueError) as error:
        shown = user_error(error)
        if shown is error:
            raise
        raise shown from None
    finally:
        sys.argv = saved


def run(args: list[str] | None = None) -> None:
    """Run a LightningCLI subcommand with ``args`` (without the program name; ``None``:
    ``sys.argv``); ``--help`` prints the full help."""
    _cli(FGATCLI, args)


class _Resolved(Exception):
    """Raised by :class:`_ResolveOnly` with the resolved configuration, before any class is
    built."""

    def __init__(self, config: dict) -> None:
        super().__init__("resolved")
        self.config = config


class _ResolveOnly(FGATCLI):
    def before_instantiate_classes(self) -> None:
        raise _Resolved(self.resolved())


def resolved_config(args: list[str]) -> dict:
    """The configuration a LightningCLI subcommand would run with (config files, defaults and
    overrides resolved, and checked as :func:`run` checks them), as a plain dict, without building
    the model, data or trainer."""
    try:
        _cli(_ResolveOnly, args)
    except _Resolved as resolved:
        return resolved.config
    raise RuntimeError("the configuration was not resolved")  # _ResolveOnly always raises
