"""The per-view window size of a measurement (from its metadata or its lenslet centres) and
the check of a ground-truth volume against the reconstruction's shape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgat.io.yaml_files import read_yaml
from fgat.optics.lenslets import largest_view_size


def simulation_view_size(measurement: str | Path) -> int | None:
    """The ``view_size`` of the ``params.yaml`` written by ``python -m fgat simulate`` in the
    measurement's folder; ``None`` without one (a ``params.yaml`` of another program is ignored)."""
    params = Path(measurement).parent / "params.yaml"
    if not params.is_file():
        return None
    try:
        content = read_yaml(params, str(params))
    except ValueError:
        return None
    config = content.get("config") if isinstance(content, dict) else None
    size = config.get("view_size") if isinstance(config, dict) else None
    return size if isinstance(size, int) and size >= 1 else None


def choose_view_size(
    view_size: int | None,
    option: str,
    measurement: str | Path,
    truth: tuple[str | Path, tuple[int, ...]] | None,
    centers: np.ndarray,
    sensor_shape: tuple[int, int],
) -> tuple[int, str]:
    """The lateral size ``Y = X`` of the views and of the volume, pixels, and where it came from.

    In order: ``view_size`` (given as ``option``), the ``view_size`` of the simulation that wrote
    the measurement (:func:`simulation_view_size`), the lateral size of the ground truth, the
    largest square between the lenslet centres. A truth thus never sets the size of a measurement
    whose size is known; :func:`check_truth_shape` then refuses a truth of another size.

    Parameters
    ----------
    view_size : int or None
        The size the user gave.
    option : str
        Its name, for the origin (``"data.view_size"``, ``"--view-size"``).
    measurement : str or Path
        The sensor image (its folder may hold the simulation's ``params.yaml``).
    truth : (path, shape) or None
        The ground truth's file and shape ``(..., Y, X)``.
    centers : ndarray
        Lenslet centres ``(V, 2)``, pixels.
    sensor_shape : (int, int)
        Sensor ``(H, W)``, pixels.

    Returns
    -------
    size : int
        Pixels.
    origin : str
        E.g. ``"the simulation's sim/params.yaml"``.
    """
    if view_size is not None:
        return view_size, option
    simulated = simulation_view_size(measurement)
    if simulated is not None:
        return simulated, f"the simulation's {Path(measurement).parent / 'params.yaml'}"
    if truth is not None:
        return truth[1][-1], f"the lateral size of the truth {truth[0]}"
    return largest_view_size(
        centers, sensor_shape
    ), "the largest square between the lenslet centres"


def check_truth_shape(
    source: str, path: str | Path, shape: tuple[int, ...], expected: tuple[int, ...], origin: str
) -> None:
    """Refuse a ground truth whose shape is not the reconstruction's, before anything is computed
    (a truth of another lateral size would otherwise resize the views it is compared with).

    Parameters
    ----------
    source : str
        How the truth was given (``"data.truth"``, ``"--truth"``).
    path : str or Path
        Its file.
    shape : tuple of int
        Its shape ``((T,) Z, Y, X)``.
    expected : tuple of int
        The reconstruction's ``((T,) Z, Y, X)``: frames, PSF depths, view size.
    origin : str
        Where the view size came from (:func:`choose_view_size`).

    Raises
    ------
    ValueError
        ``"--truth t.tif: shape (3, 32, 32) does not match the reconstruction (3, 64, 64) ..."``.
    """
    if tuple(shape) == tuple(expected):
        return
    raise ValueError(
        f"{source} {path}: shape {tuple(shape)} does not match the reconstruction "
        f"{tuple(expected)} (({'T, ' if len(expected) == 4 else ''}Z, Y, X): PSF depths, view "
        f"size {expected[-1]} px from {origin}); give the truth of this measurement, or set the "
        "view size to the truth's if its views are meant to be that size"
    )
