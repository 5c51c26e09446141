"""The 4DGAT reconstruction as plain PyTorch objects (no Lightning): a :class:`Scene`, the static
stage (:class:`StaticReconstruction`) and the dynamic stage (:class:`DynamicReconstruction`),
each with ``step()``, ``evaluate()`` and ``state_dict()``."""

from fgat.reconstruction.dynamic import (
    DynamicReconstruction,
    DynamicSettings,
    StaticResult,
    load_static,
)
from fgat.reconstruction.plateau import HoldoutStop, Plateau
from fgat.reconstruction.scene import Scene, phantom_scene
from fgat.reconstruction.static import StaticReconstruction, StaticSettings, StepResult

__all__ = [
    "DynamicReconstruction",
    "DynamicSettings",
    "HoldoutStop",
    "Plateau",
    "Scene",
    "StaticReconstruction",
    "StaticResult",
    "StaticSettings",
    "StepResult",
    "load_static",
    "phantom_scene",
]
