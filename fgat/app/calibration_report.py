"""Writing a calibration folder from a lattice fit, with its report (``lattice.yaml``)
and overlay figure (``overlay.png``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgat._core.conventions import VIEW_ORDER
from fgat.instrument.calibration import Calibration, save_calibration
from fgat.instrument.camera import CameraModel
from fgat.instrument.lattice import LatticeFit, LatticeQuality


def write_calibration(
    fit: LatticeFit,
    folder,
    image: np.ndarray,
    source: str,
    *,
    gains: np.ndarray | None = None,
    gains_source: str | None = None,
    camera: CameraModel | None = None,
    camera_source: str | None = None,
    depth_axis: str = "up",
    quality: LatticeQuality | None = None,
) -> dict[str, Path]:
    """Write a calibration folder from a lattice fit: ``lattice.yaml`` (the fit's report:
    centre, pitch, rotation, per-view residuals and missing views, the image it came from and
    the fit's ``quality`` (:meth:`LatticeQuality.record`); not read back), ``overlay.png`` (the
    image with each view's circle, number and gain, and the hot pixels) and, by
    :func:`save_calibration`, ``centers.csv``, the camera's maps and ``calibration.yaml``.
    Returns the paths by name."""
    import yaml  # loaded when a file is read or written: keeps start-up fast

    from fgat.io.files import atomic_path  # imported when used: keeps start-up fast
    from fgat.viz.optics import plot_calibration_overlay  # imported when used: keeps start-up fast

    calibration = Calibration(
        centers=fit.centers,
        lattice=fit.lattice,
        residuals=fit.residuals,
        gains=gains,
        camera=camera,
        depth_axis=depth_axis,
        source=source,
        gains_source=gains_source,
        camera_source=camera_source,
    )
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {name: folder / name for name in ("lattice.yaml", "overlay.png")}
    lattice = fit.lattice
    record = {
        "source": source,
        "n_lenslets": len(fit.centers),
        "center_px": [float(v) for v in lattice.center],
        "pitch_px": float(lattice.pitch),
        "rotation_deg": float(lattice.rotation_deg),
        "residuals_px": [round(float(r), 4) for r in fit.residuals],
        "missing_views": [int(v) for v in np.flatnonzero(fit.missing)],
        "quality": None if quality is None else quality.record(),
        "view_order": VIEW_ORDER,
    }
    with atomic_path(paths["lattice.yaml"]) as temporary:
        temporary.write_text(yaml.safe_dump(record, sort_keys=False))
    plot_calibration_overlay(
        image,
        fit.centers,
        0.45 * lattice.pitch,
        paths["overlay.png"],
        gains=gains,
        hot_pixels=None if camera is None else camera.hot_pixels,
    )
    return {**paths, **save_calibration(calibration, folder)}
