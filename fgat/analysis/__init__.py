"""Downstream analysis of reconstructed volumes (plain NumPy): temporal interpolation and
kymographs (Fig. S12)."""

from fgat.analysis.temporal import cubic_interpolation, kymograph, sample_and_hold

__all__ = ["cubic_interpolation", "kymograph", "sample_and_hold"]
