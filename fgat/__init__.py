"""fgat: 4DGAT reconstruction of Fourier light-field microscopy (FLFM) volumes.

The physics lives in :mod:`fgat.optics` (design relations, Zernike pupil, JPGM PSF generator,
forward operator) and imports neither Lightning nor MLflow.
"""

__version__ = "0.1.0"
