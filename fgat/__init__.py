"""fgat: 4DGAT reconstruction of Fourier light-field microscopy (FLFM) volumes.

The physics lives in :mod:`fgat.optics` (design relations, Zernike pupil, JPGM PSF generator,
forward operator), the two reconstruction stages in :mod:`fgat.recon` (plain PyTorch
engines); neither imports Lightning or MLflow. :mod:`fgat.app.modules`, :mod:`fgat.app.datamodules`
and :mod:`fgat.app.callbacks` run the engines as Lightning experiments logged to MLflow.
"""

import sys

__version__ = "0.2.0"

if "torch" not in sys.modules:  # the OpenMP runtime reads its environment when torch loads it
    from fgat._core.threads import configure_threads

    configure_threads()
