"""Reading and writing: OME-TIFF and MAT images (:mod:`fgat.io.images`), OME-Zarr series
(:mod:`fgat.io.zarr_series`), YAML (:mod:`fgat.io.yaml_files`), atomic writes and tables
(:mod:`fgat.io.files`) and checkpoints (:mod:`fgat.io.checkpoints`)."""
