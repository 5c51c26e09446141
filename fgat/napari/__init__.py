"""fgat in napari (``pip install -e ".[napari]"``): a reader for every file and folder fgat
writes, and dock widgets that calibrate, deconvolve and fit from the viewer.

The plugin's manifest is ``napari.yaml`` beside this module (npe2). This is the top layer of the
package: it may import every layer below it, and nothing imports it.
"""
