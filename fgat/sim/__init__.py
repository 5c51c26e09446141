"""Synthetic data: phantoms (beads, tubules, cells, moving scenes) and the simulation of FLFM
measurements through the JPGM optics and the camera model."""
