"""A fit run under a caller's :class:`~fgat.app.monitor.Monitor` (the napari Fit widget): its
progress, its stop on request, and where its results went."""

from __future__ import annotations

import lightning.pytorch as pl

from fgat.app.callbacks.mlflow import mlflow_loggers, results_folder
from fgat.app.monitor import active


class MonitorStop(pl.Callback):
    """Report a fit's steps to the monitor of the code that started it
    (:func:`fgat.app.monitor.active`) and stop the fit at the end of the step under way once
    the monitor is cancelled: the fit then ends as one that reached its step budget (its results
    written, its MLflow run finished, ``last.ckpt`` saved), so a cancelled fit leaves a complete
    run. At the end it stores in :attr:`Monitor.outputs <fgat.app.monitor.Monitor>` the results
    folder (``results``), the step reached (``step``) and its MLflow runs (``mlflow``: ``(run
    name, run id, experiment, tracking URI)`` each). On the command line no caller set a
    monitor, and it does nothing.
    """

    def __init__(self) -> None:
        self._monitor = None
        self._bar = None

    def setup(self, trainer, pl_module, stage: str) -> None:
        self._monitor = active()

    def on_train_start(self, trainer, pl_module) -> None:
        if self._monitor is not None and self._monitor.progress is not None:
            total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else None
            self._bar = self._monitor.bar(total=total, desc="fit", unit="step")
            self._bar.update(trainer.global_step)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self._bar is not None:
            self._bar.update(1)
        if self._monitor is not None and self._monitor.cancelled:
            trainer.should_stop = True

    def on_fit_end(self, trainer, pl_module) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        monitor = self._monitor
        if monitor is None:
            return
        runs = []
        for logger in mlflow_loggers(trainer):
            client = logger.experiment
            run = client.get_run(logger.run_id)
            experiment = client.get_experiment(run.info.experiment_id).name
            runs.append((run.info.run_name, logger.run_id, experiment, client.tracking_uri))
        monitor.outputs.update(
            results=results_folder(trainer),
            step=trainer.global_step,
            mlflow=runs,
        )
