"""Anisotropic 3D Gaussians (Note S3.1-S3.2): activations, voxelization, densification.

Plain PyTorch; no training loop.
"""

from fgat.gaussians.voxelize import voxelize

__all__ = ["voxelize"]
