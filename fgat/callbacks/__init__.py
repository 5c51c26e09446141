"""The Lightning callbacks under the name configs use
(``class_path: fgat.callbacks.PlateauStopping``); the code lives in :mod:`fgat.app.callbacks`."""

from fgat.app.callbacks import (  # noqa: F401
    HoldoutStopping,
    MLflowResume,
    MLflowSaveConfig,
    PlateauStopping,
    ReconstructionArtifacts,
    SignalStop,
    StepCheckpoint,
    VolumeSeriesWriter,
)

__all__ = [
    "HoldoutStopping",
    "MLflowResume",
    "MLflowSaveConfig",
    "PlateauStopping",
    "ReconstructionArtifacts",
    "SignalStop",
    "StepCheckpoint",
    "VolumeSeriesWriter",
]
