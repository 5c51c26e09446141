"""FLFM system descriptions: the Table S1 objectives on the Note S1 module, and a small system.

A system is a YAML file of the fields of :class:`FLFMSystem`; fgat ships ``20x/0.45``,
``40x/0.90``, ``60x/1.25`` (Table S1) and ``small`` (a CPU-sized system for tests and the
quickstart). :func:`load_system` takes one of these names or the path of a user's YAML file.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from fgat._core.validation import check_number, parse_values
from fgat.io.files import read_text
from fgat.io.yaml_files import yaml_fields
from fgat.optics.design import flfm_design
from fgat.optics.lenslets import lattice_points

LENSLET_SHAPES = ("circle", "hexagon")
ZERNIKE_DISKS = ("pupil", "aperture")
PITCH_CONVENTIONS = {"center": 1.0, "row": 2.0 / math.sqrt(3.0), "corner": math.sqrt(3.0) / 2.0}
"""``mla_pitch_convention`` -> centre-to-centre spacing of neighbouring lenslets per unit of
``mla_pitch_mm``: ``center``, the spacing itself; ``row``, the distance between neighbouring
rows of lenslets (``sqrt(3) / 2`` of the spacing); ``corner``, the corner-to-corner width of a
hexagonal lenslet that tiles the array (``2 / sqrt(3)`` of the spacing, its flat-to-flat
width)."""
MLA_ORIENTATIONS = {"pointy-top": 0.0, "flat-top": 30.0}
"""``mla_orientation`` -> rotation (degrees, counter-clockwise as displayed) of the array from
fgat's lattice, whose neighbours lie along the column axis (the hexagonal cells then stand on
a corner: pointy-top); ``flat-top`` cells have neighbours along the row axis."""


@dataclass(frozen=True)
class FLFMSystem:
    """Optical parameters of an FLFM microscope (Note S1).

    Attributes
    ----------
    name : str
        Label used in logs and tables.
    magnification, na : float
        Objective magnification and numerical aperture.
    immersion_index : float
        Refractive index of the immersion medium (1.0 air, 1.406 silicone oil, 1.518 oil).
    sample_index : float or None
        Refractive index of the sample medium the PSF depths lie in (1.33 water); ``None``: the
        immersion index. It sets the depth dependence of the pupil phase
        (:func:`fgat.optics.propagation.defocus_phase_per_um`). ``na`` may exceed it: the pupil
        points with ``NA rho >= sample_index`` (supercritical angles, evanescent in the sample)
        then carry no light.
    depth_scale : float
        Calibrated factor on the depth dependence of the pupil phase: the JPGM's plane at depth
        ``z`` carries the defocus of ``depth_scale * z`` um in the sample (1: the model as
        designed). Measured from a bead z-stack (:mod:`fgat.optics.depth_scale`, ``python -m
        fgat calibrate-depth``) and applied from a calibration folder by every command that
        reads one.
    wavelength_um : float
        Emission wavelength in micrometres.
    f_fourier_mm, f_mla_mm : float
        Focal lengths of the Fourier lens and of each microlens, millimetres.
    mla_pitch_mm : float
        MLA pitch in mm as the datasheet quotes it, read by ``mla_pitch_convention``; the
        centre-to-centre distance of neighbouring lenslet axes is :attr:`center_pitch_mm`.
    mla_pitch_convention : {"center", "row", "corner"}
        What ``mla_pitch_mm`` measures on the hexagonal array (:data:`PITCH_CONVENTIONS`):
        ``"center"`` (default), the distance between neighbouring lenslet centres; ``"row"``,
        the distance between neighbouring rows of lenslets, ``sqrt(3) / 2`` of it; ``"corner"``,
        the corner-to-corner width of a tiling hexagonal lenslet, ``2 / sqrt(3)`` of it.
        ``python -m fgat calibrate`` measures the centre spacing and names the convention when
        the system's pitch is off by one of these factors.
    mla_orientation : {"pointy-top", "flat-top"}
        Orientation of the hexagonal array on the camera image as displayed (row 0 at the top):
        ``"pointy-top"`` (default), neighbouring lenslets side by side along the columns (rows of
        lenslets run horizontally; hexagonal cells stand on a corner); ``"flat-top"``,
        neighbours stacked along the rows (the array turned by 30 degrees).
    mla_rotation_deg : float
        Further rotation of the array (its mount, or the camera), degrees, counter-clockwise as
        displayed. With ``mla_orientation`` it sets :attr:`lattice_rotation_deg`, the rotation
        of the nominal lattice (:meth:`lenslet_centers_px`, and hence of the hexagonal
        apertures of the PSF model, :func:`fgat.optics.pupil.lattice_angle`, and of
        simulations).
    lenslet_aperture_mm : float
        Lenslet clear-aperture diameter, mm (for hexagonal lenslets the flat-to-flat width,
        whatever ``mla_pitch_convention`` says).
    lenslet_shape : {"circle", "hexagon"}
        Lenslet clear aperture: a disk, or a regular hexagon whose flats face the neighbouring
        lenslets (:func:`fgat.optics.pupil.lenslet_aperture`); with ``lenslet_aperture_mm``
        equal to :attr:`center_pitch_mm` the hexagons tile the array.
    pixel_um : float
        Camera pixel pitch, micrometres.
    sensor_shape : tuple of int
        Camera size ``(H, W)`` in pixels; the optical axis hits pixel ``(H // 2, W // 2)``.
    n_lenslets : int
        Number of lenslets of the hexagonal array inside the pupil.
    crop_radius_px : int
        Half-width ``r`` of the per-view PSF crops (Eq. S12), pixels.
    zernike_disk : {"pupil", "aperture"}
        The unit disk of the Zernike basis (Eq. S4), centred on the central lenslet's axis:
        ``"pupil"``, the objective-pupil image at the MLA plane (radius ``D / 2``, Eq. S1; the
        optical-design convention, so ``c_j`` are the objective's aberrations); ``"aperture"``,
        the circle circumscribing the light-carrying mask M (the lenslet apertures inside the
        pupil), the radius Eq. S4 infers from M. On the Table S1 MLA the outer lenslets reach
        0.889 of the pupil radius, so the same coefficients describe different wavefronts
        under the two choices.
    """

    name: str
    magnification: float
    na: float
    immersion_index: float = 1.0
    sample_index: float | None = None
    depth_scale: float = 1.0
    wavelength_um: float = 0.51
    f_fourier_mm: float = 300.0
    f_mla_mm: float = 100.0
    mla_pitch_mm: float = 4.0
    mla_pitch_convention: str = "center"
    mla_orientation: str = "pointy-top"
    mla_rotation_deg: float = 0.0
    lenslet_aperture_mm: float = 4.0
    lenslet_shape: str = "circle"
    pixel_um: float = 6.5
    sensor_shape: tuple[int, int] = (2048, 2048)
    n_lenslets: int = 7
    crop_radius_px: int = 80
    zernike_disk: str = "pupil"

    def __post_init__(self) -> None:
        optional = ("sample_index",) if self.sample_index is not None else ()
        for field in (
            "magnification",
            "na",
            "immersion_index",
            *optional,
            "depth_scale",
            "wavelength_um",
            "f_fourier_mm",
            "f_mla_mm",
            "mla_pitch_mm",
            "lenslet_aperture_mm",
            "pixel_um",
        ):
            value = getattr(self, field)
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not (number and math.isfinite(value) and value > 0):
                raise ValueError(
                    f"system {self.name!r}: {field} must be a positive number, got {value!r}"
                )
        if self.lenslet_shape not in LENSLET_SHAPES:
            raise ValueError(
                f"system {self.name!r}: lenslet_shape must be one of {LENSLET_SHAPES}, "
                f"got {self.lenslet_shape!r}"
            )
        for field, choices in (
            ("mla_pitch_convention", PITCH_CONVENTIONS),
            ("mla_orientation", MLA_ORIENTATIONS),
        ):
            value = getattr(self, field)
            if not isinstance(value, str) or value not in choices:
                raise ValueError(
                    f"system {self.name!r}: {field} must be one of {list(choices)}, got {value!r}"
                )
        rotation = self.mla_rotation_deg
        if isinstance(rotation, bool) or not (
            isinstance(rotation, (int, float)) and math.isfinite(rotation)
        ):
            raise ValueError(
                f"system {self.name!r}: mla_rotation_deg must be a finite number of degrees, "
                f"got {rotation!r}"
            )
        if self.zernike_disk not in ZERNIKE_DISKS:
            raise ValueError(
                f"system {self.name!r}: zernike_disk must be one of {ZERNIKE_DISKS}, "
                f"got {self.zernike_disk!r}"
            )
        if self.na >= self.immersion_index:
            raise ValueError(
                f"system {self.name!r}: na ({self.na}) must be below immersion_index "
                f"({self.immersion_index})"
            )
        object.__setattr__(self, "sensor_shape", self._sensor_shape())
        for field in ("n_lenslets", "crop_radius_px"):
            try:
                count = check_number(field, getattr(self, field), integer=True, minimum=1)
            except ValueError as error:
                raise ValueError(f"system {self.name!r}: {error}") from None
            object.__setattr__(self, field, count)
        self._check_counts()

    def _sensor_shape(self) -> tuple[int, int]:
        """``sensor_shape`` as two positive integers (``2048.0`` and ``"2048"`` read as 2048), or
        one ``ValueError`` naming the field."""
        shape = self.sensor_shape
        sides = None
        if not isinstance(shape, (str, bytes)) and hasattr(shape, "__len__") and len(shape) == 2:
            try:
                sides = tuple(check_number("side", s, integer=True, minimum=1) for s in shape)
            except ValueError:
                sides = None
        if sides is None:
            raise ValueError(
                f"system {self.name!r}: sensor_shape must be two positive integers, got {shape!r}"
            )
        return sides

    def _check_counts(self) -> None:
        """Refuse counts the optics cannot hold, before any array of their size is made: more
        lenslets than hexagonal cells of :attr:`pitch_px` (area ``sqrt(3) / 2 p^2``) tile either
        the sensor or the pupil image grown by one pitch (lenslets the pupil edge cuts), or a PSF
        crop (``2 r + 1`` pixels) wider than the sensor."""
        height, width = self.sensor_shape
        cell = math.sqrt(3.0) / 2.0 * self.pitch_px**2
        on_sensor = height * width / cell
        in_pupil = math.pi * (self.pupil_radius_px + self.pitch_px) ** 2 / cell
        cells = max(1, int(max(on_sensor, in_pupil)))
        if self.n_lenslets > cells:
            raise ValueError(
                f"system {self.name!r}: n_lenslets = {self.n_lenslets} lenslets of pitch "
                f"{self.pitch_px:.1f} px fit neither on the {height} x {width} px sensor nor in "
                f"the pupil of radius {self.pupil_radius_px:.1f} px (at most about {cells}); "
                "check n_lenslets, mla_pitch_mm, pixel_um and sensor_shape"
            )
        if 2 * self.crop_radius_px + 1 > max(height, width):
            raise ValueError(
                f"system {self.name!r}: crop_radius_px = {self.crop_radius_px} makes PSF crops "
                f"of {2 * self.crop_radius_px + 1} px, wider than the {height} x {width} px "
                "sensor"
            )

    @property
    def sample_medium_index(self) -> float:
        """Refractive index of the sample: ``sample_index``, or the immersion index if unset."""
        return self.immersion_index if self.sample_index is None else self.sample_index

    @property
    def design(self) -> dict[str, float]:
        """Nominal design values (:func:`fgat.optics.design.flfm_design`)."""
        return flfm_design(
            self.magnification,
            self.na,
            wavelength_um=self.wavelength_um,
            f_fourier_mm=self.f_fourier_mm,
            f_mla_mm=self.f_mla_mm,
            mla_pitch_mm=self.center_pitch_mm,
            pixel_um=self.pixel_um,
        )

    @property
    def pupil_radius_px(self) -> float:
        """Radius of the objective-pupil image at the MLA plane, ``D / 2`` (Eq. S1), in pixels."""
        return self.design["pupil_diameter_mm"] * 500.0 / self.pixel_um

    @property
    def center_pitch_mm(self) -> float:
        """Centre-to-centre distance of neighbouring lenslets, mm: ``mla_pitch_mm`` read by
        ``mla_pitch_convention`` (:data:`PITCH_CONVENTIONS`)."""
        return self.mla_pitch_mm * PITCH_CONVENTIONS[self.mla_pitch_convention]

    @property
    def pitch_px(self) -> float:
        """Centre-to-centre MLA pitch in camera pixels."""
        return self.center_pitch_mm * 1000.0 / self.pixel_um

    @property
    def lattice_rotation_deg(self) -> float:
        """Rotation of the nominal lattice, degrees in ``(-30, 30]`` counter-clockwise as
        displayed (the hexagonal array repeats every 60 degrees): ``mla_orientation`` (0 or 30)
        plus ``mla_rotation_deg``. A flat-top array is at 30: view 1 upper right, the views
        numbered counter-clockwise from there (:mod:`fgat.optics.lenslets`)."""
        turn = MLA_ORIENTATIONS[self.mla_orientation] + self.mla_rotation_deg
        return 30.0 - (30.0 - turn) % 60.0

    @property
    def voxel_size_um(self) -> float:
        """Lateral sample-space sampling of the elemental images, ``pixel / M_T`` (um)."""
        return self.design["effective_pixel_um"]

    @property
    def optical_axis_px(self) -> tuple[float, float]:
        """Sensor pixel ``(row, col)`` hit by the optical axis."""
        return float(self.sensor_shape[0] // 2), float(self.sensor_shape[1] // 2)

    def lenslet_centers_px(self) -> np.ndarray:
        """Nominal lenslet axes on the camera, ``(V, 2)`` (row, col) pixels, in view order: the
        hexagonal lattice of :attr:`pitch_px` turned by :attr:`lattice_rotation_deg` about the
        optical axis, view 0 on it."""
        return lattice_points(
            self.n_lenslets, self.pitch_px, self.lattice_rotation_deg, self.optical_axis_px
        )

    def grid_voxel_size_um(self, depths_um) -> tuple[float, float, float]:
        """Voxel size ``(dz, dy, dx)`` in um of a reconstruction grid on these depth planes:
        the plane spacing (1 for a single plane) and the lateral ``pixel / M_T``."""
        depths = list(depths_um)
        dz = abs(depths[1] - depths[0]) if len(depths) > 1 else 1.0
        return dz, self.voxel_size_um, self.voxel_size_um

    def replace(self, **changes) -> FLFMSystem:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


def parse_depths(spec) -> list[float]:
    """Distinct finite depths in um from a list, ``"-30,0,30"``, or ``"start:stop:count"``
    (inclusive, evenly spaced)."""
    return parse_values(spec, "depth", distinct=True)


PRESETS = {
    "20x/0.45": "20x_0.45.yaml",
    "40x/0.90": "40x_0.90.yaml",
    "60x/1.25": "60x_1.25.yaml",
    "small": "small.yaml",
    "small37": "small37.yaml",
}


def system_from_yaml(path: str | Path) -> FLFMSystem:
    """Read an :class:`FLFMSystem` from a YAML file, naming the file in every error."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"system file {path} does not exist")
    return _system_from_text(read_text(path), str(path), path.parent, (str(path.resolve()),))


def _system_from_text(
    text: str, source: str, folder: Path | None = None, chain: tuple[str, ...] = ()
) -> FLFMSystem:
    """The system of a YAML text: its fields, or ``base`` (a shipped name or a YAML path relative
    to ``folder``) with some fields changed; ``chain`` lists the files already being read."""
    fields = yaml_fields(text, source, FLFMSystem, extra=("base",))
    base = fields.pop("base", None)
    if base is not None:
        fields = {**dataclasses.asdict(_base_system(base, source, folder, chain)), **fields}
    for required in ("name", "magnification", "na"):
        if required not in fields:
            raise ValueError(f"{source}: missing required field {required!r}")
    if "sensor_shape" in fields:
        fields["sensor_shape"] = tuple(fields["sensor_shape"])
    try:
        return FLFMSystem(**fields)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from None


def _base_system(base, source: str, folder: Path | None, chain: tuple[str, ...]) -> FLFMSystem:
    """The system a YAML file's ``base`` names, relative paths resolved against ``folder``."""
    key = str(base)
    if key in PRESETS:
        return load_system(key)
    path = Path(key) if folder is None or Path(key).is_absolute() else folder / key
    if str(path.resolve()) in chain:
        raise ValueError(f"{source}: base {base!r} leads back to a file already being read")
    if not path.is_file():
        raise ValueError(f"{source}: base {base!r}: no shipped system and no file {path}")
    chain = (*chain, str(path.resolve()))
    return _system_from_text(read_text(path), str(path), path.parent, chain)


def load_system(name_or_path: str | Path) -> FLFMSystem:
    """A shipped system by name (``"20x/0.45"``, ``"40x/0.90"``, ``"60x/1.25"``, ``"small"``) or a
    YAML file path."""
    key = str(name_or_path)
    if key in PRESETS:
        text = resources.files("fgat.optics").joinpath("systems", PRESETS[key]).read_text()
        return _system_from_text(text, f"preset {key!r}")
    if Path(key).suffix.lower() in (".yaml", ".yml"):
        return system_from_yaml(key)
    raise ValueError(
        f"unknown system {key!r}: use one of {sorted(PRESETS)} or a path to a YAML file"
    )
