"""Lightning callbacks: densification, plateau stopping, checkpoints, artifacts, MLflow config logging."""

from fgat.callbacks.artifacts import ReconstructionArtifacts, VolumeSeriesWriter
from fgat.callbacks.mlflow import MLflowSaveConfig
from fgat.callbacks.schedule import Densification, PlateauStopping, StepCheckpoint

__all__ = ["Densification", "MLflowSaveConfig", "PlateauStopping", "ReconstructionArtifacts", "StepCheckpoint",
           "VolumeSeriesWriter"]
