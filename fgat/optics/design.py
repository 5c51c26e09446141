"""FLFM design relations (Supplementary Note S1, Guo et al. 2019).

A Fourier light-field microscope places a microlens array (MLA) in the back focal plane of a
Fourier lens of focal length ``f_FL`` that relays the objective pupil; the camera sits one MLA
focal length ``f_ML`` behind the array. These closed-form relations give the nominal design
quantities of Table S1 from the objective (magnification ``M``, numerical aperture ``NA``) and
the fixed detection module.
"""

from __future__ import annotations

import math
import re
from decimal import ROUND_HALF_UP, Decimal


def _require_positive(**values: float) -> None:
    for name, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def flfm_design(
    magnification: float,
    na: float,
    *,
    wavelength_um: float = 0.51,
    f_fourier_mm: float = 300.0,
    f_mla_mm: float = 100.0,
    mla_pitch_mm: float = 4.0,
    pixel_um: float = 6.5,
) -> dict[str, float]:
    """Nominal design values of an FLFM system (Eq. S1 and the relations of Table S1).

    Parameters
    ----------
    magnification : float
        Objective magnification ``M`` (with its design tube lens).
    na : float
        Objective numerical aperture.
    wavelength_um : float
        Emission wavelength in micrometres.
    f_fourier_mm, f_mla_mm : float
        Focal lengths of the Fourier lens and of the microlenses, in millimetres.
    mla_pitch_mm : float
        Microlens pitch (and outer-lenslet radial displacement), in millimetres.
    pixel_um : float
        Camera pixel pitch in micrometres.

    Returns
    -------
    dict
        ``na_over_m``; ``pupil_diameter_mm`` ``D = 2 NA f_FL / M`` (Eq. S1);
        ``lenslets_across_pupil`` ``N = D / pitch``; ``total_magnification``
        ``M_T = M f_ML / f_FL``; ``effective_pixel_um`` ``pixel / M_T``; ``fov_um``
        ``pitch / M_T``; ``lateral_resolution_um`` ``lambda N / (2 NA)``;
        ``axial_resolution_um`` ``lambda N^2 / (4 NA^2)``; ``dof_um``
        ``2 lambda N^2 / NA^2 + 2 N pixel / (M_T NA)``.
    """
    _require_positive(
        magnification=magnification,
        na=na,
        wavelength_um=wavelength_um,
        f_fourier_mm=f_fourier_mm,
        f_mla_mm=f_mla_mm,
        mla_pitch_mm=mla_pitch_mm,
        pixel_um=pixel_um,
    )
    pupil_mm = 2.0 * na * f_fourier_mm / magnification
    n_across = pupil_mm / mla_pitch_mm
    m_total = magnification * f_mla_mm / f_fourier_mm
    return {
        "na_over_m": na / magnification,
        "pupil_diameter_mm": pupil_mm,
        "lenslets_across_pupil": n_across,
        "total_magnification": m_total,
        "effective_pixel_um": pixel_um / m_total,
        "fov_um": mla_pitch_mm * 1000.0 / m_total,
        "lateral_resolution_um": wavelength_um * n_across / (2.0 * na),
        "axial_resolution_um": wavelength_um * n_across**2 / (4.0 * na**2),
        "dof_um": 2.0 * wavelength_um * n_across**2 / na**2
        + 2.0 * n_across * pixel_um / (m_total * na),
    }


_OBJECTIVE = re.compile(r"^\s*(\d+(?:\.\d*)?)\s*[xX]\s*/\s*(\d*\.?\d+)\s*$")
MAX_IMMERSION_INDEX = 1.78
"""The highest refractive index of an objective's immersion medium (the 1.78 liquid of NA 1.7
TIRF objectives): ``NA = n sin(theta)`` stays below it."""


def parse_objective(text: str) -> tuple[float, float]:
    """Parse an objective written as ``"20x/0.45"`` into ``(magnification, na)``; an NA at or
    above :data:`MAX_IMMERSION_INDEX` is refused (:func:`flfm_design` checks the rest)."""
    match = _OBJECTIVE.match(text)
    if match is None:
        raise ValueError(
            f"objective {text!r} is not of the form MAGx/NA, e.g. '20x/0.45' or '60x/1.25'"
        )
    magnification, na = float(match.group(1)), float(match.group(2))
    if na >= MAX_IMMERSION_INDEX:
        raise ValueError(
            f"objective {text!r}: expected NA < {MAX_IMMERSION_INDEX} (NA = n sin(theta) stays "
            "below the immersion index n)"
        )
    return magnification, na


# Column labels and printed decimals of Table S1.
TABLE_S1_FORMAT = {
    "na_over_m": ("NA/M", 5),
    "pupil_diameter_mm": ("D_pupil (mm)", 2),
    "total_magnification": ("M_T", 3),
    "effective_pixel_um": ("p_eff (um)", 4),
    "fov_um": ("FOV (um)", 0),
    "lateral_resolution_um": ("R_xy (um)", 4),
    "axial_resolution_um": ("R_z (um)", 4),
    "dof_um": ("DOF (um)", 1),
}


def round_half_up(value: float, decimals: int) -> str:
    """Decimal string of ``value`` rounded half away from zero, as tables are printed
    (``0.95625 -> "0.9563"``, where Python's ``format`` would give ``"0.9562"``)."""
    exact = Decimal(f"{value:.12g}")
    return str(exact.quantize(Decimal(1).scaleb(-decimals), rounding=ROUND_HALF_UP))


def format_design_table(rows: dict[str, dict[str, float]]) -> str:
    """Render design dicts (keyed by objective name) as a plain-text table like Table S1."""
    headers = ["Objective"] + [label for label, _ in TABLE_S1_FORMAT.values()]
    body = [
        [name]
        + [round_half_up(design[key], decimals) for key, (_, decimals) in TABLE_S1_FORMAT.items()]
        for name, design in rows.items()
    ]
    widths = [max(len(r[i]) for r in [headers] + body) for i in range(len(headers))]
    lines = ["  ".join(cell.rjust(w) for cell, w in zip(row, widths)) for row in [headers] + body]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
