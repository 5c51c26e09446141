"""Logging the resolved LightningCLI config to MLflow."""

from __future__ import annotations

from lightning.pytorch.cli import SaveConfigCallback
from lightning.pytorch.loggers import MLFlowLogger


def mlflow_loggers(trainer) -> list[MLFlowLogger]:
    return [logger for logger in trainer.loggers if isinstance(logger, MLFlowLogger)]


class MLflowSaveConfig(SaveConfigCallback):
    """Store the resolved config as ``config.yaml`` in every MLflow run of the trainer.

    Lightning's own callback writes into the logger's ``log_dir``, which an MLflow logger on a
    SQLite store does not have; this one logs the text as an MLflow artifact instead.
    """

    def setup(self, trainer, pl_module, stage: str) -> None:
        if self.already_saved or not trainer.is_global_zero:
            return
        text = self.parser.dump(self.config, skip_none=False)
        for logger in mlflow_loggers(trainer):
            logger.experiment.log_text(logger.run_id, text, "config.yaml")
        self.already_saved = True
