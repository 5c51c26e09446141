"""Lenslet centres files: CSV (row, col per view) and MAT."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgat.instrument.lattice import least_squares_lattice
from fgat.io.files import atomic_path
from fgat.io.images import read_mat
from fgat.optics.lenslets import (
    sort_lenslet_centers,
)

# header -> the CSV columns holding (row, col); x is the column (image axis 1), y the row
CENTER_HEADERS = {"row,col": (0, 1), "col,row": (1, 0), "y,x": (0, 1), "x,y": (1, 0)}


def write_centers(path: str | Path, centers: np.ndarray) -> None:
    """Write lenslet centres ``(V, 2)`` as ``row,col`` CSV (0-based pixels), atomically."""
    lines = ["row,col"] + [
        f"{row:.6f},{col:.6f}" for row, col in np.asarray(centers, dtype=np.float64)
    ]
    with atomic_path(path) as temporary:
        temporary.write_text("\n".join(lines) + "\n")


def read_centers(path: str | Path) -> np.ndarray:
    """Lenslet centres ``(V, 2)`` (row, col), 0-based, from a CSV or a MATLAB ``.mat``.

    A CSV starts with a header naming its columns, ``row,col``, ``col,row``, ``x,y`` or ``y,x``
    (case and spaces ignored; ``x`` is the column, ``y`` the row, both in pixels with the image's
    row 0 at the top), then one line per view; a ``.mat`` holds one ``(V, 2)`` (row, col) array in
    MATLAB's 1-based indices, converted. Every user of centres gets them checked: finite, and
    no two closer than one pixel (each view needs its own lenslet).
    """
    path = Path(path)
    if path.suffix.lower() == ".mat":
        centers = read_mat(path).astype(np.float64) - 1.0
    else:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        try:
            lines = path.read_text(encoding="utf-8-sig").splitlines()
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text (CSV) file of lenslet centres") from None
        if not lines:
            raise ValueError(
                f"{path}: the file is empty; expected a 'row,col' header and one line per view"
            )
        header = lines[0].replace(" ", "").lower()
        if header not in CENTER_HEADERS:
            raise ValueError(
                f"{path}: header {lines[0]!r}; expected 'row,col', 'col,row', 'x,y' or 'y,x' "
                "followed by one line per view"
            )
        if not any(line.strip() for line in lines[1:]):
            raise ValueError(f"{path}: no lenslet centres after the '{lines[0]}' header")
        try:
            centers = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
        except ValueError as error:
            raise ValueError(
                f"{path}: expected one '{header}' line of two numbers per view ({error})"
            ) from None
        if centers.size and centers.shape[1] == 2:
            centers = centers[:, CENTER_HEADERS[header]]
    if (
        centers.ndim != 2
        or centers.shape[1] != 2
        or not len(centers)
        or not np.isfinite(centers).all()
    ):
        raise ValueError(
            f"{path}: expected finite lenslet centres of shape (V, 2), V >= 1, got {centers.shape}"
        )
    distances = np.linalg.norm(centers[:, None] - centers[None], axis=2) + np.diag(
        np.full(len(centers), np.inf)
    )
    if distances.min() < 1:
        i, j = sorted(np.unravel_index(int(np.argmin(distances)), distances.shape))
        raise ValueError(
            f"{path}: centres {i} and {j} ({centers[i, 0]:g}, {centers[i, 1]:g}) and "
            f"({centers[j, 0]:g}, {centers[j, 1]:g}) are less than 1 pixel apart; "
            "each view needs its own lenslet centre"
        )
    check_view_order(centers, str(path))
    return centers


def _lattice_misfit(centers: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: centres more than a quarter pitch from a hexagonal lattice fitted to them
    in the order given."""
    lattice = least_squares_lattice(centers, len(centers), np.ones(len(centers), dtype=bool))
    misfit = np.linalg.norm(centers - lattice.centers(len(centers)), axis=1)
    return misfit > 0.25 * max(lattice.pitch, 1e-9)


def check_view_order(centers: np.ndarray, source: str) -> None:
    """Raise ``ValueError`` naming ``source`` when the centres ``(V, 2)`` (row, col) form a
    hexagonal array listed in another order than fgat's view order (the order of every PSF stack
    fgat makes), which would pair each view with another lenslet's PSF. Centres that form no
    hexagonal array in any order are left to the checks of their geometry."""
    centers = np.asarray(centers, dtype=np.float64)
    if len(centers) < 3 or not _lattice_misfit(centers).any():
        return
    ordered = sort_lenslet_centers(centers)
    if _lattice_misfit(ordered).any():
        return
    v = int(np.flatnonzero(np.any(ordered != centers, axis=1))[0])
    view = int(np.flatnonzero(np.all(ordered == centers[v], axis=1))[0])
    raise ValueError(
        f"{source}: lenslet centres are not in fgat's view order: line {v + 1} "
        f"({centers[v, 0]:g}, {centers[v, 1]:g}) is view {view} (view 0 nearest the array "
        "centre, then ring by ring counter-clockwise from +column); 'python -m fgat calibrate' "
        "writes them in order"
    )
