"""Analysis of the optics and of reconstructed volumes (plain NumPy / PyTorch, no Lightning).

* :mod:`fgat.analysis.temporal`: temporal interpolation and kymographs (Fig. S12);
* :mod:`fgat.optics.crossinfo`, :mod:`fgat.app.crossinfo_tables`: the cross-information
  of the Zernike and lenslet-shift parameters (Notes S4-S5, Tables S2-S5);
* :mod:`fgat.analysis.morphology`: apparent tubule widths from line profiles (Note S8.2);
* :mod:`fgat.analysis.cytometry`: 3D blob detection, marker classes and their fractions
  against a reference count (Notes S8.7-S8.8);
* :mod:`fgat.analysis.tracking`: 3D tracking, speeds, mean squared displacement and the
  anomalous-diffusion exponent (Note S8.9);
* :mod:`fgat.analysis.scales`: the length options of these analyses checked against the voxel
  size and the volume's extent;
* :mod:`fgat.analysis.outputs`: their output folder, checked first, written atomically, left as
  it was by a failed run.
"""

from fgat.analysis.temporal import cubic_interpolation, kymograph, sample_and_hold

__all__ = ["cubic_interpolation", "kymograph", "sample_and_hold"]
