"""What both Lightning modules share: typed settings from their arguments (errors named as the
config names them) and logging what an engine step returns."""

from __future__ import annotations

import dataclasses
import math

from lightning.pytorch.utilities import rank_zero_info

from fgat.io.yaml_files import check_fields
from fgat.recon import StepResult
from fgat.recon.names import GAUSSIAN_COUNT, HOLDOUT_LOSS, LOSS


def settings(cls: type, field: str, value):
    """``value`` (an instance of dataclass ``cls``, a dict of its fields, or ``None`` for the
    defaults) as a ``cls``; errors name ``field`` (``model.densification.start must be ...``)."""
    if isinstance(value, cls):
        return value
    check_fields(field, cls, value)
    try:
        return cls(**(value or {}))
    except ValueError as error:
        raise ValueError(f"{field.rsplit('.', 1)[0]}.{error}") from None


def flat_settings(cls: type, hparams) -> object:
    """A ``cls`` from the module arguments of the same names; errors prefixed ``model.``."""
    return settings(
        cls, "model.settings", {f.name: hparams[f.name] for f in dataclasses.fields(cls)}
    )


def plain_hyperparameters(module) -> None:
    """Dataclass-valued hyperparameters as dicts (checkpoints load with ``weights_only=True``)."""
    for key, value in list(module.hparams.items()):
        if dataclasses.is_dataclass(value):
            module.hparams[key] = dataclasses.asdict(value)


def log_step(module, result: StepResult) -> None:
    """``loss/<term>``, ``loss`` on the progress bar, ``gaussians/count``, ``time/<part>_ms`` and
    the step's other metrics (e.g. ``gain/view{v}``) on logging steps (:func:`logging_step`);
    each event once, at the step it happened."""
    module.last_loss = result.losses["total"]
    module.loss_trend.update(module.last_loss)
    module.last_holdout = result.metrics.get(HOLDOUT_LOSS, math.nan)
    if logging_step(module.trainer):
        module.log_dict(
            {
                **{f"loss/{name}": value for name, value in result.losses.items()},
                GAUSSIAN_COUNT: float(result.count),
                **{f"time/{name}": value for name, value in result.timings_ms.items()},
                **result.metrics,
            }
        )
        module.log(LOSS, result.losses["total"], prog_bar=True)
    changes = result.events.get("densification")
    if changes:
        log_event(
            module.loggers,
            {f"gaussians/{key}": value for key, value in changes.items() if key != "count"},
            module.global_step,
        )
        rank_zero_info(
            f"fgat: step {module.global_step}: densification cloned {changes['cloned']:.0f}, "
            f"split {changes['split']:.0f}, pruned {changes['pruned']:.0f} "
            f"-> {changes['count']:.0f} Gaussians"
        )
        if "stopped_at_step" in changes:  # logged as names.DENSIFICATION_STOPPED
            rank_zero_info(
                f"fgat: step {module.global_step}: the Gaussian count has settled "
                "(densification.stable_fraction): densification stops here"
            )
    for name, metrics in result.events.items():
        if name != "densification":
            log_event(module.loggers, metrics, module.global_step)


def logging_step(trainer) -> bool:
    """Whether the loggers write this step's metrics (every ``trainer.log_every_n_steps``, and
    on the last step). Metrics of other steps are not handed to ``self.log`` at all: Lightning
    would drop them, after about 1.5 ms of bookkeeping per call."""
    return trainer._logger_connector.should_update_logs


def log_event(loggers, metrics: dict[str, float], step: int) -> None:
    """Log metrics of a one-off event once, at ``step`` (``self.log`` would repeat the last
    value)."""
    for logger in loggers:
        logger.log_metrics(metrics, step=step)
