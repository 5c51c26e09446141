"""The instrument as measured: the camera model, the lenslet lattice fitted to a calibration
image, calibration records and folders, and the assembly of a measurement into views."""
