"""Figures (matplotlib), by subject: volumes and their projections, optics, calibration and
analysis. Every figure carries its units and colour bars."""
