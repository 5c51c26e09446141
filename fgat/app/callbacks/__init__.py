"""Lightning callbacks: plateau and held-out stopping, checkpoints, artifacts, MLflow config
logging and resumed runs, stopping on a signal or at a caller's request."""

from fgat.app.callbacks.artifacts import ReconstructionArtifacts, VolumeSeriesWriter
from fgat.app.callbacks.interrupt import SignalStop
from fgat.app.callbacks.mlflow import MLflowResume, MLflowSaveConfig
from fgat.app.callbacks.monitor import MonitorStop
from fgat.app.callbacks.schedule import HoldoutStopping, PlateauStopping, StepCheckpoint

__all__ = [
    "HoldoutStopping",
    "MLflowResume",
    "MLflowSaveConfig",
    "MonitorStop",
    "PlateauStopping",
    "ReconstructionArtifacts",
    "SignalStop",
    "StepCheckpoint",
    "VolumeSeriesWriter",
]
