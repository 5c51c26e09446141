"""Lightning callbacks: densification, plateau stopping, checkpoints, artifacts, MLflow config logging and resumed runs."""

from fgat.callbacks.artifacts import ReconstructionArtifacts, VolumeSeriesWriter
from fgat.callbacks.mlflow import MLflowResume, MLflowSaveConfig
from fgat.callbacks.schedule import Densification, PlateauStopping, StepCheckpoint

__all__ = ["Densification", "MLflowResume", "MLflowSaveConfig", "PlateauStopping", "ReconstructionArtifacts", "StepCheckpoint",
           "VolumeSeriesWriter"]
