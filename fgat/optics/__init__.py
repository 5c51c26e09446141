"""FLFM optics: design relations, Zernike pupil, JPGM PSF stack, lenslets and forward operator.

Plain PyTorch and NumPy, no training loop: import the submodules directly, e.g.
``from fgat.optics.operator import FLFMOperator``.
"""
