"""MLflow bookkeeping: the tracking store, the resolved config, and resumed runs."""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import time
from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.cli import SaveConfigCallback
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.utilities import rank_zero_info

from fgat.app.tracking_server import check_database

RESUMED_FROM, RESUMED_BY, FINGERPRINT = (
    "fgat.resumed_from",
    "fgat.resumed_by",
    "fgat.app.fingerprint",
)
RUN_FOLDER, PID, HOST = "fgat.run_folder", "fgat.pid", "fgat.host"


def mlflow_loggers(trainer) -> list[MLFlowLogger]:
    return [logger for logger in trainer.loggers if isinstance(logger, MLFlowLogger)]


def results_folder(trainer) -> Path:
    """``<default_root_dir>/results/<MLflow run id>`` (``.../latest`` without an MLflow logger)."""
    loggers = mlflow_loggers(trainer)
    return (
        Path(trainer.default_root_dir) / "results" / str(loggers[0].run_id if loggers else "latest")
    )


def _store_lock(database: Path) -> Path:
    """The lock file of ``database``: in the system's temporary folder, named by a hash of its
    absolute path (every process of the machine that opens that database takes the same one),
    never beside the user's files, where it would stay."""
    digest = hashlib.sha256(str(database.resolve()).encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"fgat-mlflow-{digest}.lock"


@contextlib.contextmanager
def no_http_retries():
    """MLflow retries an unreachable server for minutes; a set-up check should answer at once."""
    saved = {
        name: os.environ.get(name)
        for name in ("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "MLFLOW_HTTP_REQUEST_TIMEOUT")
    }
    os.environ.update({"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0", "MLFLOW_HTTP_REQUEST_TIMEOUT": "10"})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def check_tracking_uri(uri: str, experiment: str) -> None:
    """Check the tracking store ``uri`` and create (or migrate) it and ``experiment`` once,
    before a run starts: every command that logs (``fit``, ``sweep``, ``pipeline``, the
    recipes) calls it first.

    An unusable URI (unknown scheme, unreachable server, a database in a missing or read-only
    folder, one that is a folder or a file of another kind) fails at once with one line. Runs
    started together on a new SQLite store race on MLflow's schema creation ("table ... already
    exists") and on the experiment's creation; both happen here under a file lock of the
    database (:func:`_store_lock`).
    """
    from filelock import FileLock  # loaded when used: keeps start-up fast

    source = "--mlflow.tracking_uri"
    database = check_database(uri, source)
    lock = (
        contextlib.nullcontext()
        if database is None
        else FileLock(_store_lock(database), timeout=300, mode=0o666)
    )
    import mlflow  # MLflow loaded when used: keeps start-up fast

    try:
        with lock, no_http_retries():
            _get_or_create_experiment(mlflow.MlflowClient(uri), experiment)
    except (
        Exception
    ) as error:  # MLflow raises many types for a bad store (MlflowException, OSError, requests ...)
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ValueError(f"{source} {uri}: cannot open the tracking store ({first})") from None


def delete_run(uri: str, run_id: str) -> None:
    """Move the run ``run_id`` of the store ``uri`` to MLflow's deleted stage (out of the UI and
    of searches, restorable), as far as the store answers: a refused fit leaves no run."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    with contextlib.suppress(Exception), no_http_retries():
        mlflow.MlflowClient(uri).delete_run(run_id)


def _get_or_create_experiment(client, experiment: str) -> str:
    """The id of ``experiment``, created if missing. A tracking server serves runs started
    together on other machines, so another run may create it between the lookup and the
    creation; its ``RESOURCE_ALREADY_EXISTS`` answer means the experiment is there."""
    from mlflow.exceptions import MlflowException  # MLflow loaded when used: keeps start-up fast

    found = client.get_experiment_by_name(experiment)
    if found is not None:
        return found.experiment_id
    try:
        return client.create_experiment(experiment)
    except MlflowException as error:
        if error.error_code != "RESOURCE_ALREADY_EXISTS":
            raise
        return client.get_experiment_by_name(experiment).experiment_id


def finished_fingerprints(uri: str, experiment: str) -> set[str]:
    """The fingerprints (``fgat.app.fingerprint`` tags) of the finished runs of ``experiment``: a
    recipe's trial with one of these has been computed already."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    client = mlflow.MlflowClient(uri)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        return set()
    runs = client.search_runs([found.experiment_id], filter_string="attributes.status = 'FINISHED'")
    return {run.data.tags[FINGERPRINT] for run in runs if FINGERPRINT in run.data.tags}


def continue_history(
    client, previous: str, current: str, step: int, saved_ms: int | None = None
) -> int:
    """Make ``current`` the continuation of the interrupted run ``previous``.

    ``previous`` is marked KILLED if it is still RUNNING (a killed process never ended it), both
    runs are linked by tags (``fgat.resumed_from`` / ``fgat.resumed_by``), and the metric points
    ``previous`` logged before its checkpoint was saved are copied into ``current`` at their
    steps, so the resumed run holds one history without the steps the resume computes again.
    ``saved_ms`` is the checkpoint's save time (ms since the epoch, as MLflow stamps points): the
    points stamped up to it are the ones the checkpoint's state had logged, events at the
    checkpoint's own step included. A checkpoint without it (written by an older fgat) copies
    the points before ``step``, its global step. Returns the number of points copied.
    """
    from mlflow.entities import Metric  # MLflow loaded when used: keeps start-up fast

    run = client.get_run(previous)
    if run.info.status == "RUNNING":
        client.set_terminated(previous, "KILLED")
    client.set_tag(current, RESUMED_FROM, previous)
    client.set_tag(previous, RESUMED_BY, current)
    points = [
        Metric(key, m.value, m.timestamp, m.step)
        for key in run.data.metrics
        for m in client.get_metric_history(previous, key)
        if (m.step < step if saved_ms is None else m.timestamp <= saved_ms)
    ]
    for start in range(0, len(points), 1000):
        client.log_batch(current, metrics=points[start : start + 1000])
    return len(points)


def stamp_ms() -> int:
    """Now in ms since the epoch, as MLflow stamps metric points, once the clock has passed it:
    every point logged before the call is stamped at most this, every later one after it."""
    now = int(time.time() * 1000)
    while int(time.time() * 1000) <= now:
        time.sleep(1e-4)
    return now


def end_orphaned_run(uri: str, run_id: str) -> bool:
    """Mark the MLflow run ``run_id`` of the store at ``uri`` KILLED if it is still RUNNING (its
    process was killed before it could end it); whether it was. A store or run that cannot be
    reached is left as it is."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    try:
        with no_http_retries():
            client = mlflow.MlflowClient(uri)
            if client.get_run(run_id).info.status != "RUNNING":
                return False
            client.set_terminated(run_id, "KILLED")
    except Exception:  # noqa: BLE001 (MLflow raises many types for a missing store or run)
        return False
    return True


def mark_killed(trainer) -> list[str]:
    """Mark the runs of the trainer's MLflow loggers KILLED (Lightning ends an interrupted fit's
    runs FAILED); their ids."""
    ids = []
    for logger in mlflow_loggers(trainer):
        logger.experiment.set_terminated(logger.run_id, "KILLED")
        ids.append(logger.run_id)
    return ids


class MLflowResume(pl.Callback):
    """Link a resumed fit to the run it continues.

    Checkpoints store the MLflow run id; a fit resumed from one (``--ckpt_path``) logs to a new
    run, which :func:`continue_history` makes the continuation of the old one.
    """

    def __init__(self) -> None:
        self.run_id: str | None = None
        self.previous: str | None = None
        self.saved_ms: int | None = None

    def setup(self, trainer, pl_module, stage: str) -> None:
        loggers = mlflow_loggers(trainer)
        self.run_id = loggers[0].run_id if loggers else None

    def state_dict(self) -> dict:
        """Called as a checkpoint is saved: the run, and when (:func:`stamp_ms`)."""
        return {"run_id": self.run_id, "saved_ms": stamp_ms()}

    def load_state_dict(self, state_dict: dict) -> None:
        self.previous, self.saved_ms = state_dict.get("run_id"), state_dict.get("saved_ms")

    def on_train_start(self, trainer, pl_module) -> None:
        loggers = mlflow_loggers(trainer)
        if not loggers or not trainer.is_global_zero or self.previous in (None, self.run_id):
            return
        copied = continue_history(
            loggers[0].experiment, self.previous, self.run_id, trainer.global_step, self.saved_ms
        )
        rank_zero_info(
            f"fgat: resumed at step {trainer.global_step} from MLflow run {self.previous} "
            f"(marked KILLED if it was still running; {copied} earlier metric points copied)"
        )


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
