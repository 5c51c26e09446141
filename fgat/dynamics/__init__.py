"""The dynamic stage's deformation field (Notes S3.3-S3.4): HexPlane features, deformation MLP,
the deformation-application operator and the plane regularisers. Plain PyTorch, with Triton
kernels for the HexPlane features and the deformation on a GPU; no training loop.
"""

from fgat.dynamics.deformation import DeformationField, apply_deformation
from fgat.dynamics.hexplane import HexPlane
from fgat.dynamics.regularizers import (
    plane_l1_to_one,
    plane_regularisers,
    plane_tv,
    temporal_smoothness,
)

__all__ = [
    "DeformationField",
    "HexPlane",
    "apply_deformation",
    "plane_l1_to_one",
    "plane_regularisers",
    "plane_tv",
    "temporal_smoothness",
]
