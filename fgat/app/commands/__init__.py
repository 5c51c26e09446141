"""The command families of ``python -m fgat``: optics (``design``, ``psf``), data
(``simulate``, ``calibrate``, ``calibrate-depth``, ``deconvolve``) and ``analyze``; the
Lightning commands (``fit``, ``validate``, ``predict``) live in :mod:`fgat.app.lightning_cli`,
``pipeline``, ``sweep`` and ``tracking-server`` in their own modules."""
