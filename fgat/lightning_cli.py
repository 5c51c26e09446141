"""``python -m fgat fit|validate|test|predict``: LightningCLI with fgat's defaults.

* Model and data classes come from the config (``model.class_path``, ``data.class_path``);
  every field can be overridden on the command line (``--model.init_args.lr_means=0.01``).
  Configs are parsed in omegaconf+ mode: interpolations see command-line overrides.
* MLflow is the logger unless the config sets ``trainer.logger``: experiment ``--mlflow.experiment``,
  tracking URI ``--mlflow.tracking_uri``, else ``MLFLOW_TRACKING_URI``, else ``sqlite:///mlflow.db``.
* Checkpoints go to ``<trainer.default_root_dir>/checkpoints`` (``last.ckpt`` every
  ``--checkpoint_every`` steps and at the end), so ``--ckpt_path last`` resumes a killed or
  finished run.
* The artifact callbacks are always attached, and densification to the static stage.
* ``predict`` renders a dynamic run at ``--times`` (normalised sequence times: 0 the first
  frame, 1 the last; ``start:stop:count`` or a comma list; default the frames' times) into one
  OME-TIFF ``(T, Z, Y, X)`` at ``--out`` (default ``<default_root_dir>/predictions/volumes.ome.tif``).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from lightning.pytorch import LightningDataModule, LightningModule
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import MLFlowLogger

from fgat.callbacks import Densification, MLflowSaveConfig, ReconstructionArtifacts, StepCheckpoint, VolumeSeriesWriter
from fgat.io import parse_values

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"


def tracking_uri(configured: str | None) -> str:
    """The config's URI, else ``MLFLOW_TRACKING_URI``, else a SQLite file in the working directory."""
    return configured or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_TRACKING_URI


class FGATCLI(LightningCLI):
    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument("--mlflow.experiment", type=str, default="fgat", help="MLflow experiment name")
        parser.add_argument("--mlflow.tracking_uri", type=str | None, default=None,
                            help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)")
        parser.add_argument("--mlflow.run_name", type=str | None, default=None,
                            help="MLflow run name (default <subcommand>-<static|dynamic>-<date>-<time>)")
        parser.add_argument("--checkpoint_every", type=int, default=100, help="save last.ckpt every N steps")
        parser.add_argument("--times", type=str | None, default=None,
                            help="predict: normalised times (0 = first frame, 1 = last), start:stop:count or a list")
        parser.add_argument("--out", type=str | None, default=None,
                            help="predict: OME-TIFF of the rendered volumes (T, Z, Y, X)")

    def before_fit(self) -> None:
        settings = self.config["fit"]
        if settings["times"] is not None or settings["out"] is not None:
            raise ValueError("--times and --out belong to 'predict' (render a dynamic run at chosen times), not 'fit'")

    def before_predict(self) -> None:
        settings = self.config["predict"]
        if not getattr(self.model, "per_frame", False):
            raise ValueError(f"predict renders a dynamic run (fgat.modules.DynamicModule); the config's model is "
                             f"{type(self.model).__name__}")
        if settings["times"] is not None:
            times = parse_values(settings["times"], "time")
            if not times or min(times) < 0 or max(times) > 1:
                raise ValueError(f"--times {settings['times']!r}: expected normalised times in [0, 1] "
                                 "(0 = first frame, 1 = last), e.g. 0:1:101")
            self.datamodule.predict_times = times
        for callback in self.trainer.callbacks:
            if isinstance(callback, VolumeSeriesWriter) and settings["out"] is not None:
                callback.path = settings["out"]

    def _instantiate_trainer(self, config, callbacks):
        settings = self.config[self.subcommand]
        root = Path(config.get("default_root_dir") or "runs/fgat")
        config["default_root_dir"] = str(root)
        if config.get("logger") in (None, True):
            mlflow = settings["mlflow"]
            # seed_everything also seeds MLflow's random run names: every run would get the same one
            stage = "dynamic" if getattr(self.model, "per_frame", False) else "static"
            run_name = mlflow["run_name"] or f"{self.subcommand}-{stage}-{time.strftime('%Y%m%d-%H%M%S')}"
            config["logger"] = MLFlowLogger(experiment_name=mlflow["experiment"], run_name=run_name,
                                            tracking_uri=tracking_uri(mlflow["tracking_uri"]), log_model=False)
        given = list(config.get("callbacks") or []) + list(callbacks)
        present = [type(c) for c in given]
        if not any(isinstance(c, ModelCheckpoint) for c in given):
            callbacks.append(StepCheckpoint(dirpath=root / "checkpoints",
                                            every_n_train_steps=settings["checkpoint_every"], save_last=True,
                                            save_top_k=0))
        extras = [ReconstructionArtifacts, VolumeSeriesWriter]
        if hasattr(self.model, "densification"):  # the static stage
            extras.insert(0, Densification)
        for extra in extras:
            if extra not in present:
                callbacks.append(extra())
        return super()._instantiate_trainer(config, callbacks)


def run(args: list[str] | None = None) -> None:
    """Run a LightningCLI subcommand with ``args`` (without the program name; ``None``: ``sys.argv``)."""
    saved = sys.argv
    if args is not None:
        sys.argv = sys.argv[:1]  # a calling script's own options are not the CLI's
    try:
        FGATCLI(LightningModule, LightningDataModule, subclass_mode_model=True, subclass_mode_data=True,
                save_config_callback=MLflowSaveConfig,
                parser_kwargs={"parser_mode": "omegaconf+", "prog": "python -m fgat"}, args=args,
                auto_configure_optimizers=False)
    finally:
        sys.argv = saved
