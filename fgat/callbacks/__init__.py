"""Lightning callbacks: plateau stopping, checkpoints, artifacts, MLflow config logging and resumed
runs."""

from fgat.callbacks.artifacts import ReconstructionArtifacts, VolumeSeriesWriter
from fgat.callbacks.mlflow import MLflowResume, MLflowSaveConfig
from fgat.callbacks.schedule import PlateauStopping, StepCheckpoint

__all__ = [
    "MLflowResume",
    "MLflowSaveConfig",
    "PlateauStopping",
    "ReconstructionArtifacts",
    "StepCheckpoint",
    "VolumeSeriesWriter",
]
