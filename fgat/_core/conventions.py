"""Conventions every layer shares: the lenslet view order and the depth-axis orientation
of volumes (and the flip between them).
"""

from __future__ import annotations

import numpy as np

VIEW_ORDER = (
    "view 0 is the lenslet at the array centre (on the optical axis); the others follow in "
    "shells of increasing distance from it (1, sqrt(3), 2, sqrt(7), ... pitches: 6 lenslets "
    "each for the first three), and within a shell by increasing angle atan2(-d_row, d_col) "
    "counted from 5 degrees below the +column direction, i.e. counter-clockwise as the image is "
    "displayed (row 0 at the top); 7 lenslets: centre, right, upper right, upper left, left, "
    "lower left, lower right; an array rotated by less than 30 degrees keeps the numbering of "
    "the unrotated one (fgat.optics.lenslets.hexagonal_offsets), and one calibrated against a "
    "system the numbering of the system's nominal lattice (its mla_orientation and "
    "mla_rotation_deg)"
)
DEPTH_AXES = {
    "up": "Z index k holds the PSF stack's depth k (depths_um[k]; ascending for start:stop:count "
    "ranges, so index 0 is the most negative depth). A positive depth_um is a point farther "
    "from the objective than the native focal plane (fgat's defocus phase z (-2 pi n / lambda) "
    "(1 - cos theta) has the sign of a converging lens and of forward angular-spectrum "
    "propagation), whose image moves towards the array centre in every outer view; so index 0 "
    "is nearest the objective and Z grows away from it (upwards on an inverted microscope)",
    "down": "Z is flipped: index k holds depths_um[Z - 1 - k], so index 0 is the largest depth "
    "of an ascending range, farthest from the objective, and Z grows towards the objective "
    "(downwards on an inverted microscope)",
}


def orient_volume(volume, depth_axis: str):
    """A volume ``(..., Z, Y, X)`` (NumPy array or torch tensor) in fgat's Z order turned to
    ``depth_axis``: unchanged for ``"up"``, Z reversed for ``"down"`` (see :data:`DEPTH_AXES`);
    the depths of the flipped volume's planes are ``depths_um[::-1]``."""
    if depth_axis not in DEPTH_AXES:
        raise ValueError(f"depth_axis must be one of {list(DEPTH_AXES)}, got {depth_axis!r}")
    if len(volume.shape) < 3:
        raise ValueError(f"expected a volume (..., Z, Y, X), got shape {tuple(volume.shape)}")
    if depth_axis == "up":
        return volume
    return np.flip(volume, axis=-3) if isinstance(volume, np.ndarray) else volume.flip(-3)
