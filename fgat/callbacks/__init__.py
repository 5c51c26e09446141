"""Lightning callbacks: plateau and held-out stopping, checkpoints, artifacts, MLflow config
logging and resumed runs, stopping on a signal."""

from fgat.callbacks.artifacts import ReconstructionArtifacts, VolumeSeriesWriter
from fgat.callbacks.interrupt import SignalStop
from fgat.callbacks.mlflow import MLflowResume, MLflowSaveConfig
from fgat.callbacks.schedule import HoldoutStopping, PlateauStopping, StepCheckpoint

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
