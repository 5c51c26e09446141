"""Simulated FLFM acquisitions: phantom -> JPGM PSF stack -> sensor image with camera noise.

A simulation is described by a :class:`SimulationConfig` (a YAML file for ``fgat simulate``)
and written as a folder that reads back identically:

=================  ==========================================================================
``truth.ome.tif``  ground-truth volume ``(Z, Y, X)``, float32, voxel sizes in um
``psf.ome.tif``    PSF stack ``(V, Z, 2r+1, 2r+1)`` used for the forward model
``sensor.ome.tif`` sensor image ``(H, W)`` in counts (background, shot and read noise)
``views.ome.tif``  per-view images ``(V, Y, X)`` cropped from the sensor around the centres
``centers.csv``    lenslet centres, one ``row,col`` line per view (0-based pixels)
``params.yaml``    every parameter: optics, depths, Zernike coefficients, shifts, noise, seed
=================  ==========================================================================

A realistic acquisition (:class:`Imperfections`, ``imperfections`` in the YAML) adds, where asked:

========================  ===================================================================
``truth_padded.ome.tif``  the whole object ``(Z, Y + 2m, X + 2m)`` of a field margin ``m``
                          (``truth.ome.tif`` is its central crop, what the views see)
``dark.ome.tif``          dark frames ``(T, H, W)``: offset, read noise, hot pixels, no light
``flat.ome.tif``          white-light image of the MLA ``(H, W)``: one lit disk per lenslet
                          (for lenslet calibration and view gains; not a sensor flat field)
``hot_pixels.csv``        hot pixels, one ``row,col,counts`` line each
========================  ===================================================================

and ``centers.csv`` then holds the true (rotated, jittered) lenslet centres, ``params.yaml``
the drawn gains and hot pixels under ``imperfections``.

The volumes and the PSF stack record fgat's depth axis (``"up"``), their planes' depths and
the view order (:func:`fgat.io.images.volume_metadata`).

A dynamic phantom (``moving_beads``, ``beating_shell``) with ``frames > 1`` gives a sequence: the
truth is ``(T, Z, Y, X)``, the sensor ``(T, H, W)`` and the views ``(T, V, Y, X)``, at the
normalised times :func:`frame_times` (the same optics and one photon scale for every frame).
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import math
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import torch
import yaml

from fgat import __version__
from fgat._core.resources import check_disk_space, check_memory
from fgat._core.validation import check_number, coerce_fields, parse_overrides
from fgat.instrument.centres import check_view_order, write_centers
from fgat.io.files import atomic_path, check_output_file, check_writable_folder, read_text
from fgat.io.images import volume_entries, write_tiff
from fgat.io.yaml_files import check_fields, yaml_fields
from fgat.optics.operator import FLFMOperator, operator_memory
from fgat.optics.psf import JPGM, check_optics
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import FLFMSystem, load_system, parse_depths
from fgat.optics.zernike import DEFAULT_INDICES
from fgat.sim.phantoms import (
    beads,
    beating_shell,
    lenslet_flat,
    line_sphere,
    moving_beads,
    noisy_measurement,
    reticular,
    shell_beads,
)

PHANTOMS = {
    "beads": beads,
    "line_sphere": line_sphere,
    "reticular": reticular,
    "moving_beads": moving_beads,
    "beating_shell": beating_shell,
    "shell_beads": shell_beads,
}
DYNAMIC_PHANTOMS = ("moving_beads", "beating_shell")  # functions of (shape, times, ...)
SUPPLIED_OPTIONS = ("shape", "times", "voxel_size_um")  # given by the simulation, not the YAML
OUTPUT_FILES = (
    "truth.ome.tif",
    "psf.ome.tif",
    "sensor.ome.tif",
    "views.ome.tif",
    "centers.csv",
    "params.yaml",
)
# Written only by a simulation with imperfections that asks for them (see the module docstring).
OPTIONAL_OUTPUT_FILES = (
    "truth_padded.ome.tif",
    "dark.ome.tif",
    "flat.ome.tif",
    "hot_pixels.csv",
)
FLAT_COUNTS = 1000.0  # peak counts of the flat field of a noise-free simulation (photons: null)


@dataclass(frozen=True)
class Aberrations:
    """Random true optics of a simulation (Figs. S6-S9), drawn by :func:`sample_aberrations`.

    Attributes
    ----------
    terms : int
        The first ``terms`` Noll indices of J = 5..21 are aberrated.
    amplitude : float
        Coefficients uniform in ``[-amplitude, amplitude]`` waves.
    rms : float or None
        Then rescaled to this RMS (2-norm of the coefficients) in waves.
    intercept_range, slope_range : float
        Per-view intercepts / slopes uniform in ``[-range, range]`` pixels, per axis.
    seed : int or None
        Seed of the draw; ``None``: the simulation's.
    """

    terms: int = 17
    amplitude: float = 1.0
    rms: float | None = None
    intercept_range: float = 0.0
    slope_range: float = 0.0
    seed: int | None = None

    def sample(self, n_views: int, default_seed: int) -> dict[str, dict]:
        """:func:`sample_aberrations` of these settings for ``n_views`` views."""
        fields = {
            **dataclasses.asdict(self),
            "seed": default_seed if self.seed is None else self.seed,
        }
        return sample_aberrations(n_views, **fields)


@dataclass(frozen=True)
class Imperfections:
    """What a real acquisition has and the ideal simulation lacks (``imperfections`` in YAML).

    Every default is the ideal. With any ``Imperfections`` (even all defaults) the camera offset
    ``background`` is a bias without shot noise, as in a dark frame (the ideal simulation,
    ``imperfections: null``, puts Poisson noise on it, unchanged for reproducibility).

    Attributes
    ----------
    mla_rotation_deg : float
        Rotation of the whole MLA about the optical axis, degrees in (-30, 30),
        counter-clockwise as the image is displayed (rows down; the convention of
        :class:`fgat.instrument.lattice.HexLattice`): the lenslet centres turn about view 0.
    center_jitter_px : float
        Each lenslet centre (view 0 too) moves off the lattice by a uniform draw in
        ``[-j, j]`` pixels per axis (below a quarter of the pitch).
    gains : (lo, hi) or list of V floats, optional
        Relative per-view gains (transmission of each lenslet), positive: two numbers are a
        range, view 0 (the centre, the brightest) gets ``hi`` and every other view a uniform
        draw in ``[lo, hi]``; ``V`` numbers are the gains themselves. ``None``: all 1. Each
        view is multiplied by its gain before it is placed on the sensor.
    hot_pixels : int
        Number of hot pixels at random distinct sensor positions (``hot_pixels.csv``).
    hot_pixel_counts : float
        Extra dark signal of each hot pixel, counts (mean; Poisson when ``photons`` is set), in
        the image, the dark frames and the flat.
    field_margin_px : int
        The object extends this many pixels beyond the view field on each lateral side: the
        phantom is drawn on ``(Z, Y + 2m, X + 2m)``, projected whole with the same PSF stack and
        each view's padded image is placed on the sensor (neighbours' images may overlap and
        add), so light from outside a view's field reaches it. ``truth.ome.tif`` is the central
        ``(Z, Y, X)`` crop, ``truth_padded.ome.tif`` the whole object.
    dark_frames : int
        Number of dark frames ``(T, H, W)`` written as ``dark.ome.tif`` (0: none).
    flat : bool
        Write ``flat.ome.tif``: every lenslet's elemental image a uniformly lit disk of radius
        ``flat_radius_pitch`` pitches around its true centre (smooth edge) times its gain, at
        ``photons`` counts (:data:`FLAT_COUNTS` when ``photons`` is null), with the camera's
        offset, noise and hot pixels.
    flat_radius_pitch : float
        Disk radius of the flat in lenslet pitches, in (0, 0.5].
    seed : int or None
        Seed of the draws (centres, gains, hot pixels, dark and flat noise); ``None``: the
        simulation's.
    """

    mla_rotation_deg: float = 0.0
    center_jitter_px: float = 0.0
    gains: tuple[float, float] | list[float] | None = None
    hot_pixels: int = 0
    hot_pixel_counts: float = 500.0
    field_margin_px: int = 0
    dark_frames: int = 0
    flat: bool = False
    flat_radius_pitch: float = 0.45
    seed: int | None = None

    def __post_init__(self) -> None:
        def name(field_name: str) -> str:
            return f"imperfections.{field_name}"

        def put(field_name: str, value) -> None:
            object.__setattr__(self, field_name, value)

        rotation = check_number(name("mla_rotation_deg"), self.mla_rotation_deg)
        if not -30 < rotation < 30:
            raise ValueError(
                f"{name('mla_rotation_deg')} must be in (-30, 30) degrees (a hexagonal MLA repeats "
                f"every 60 degrees), got {self.mla_rotation_deg!r}"
            )
        put("mla_rotation_deg", rotation)
        put(
            "center_jitter_px",
            check_number(name("center_jitter_px"), self.center_jitter_px, minimum=0),
        )
        if self.gains is not None:
            gains = self.gains
            if (
                isinstance(gains, (str, bytes, dict))
                or not hasattr(gains, "__len__")
                or len(gains) < 2
            ):
                raise ValueError(
                    f"{name('gains')} must be a range [lo, hi] or one positive number per view, "
                    f"got {gains!r}"
                )
            gains = tuple(check_number(name("gains"), g, above=0) for g in gains)
            if len(gains) == 2 and gains[0] > gains[1]:
                raise ValueError(
                    f"{name('gains')} range [lo, hi] needs lo <= hi, got {self.gains!r}"
                )
            put("gains", gains)
        for integer in ("hot_pixels", "field_margin_px", "dark_frames"):
            put(
                integer,
                check_number(name(integer), getattr(self, integer), integer=True, minimum=0),
            )
        put(
            "hot_pixel_counts",
            check_number(name("hot_pixel_counts"), self.hot_pixel_counts, minimum=0),
        )
        if not isinstance(self.flat, (bool, np.bool_)):
            raise ValueError(f"{name('flat')} must be true or false, got {self.flat!r}")
        put("flat", bool(self.flat))
        put(
            "flat_radius_pitch",
            check_number(name("flat_radius_pitch"), self.flat_radius_pitch, above=0, maximum=0.5),
        )
        if self.seed is not None:
            put("seed", check_number(name("seed"), self.seed, integer=True, minimum=0))

    def draw(self, system: FLFMSystem, default_seed: int) -> DrawnImperfections:
        """The true lenslet centres, gains and hot pixels of ``system``
        (:class:`DrawnImperfections`), from ``seed`` (``default_seed`` when ``None``); raises
        ``ValueError`` naming the field when the system cannot take them (gains of the wrong
        length, jitter of a quarter pitch or more, more hot pixels than sensor pixels)."""
        seed = default_seed if self.seed is None else self.seed
        nominal = system.lenslet_centers_px()
        n_views = len(nominal)
        offsets = nominal - nominal[0]
        angle = math.radians(self.mla_rotation_deg)
        cos, sin = math.cos(angle), math.sin(angle)
        # (col, -row) turns counter-clockwise by the rotation (as HexLattice.centers)
        centers = nominal[0] + np.stack(
            [-sin * offsets[:, 1] + cos * offsets[:, 0], cos * offsets[:, 1] + sin * offsets[:, 0]],
            axis=1,
        )
        if self.center_jitter_px >= system.pitch_px / 4:
            raise ValueError(
                f"imperfections.center_jitter_px = {self.center_jitter_px:g} must be below a "
                f"quarter of the {system.pitch_px:.1f} px lenslet pitch of system {system.name!r}"
            )
        if self.center_jitter_px > 0:
            jitter = np.random.default_rng([seed, 1]).uniform(
                -self.center_jitter_px, self.center_jitter_px, (n_views, 2)
            )
            centers = centers + jitter
        check_view_order(centers, "imperfections (mla_rotation_deg, center_jitter_px)")
        gains = np.ones(n_views)
        if self.gains is not None and len(self.gains) == 2:
            low, high = self.gains
            gains = np.random.default_rng([seed, 2]).uniform(low, high, n_views)
            gains[0] = high
        elif self.gains is not None:
            if len(self.gains) != n_views:
                raise ValueError(
                    f"imperfections.gains has {len(self.gains)} values for the {n_views} views of "
                    f"system {system.name!r}: give a range [lo, hi] or {n_views} values"
                )
            gains = np.asarray(self.gains, dtype=np.float64)
        height, width = system.sensor_shape
        if self.hot_pixels > height * width:
            raise ValueError(
                f"imperfections.hot_pixels = {self.hot_pixels} is more than the {height} x {width} "
                "sensor's pixels"
            )
        flat_index = np.sort(
            np.random.default_rng([seed, 3]).choice(height * width, self.hot_pixels, replace=False)
        )
        hot = np.stack(np.unravel_index(flat_index, (height, width)), axis=1).astype(np.int64)
        return DrawnImperfections(
            nominal_centers=nominal,
            centers=centers,
            gains=gains,
            hot_pixels=hot.reshape(-1, 2),
            seed=seed,
        )


@dataclass(frozen=True, eq=False)
class DrawnImperfections:
    """One draw of :class:`Imperfections` for a system.

    Attributes
    ----------
    nominal_centers, centers : numpy.ndarray
        ``(V, 2)`` lattice and true (rotated, jittered) lenslet centres (row, col), pixels.
    gains : numpy.ndarray
        ``(V,)`` per-view gains.
    hot_pixels : numpy.ndarray
        ``(N, 2)`` int (row, col) of the hot pixels, sorted.
    seed : int
        The seed the draws came from (dark frames use ``(seed, 4, t)``, the flat ``(seed, 5)``).
    """

    nominal_centers: np.ndarray
    centers: np.ndarray
    gains: np.ndarray
    hot_pixels: np.ndarray
    seed: int

    def dark_map(self, sensor_shape: tuple[int, int], counts: float) -> np.ndarray:
        """``(H, W)`` mean dark signal: ``counts`` at each hot pixel, 0 elsewhere."""
        dark = np.zeros(sensor_shape)
        dark[self.hot_pixels[:, 0], self.hot_pixels[:, 1]] = counts
        return dark


@dataclass
class SimulationConfig:
    """Everything that defines a simulated acquisition.

    Attributes
    ----------
    system : str
        Shipped system name (``small``, ``20x/0.45`` ...) or a system YAML path.
    depths_um : str or list of float
        PSF/volume planes, ``"start:stop:count"`` or explicit values (um).
    view_size : int
        Lateral size ``Y = X`` of the volume and of each view, pixels (= sample voxels).
    phantom : dict
        ``kind`` (``beads``, ``line_sphere``, ``shell_beads``, ``reticular``, or the dynamic
        ``moving_beads`` and ``beating_shell``) and that phantom's keyword arguments (``seed``
        defaults to the simulation seed where the phantom takes one; the grid's voxel size is
        supplied to a phantom that takes ``voxel_size_um``).
    frames : int
        Number of frames ``T`` of a dynamic phantom, acquired at :func:`frame_times`; 1 (a
        single snapshot at ``t = 0``) for a static one.
    zernike : dict
        Noll index -> coefficient in waves of the true pupil aberration.
    intercepts, slopes : dict
        View -> ``[row, col]`` true PSF shifts ``b_v`` (pixels) and ``s_v`` (pixels per unit xi).
    aberrations : Aberrations, optional
        Random true optics (:class:`Aberrations`, a mapping in YAML): ``terms`` (the first N Noll
        indices of J = 5..21, default 17), ``amplitude`` (coefficients uniform in [-amplitude,
        amplitude] waves, default 1), ``rms`` (then rescaled to this RMS in waves),
        ``intercept_range`` and ``slope_range`` (pixels, uniform per view and axis, default 0),
        ``seed`` (default the simulation's). Explicit ``zernike``, ``intercepts`` and ``slopes``
        entries take precedence.
    imperfections : Imperfections, optional
        A realistic acquisition (:class:`Imperfections`, a mapping in YAML): MLA rotation,
        lenslet-centre jitter, per-view gains, hot pixels, a field margin (light from beyond the
        views' field), dark frames and a flat. ``None``: the ideal simulation.
    photons : float or None
        Expected counts at the brightest sensor pixel; ``None`` for a noise-free image.
    background : float
        Constant camera offset, counts.
    read_noise : float
        Gaussian read-noise standard deviation, counts.
    seed : int
        Seed of the phantom and of the noise.
    """

    system: str = "small"
    depths_um: str | list = "-22.5:22.5:31"
    view_size: int = 64
    phantom: dict = field(default_factory=lambda: {"kind": "beads", "n_beads": 30, "sigma": 1.0})
    frames: int = 1
    zernike: dict = field(default_factory=dict)
    intercepts: dict = field(default_factory=dict)
    slopes: dict = field(default_factory=dict)
    aberrations: Aberrations | None = None
    imperfections: Imperfections | None = None
    photons: float | None = 1000.0
    background: float = 0.0
    read_noise: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("phantom", "zernike", "intercepts", "slopes", "aberrations", "imperfections"):
            setattr(self, name, parse_overrides(getattr(self, name)))
        coerce_fields(self)
        if isinstance(self.aberrations, dict):
            check_fields("aberrations", Aberrations, self.aberrations)
            self.aberrations = Aberrations(**self.aberrations)
        if isinstance(self.imperfections, dict):
            check_fields("imperfections", Imperfections, self.imperfections)
            self.imperfections = Imperfections(**self.imperfections)

    @classmethod
    def from_yaml(cls, path: str | Path) -> SimulationConfig:
        """Read a config file; errors name the file and the field."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"simulation config {path} does not exist")
        fields = yaml_fields(read_text(path), str(path), cls)
        try:
            config = cls(**fields)
            config.validate()
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
        return config

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field (types and ranges, the phantom's
        options against its function's signature, the optics' numbers and the depths); what
        needs the system or the phantom's shape is checked by :func:`simulate` before it
        computes."""
        if not isinstance(self.view_size, int) or self.view_size < 1:
            raise ValueError(f"view_size must be a positive integer, got {self.view_size!r}")
        if not isinstance(self.phantom, dict) or self.phantom.get("kind") not in PHANTOMS:
            raise ValueError(
                f"phantom.kind must be one of {sorted(PHANTOMS)}, got {self.phantom!r}"
            )
        check_phantom_options(self.phantom)
        if not isinstance(self.frames, int) or self.frames < 1:
            raise ValueError(f"frames must be a positive integer, got {self.frames!r}")
        if self.frames > 1 and self.phantom["kind"] not in DYNAMIC_PHANTOMS:
            raise ValueError(
                f"frames = {self.frames} needs a dynamic phantom.kind {DYNAMIC_PHANTOMS}, "
                f"got {self.phantom['kind']!r}"
            )
        if self.photons is not None and not self.photons > 0:
            raise ValueError(f"photons must be positive or null, got {self.photons!r}")
        for name in ("background", "read_noise", "seed"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)!r}")
        check_optics(self.zernike, self.intercepts, self.slopes)
        if self.aberrations is not None:
            if not isinstance(self.aberrations, Aberrations):
                field_names = [f.name for f in dataclasses.fields(Aberrations)]
                raise ValueError(
                    f"aberrations must be a mapping of {field_names}, got {self.aberrations!r}"
                )
            self.aberrations.sample(1, self.seed)  # checks the values
        if self.imperfections is not None and not isinstance(self.imperfections, Imperfections):
            field_names = [f.name for f in dataclasses.fields(Imperfections)]
            raise ValueError(
                f"imperfections must be a mapping of {field_names}, got {self.imperfections!r}"
            )
        parse_depths(self.depths_um)

    @property
    def field_margin_px(self) -> int:
        """The field margin ``m`` of the imperfections (0 without)."""
        return 0 if self.imperfections is None else self.imperfections.field_margin_px


def check_phantom_options(phantom: dict) -> None:
    """Raise ``ValueError`` if ``phantom`` (``kind`` and keyword options) names an option its
    function does not take, or lacks one it requires, listing the valid options (from the
    function's signature; the shape, times and voxel size are the simulation's)."""
    kind = phantom["kind"]
    parameters = {
        name: parameter
        for name, parameter in inspect.signature(PHANTOMS[kind]).parameters.items()
        if name not in SUPPLIED_OPTIONS
    }
    options = set(phantom) - {"kind"}
    unknown = sorted(options - set(parameters))
    if unknown:
        raise ValueError(
            f"phantom: unknown option(s) {unknown} for kind {kind!r}; "
            f"valid options: {sorted(parameters)}"
        )
    missing = sorted(
        name
        for name, parameter in parameters.items()
        if parameter.default is inspect.Parameter.empty and name not in options
    )
    if missing:
        raise ValueError(
            f"phantom: kind {kind!r} needs option(s) {missing}; valid options: {sorted(parameters)}"
        )


@dataclass
class Simulation:
    """Result of :func:`simulate` (NumPy arrays, float32); a sequence's ``truth``, ``sensor`` and
    ``views`` have a leading time axis, acquired at ``times`` (normalised, ``(T,)``).

    With imperfections, ``centers`` are the true lenslet centres and ``imperfections`` their
    draw (:class:`DrawnImperfections`); ``truth_padded`` is the whole object of a field margin
    (``truth`` its central crop), ``dark`` the dark frames ``(T, H, W)`` and ``flat`` the
    white-light image ``(H, W)`` where asked (else ``None``)."""

    config: SimulationConfig
    system: FLFMSystem
    depths_um: list[float]
    truth: np.ndarray
    psf: np.ndarray
    sensor: np.ndarray
    views: np.ndarray
    centers: np.ndarray
    zernike_indices: tuple[int, ...]
    zernike_coefficients: np.ndarray
    intercepts: np.ndarray
    slopes: np.ndarray
    times: np.ndarray
    imperfections: DrawnImperfections | None = None
    truth_padded: np.ndarray | None = None
    dark: np.ndarray | None = None
    flat: np.ndarray | None = None

    @property
    def is_sequence(self) -> bool:
        return self.truth.ndim == 4

    @property
    def voxel_size_um(self) -> tuple[float, float, float]:
        return self.system.grid_voxel_size_um(self.depths_um)


def frame_times(frames: int) -> np.ndarray:
    """Normalised acquisition times ``t_k = k / (T - 1)`` in [0, 1] of ``T`` frames (``[0]`` for
    one)."""
    return np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)


def make_phantom(
    config: SimulationConfig, shape: tuple[int, int, int], times=None, *, padded: bool = False
) -> np.ndarray:
    """The ground truth of ``config.phantom`` on ``shape``: ``(Z, Y, X)`` for a static phantom or
    a single frame, ``(T, Z, Y, X)`` for a dynamic one at ``times`` (normalised; default
    :func:`frame_times` of ``config.frames``).

    With a field margin ``m`` (:class:`Imperfections`) the phantom is drawn on
    ``(Z, Y + 2m, X + 2m)`` and its central ``shape`` crop returned (the whole grid when
    ``padded``), so the truth is the same object at any call."""
    margin = config.field_margin_px
    if margin:
        grid = (shape[0], shape[1] + 2 * margin, shape[2] + 2 * margin)
        whole = make_phantom(dataclasses.replace(config, imperfections=None), grid, times)
        return whole if padded else np.ascontiguousarray(whole[..., margin:-margin, margin:-margin])
    options = {key: value for key, value in config.phantom.items() if key != "kind"}
    kind = config.phantom["kind"]
    check_phantom_options(config.phantom)
    try:
        if kind == "reticular":
            return reticular(options["path"], shape)
        if kind != "beating_shell":  # the shell is deterministic
            options.setdefault("seed", config.seed)
        if "voxel_size_um" in inspect.signature(PHANTOMS[kind]).parameters:
            depths = parse_depths(config.depths_um)
            options["voxel_size_um"] = load_system(config.system).grid_voxel_size_um(depths)
        if kind not in DYNAMIC_PHANTOMS:
            return PHANTOMS[kind](shape, **options)
        sequence = PHANTOMS[kind](
            shape, frame_times(config.frames) if times is None else np.asarray(times), **options
        )
    except ValueError as error:
        raise ValueError(f"phantom {kind}: {error}") from None
    return sequence[0] if times is None and config.frames == 1 else sequence


def sample_aberrations(
    n_views: int,
    *,
    terms: int = 17,
    amplitude: float = 1.0,
    rms: float | None = None,
    intercept_range: float = 0.0,
    slope_range: float = 0.0,
    seed: int = 0,
) -> dict[str, dict]:
    """Random true optics as in Figs. S6-S9: Zernike coefficients of the first ``terms`` Noll
    indices of J = 5..21 uniform in ``[-amplitude, amplitude]`` waves, optionally rescaled to an
    RMS of ``rms`` waves (the 2-norm of the coefficients), and per-view intercepts / slopes
    uniform in ``[-intercept_range, intercept_range]`` / ``[-slope_range, slope_range]`` pixels.

    Returns ``{"zernike": {j: c}, "intercepts": {v: [row, col]}, "slopes": {v: [row, col]}}``.
    """
    if not 1 <= terms <= len(DEFAULT_INDICES):
        raise ValueError(f"aberrations.terms must be 1..{len(DEFAULT_INDICES)}, got {terms}")
    rng = np.random.default_rng(seed)
    coefficients = rng.uniform(-amplitude, amplitude, terms)
    if rms is not None:
        coefficients *= rms / max(float(np.linalg.norm(coefficients)), 1e-12)
    shifts = {
        name: {v: rng.uniform(-width, width, 2).tolist() for v in range(n_views)} if width else {}
        for name, width in (("intercepts", intercept_range), ("slopes", slope_range))
    }
    return {"zernike": dict(zip(DEFAULT_INDICES[:terms], coefficients.tolist())), **shifts}


def true_optics(config: SimulationConfig, n_views: int) -> dict[str, dict]:
    """The simulation's true Zernike coefficients and shifts: sampled aberrations, then explicit
    entries."""
    optics = {"zernike": {}, "intercepts": {}, "slopes": {}}
    if config.aberrations is not None:
        optics = config.aberrations.sample(n_views, config.seed)
    for name in optics:
        optics[name] = {**optics[name], **{int(k): v for k, v in getattr(config, name).items()}}
    return optics


def true_psf_model(
    config: SimulationConfig, system: FLFMSystem, depths: list[float], centers_px=None
) -> JPGM:
    """The JPGM with the configuration's true aberrations and shifts set (float64), on the
    lenslet centres ``centers_px`` ``(V, 2)`` (default the system's nominal MLA)."""
    return OpticsSpec(
        system, tuple(depths), centers_px, **true_optics(config, system.n_lenslets)
    ).jpgm(dtype=torch.float64)


def simulate(config: SimulationConfig, output: str | Path | None = None) -> Simulation:
    """Phantom, PSF stack, noise-free views, sensor image with noise, and the views cropped from it.

    With ``config.imperfections`` (:class:`Imperfections`) the true (rotated, jittered) lenslet
    centres make the PSF stack and place the views; the object is drawn and projected with its
    field margin, each view is multiplied by its gain before it is placed, hot pixels join the
    camera, and the dark frames and the flat are made (:func:`calibration_frames`).

    Everything that can be known from the configuration is checked first (fields, optics, views
    on the sensor, sampling, memory: :func:`simulation_memory`; with ``output``, the folder the
    files will go to, the room on its disk: :func:`output_bytes`), so a request that cannot
    succeed fails before the phantom is drawn.
    """
    config.validate()
    system = load_system(config.system)
    depths = parse_depths(config.depths_um)
    shape = (len(depths), config.view_size, config.view_size)
    drawn = None
    if config.imperfections is not None:
        drawn = config.imperfections.draw(system, config.seed)
    model = true_psf_model(config, system, depths, None if drawn is None else drawn.centers)
    model.check_sampling()
    centers = system.lenslet_centers_px() if drawn is None else drawn.centers
    # Raises if a view leaves the sensor (the sensor stood in for by a zero-stride tensor).
    FLFMOperator.views_from_sensor(
        torch.zeros(()).expand(system.sensor_shape), centers, config.view_size
    )
    margin = config.field_margin_px
    padded = (shape[0], shape[1] + 2 * margin, shape[2] + 2 * margin)
    if margin:
        try:
            FLFMOperator.views_from_sensor(
                torch.zeros(()).expand(system.sensor_shape), centers, padded[1:]
            )
        except ValueError as error:
            raise ValueError(
                f"imperfections.field_margin_px = {margin}: the padded views do not fit on the "
                f"sensor ({error})"
            ) from None
    check_memory(
        "the phantom, PSF stack and forward model",
        simulation_memory(config, model, shape),
        hint="reduce view_size, depths_um or frames",
    )
    if output is not None:
        check_disk_space(output, output_bytes(config), what=f"output folder {output}")
    whole = make_phantom(config, shape, padded=True)
    with torch.no_grad():
        psf = model()
    operator = FLFMOperator(psf, padded)
    gains = None if drawn is None else torch.from_numpy(drawn.gains)[:, None, None]
    clean = []
    for volume in whole.reshape(-1, *padded):
        views = operator.forward(torch.from_numpy(volume).double()).clamp(min=0)
        if gains is not None:
            views = views * gains
        clean.append(FLFMOperator.sensor(views, centers, system.sensor_shape).numpy())
    dark = None
    if drawn is not None and len(drawn.hot_pixels):
        dark = drawn.dark_map(system.sensor_shape, config.imperfections.hot_pixel_counts)
    sensor = camera(clean, config, dark).reshape(*whole.shape[:-3], *system.sensor_shape)
    views = FLFMOperator.views_from_sensor(
        torch.from_numpy(sensor), centers, config.view_size
    ).numpy()
    truth = whole
    if margin:
        truth = np.ascontiguousarray(whole[..., margin:-margin, margin:-margin])
    extras = {}
    if drawn is not None:
        extras = calibration_frames(config, system, drawn, dark)
        extras.update(imperfections=drawn, truth_padded=whole if margin else None)
    return Simulation(
        config=config,
        system=system,
        depths_um=depths,
        truth=truth,
        psf=psf.float().numpy(),
        sensor=sensor,
        views=views,
        centers=centers,
        zernike_indices=model.zernike_indices,
        zernike_coefficients=model.zernike_coefficients.detach().numpy(),
        intercepts=model.intercepts.detach().numpy(),
        slopes=model.slopes.detach().numpy(),
        times=frame_times(config.frames),
        **extras,
    )


def calibration_frames(
    config: SimulationConfig,
    system: FLFMSystem,
    drawn: DrawnImperfections,
    dark: np.ndarray | None,
) -> dict[str, np.ndarray | None]:
    """The dark frames ``(T, H, W)`` and the flat ``(H, W)`` (float32 counts) that
    ``config.imperfections`` asks for (``None`` where not): the camera of :func:`camera` on no
    light, and on one lit disk per lenslet (:func:`fgat.sim.phantoms.lenslet_flat`) times its gain,
    peaking at ``photons`` counts."""
    imperfections = config.imperfections
    shape = system.sensor_shape
    camera_options = dict(
        background=0.0 if dark is None else dark,
        offset=config.background,
        read_noise=config.read_noise,
    )
    frames = {"dark": None, "flat": None}
    if imperfections.dark_frames:
        no_light = np.zeros(shape)
        frames["dark"] = np.stack(
            [
                noisy_measurement(
                    no_light, photons=config.photons, seed=[drawn.seed, 4, t], **camera_options
                )
                for t in range(imperfections.dark_frames)
            ]
        )
    if imperfections.flat:
        light = lenslet_flat(
            shape, drawn.centers, imperfections.flat_radius_pitch * system.pitch_px, drawn.gains
        )
        if config.photons is None:
            light *= FLAT_COUNTS / max(float(light.max()), 1e-30)
        frames["flat"] = noisy_measurement(
            light, photons=config.photons, seed=[drawn.seed, 5], **camera_options
        )
    return frames


# Bytes per voxel a phantom function holds at its peak beyond its float32 frames: coordinate
# grids, distances and exponentials of the whole volume for the ones drawn analytically.
PHANTOM_SCRATCH_BYTES = {
    "beads": 8,
    "moving_beads": 8,
    "line_sphere": 64,
    "beating_shell": 72,
    "shell_beads": 96,
    "reticular": 8,
}


def simulation_memory(config: SimulationConfig, model: JPGM, shape: tuple[int, int, int]) -> int:
    """Peak memory of :func:`simulate` in bytes, a rough upper bound from the shapes.

    With ``T`` frames of ``N = Z Y X`` voxels: the phantom (``T N`` float32 frames, twice for
    the final scaling, plus :data:`PHANTOM_SCRATCH_BYTES` per voxel and 48 bytes per bead
    position), the float64 PSF stack (:meth:`fgat.optics.psf.JPGM.memory_bytes`), the float64
    forward operator and one projection (:func:`fgat.recon.operator_memory`) with the float64
    copy of one frame, and the sensor images (float64 clean, noisy and float32 stored, ``T H W``)
    and views (``T V Y X`` float32); with imperfections, ``Y`` and ``X`` include the field margin
    and the dark map, dark frames and flat add their sensor images.
    """
    frames = config.frames
    margin = config.field_margin_px
    shape = (shape[0], shape[1] + 2 * margin, shape[2] + 2 * margin)
    voxels = int(np.prod(shape))
    scratch = PHANTOM_SCRATCH_BYTES[config.phantom["kind"]] * voxels
    n_beads = config.phantom.get("n_beads", 0)
    beads = (
        48 * n_beads
        if isinstance(n_beads, (int, float)) and math.isfinite(n_beads) and n_beads > 0
        else 0
    )
    phantom = 2 * 4 * frames * voxels + scratch + beads
    n_views = model.n_views
    psf_shape = (n_views, shape[0], 2 * model.radius + 1, 2 * model.radius + 1)
    forward = operator_memory(psf_shape, shape, itemsize=8, adjoint=False) + 8 * voxels
    height, width = model.system.sensor_shape
    camera_images = frames * height * width * (8 + 8 + 4)
    if config.imperfections is not None:  # dark map, dark frames, flat
        calibration = config.imperfections.dark_frames + config.imperfections.flat
        camera_images += height * width * (8 + calibration * (8 + 8 + 4))
    views = frames * n_views * shape[1] * shape[2] * 4
    return int(phantom + model.memory_bytes() + forward + camera_images + views)


def camera(
    clean: list[np.ndarray], config: SimulationConfig, dark: np.ndarray | None = None
) -> np.ndarray:
    """Noisy float32 sensor frames ``(T, H, W)`` from noise-free ones, one frame at a time (memory):
    one photon scale for the whole sequence (``config.photons`` expected counts at its brightest
    pixel) and independent noise per frame (seed ``(config.seed, k)``; a single frame uses
    ``config.seed``).

    With ``config.imperfections`` the offset ``config.background`` is a bias added after the shot
    noise, and ``dark`` ``(H, W)`` (the hot pixels' mean dark signal) is added before it;
    without, the offset is added before the shot noise (the ideal simulation's model)."""
    if config.imperfections is not None:
        levels = {"background": 0.0 if dark is None else dark, "offset": config.background}
    else:
        levels = {"background": config.background}
    if len(clean) == 1:
        return noisy_measurement(
            clean[0],
            photons=config.photons,
            read_noise=config.read_noise,
            seed=config.seed,
            **levels,
        )[None]
    peaks = [float(frame.max()) for frame in clean]
    top = max(max(peaks), 1e-30)
    return np.stack(
        [
            noisy_measurement(
                frame,
                read_noise=config.read_noise,
                photons=None if config.photons is None else config.photons * max(peak / top, 1e-12),
                seed=[config.seed, k],
                **levels,
            )
            for k, (frame, peak) in enumerate(zip(clean, peaks))
        ]
    )


def _plain(value):
    """Tuples (and NumPy scalars) inside nested dicts and lists as YAML-safe lists and numbers."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _parameters(result: Simulation) -> dict:
    config = _plain(dataclasses.asdict(result.config))
    drawn = result.imperfections
    imperfections = {}
    if drawn is not None:
        imperfections = {
            "imperfections": {
                "seed": int(drawn.seed),
                "nominal_centers_px": drawn.nominal_centers.tolist(),
                "gains": drawn.gains.tolist(),
                "hot_pixels_px": drawn.hot_pixels.tolist(),
                "hot_pixel_counts": float(result.config.imperfections.hot_pixel_counts),
            }
        }
    extra_shapes = {
        name: list(getattr(result, name).shape)
        for name in ("truth_padded", "dark", "flat")
        if getattr(result, name) is not None
    }
    return {
        "fgat_version": __version__,
        "config": config,
        "system": dataclasses.asdict(result.system)
        | {"sensor_shape": list(result.system.sensor_shape)},
        "depths_um": [float(d) for d in result.depths_um],
        "voxel_size_um": [float(v) for v in result.voxel_size_um],
        "zernike": {
            int(j): float(c) for j, c in zip(result.zernike_indices, result.zernike_coefficients)
        },
        "intercepts_px": result.intercepts.tolist(),
        "slopes_px": result.slopes.tolist(),
        "centers_px": result.centers.tolist(),
        "times": result.times.tolist(),
        "shapes": {
            "truth": list(result.truth.shape),
            "psf": list(result.psf.shape),
            "sensor": list(result.sensor.shape),
            "views": list(result.views.shape),
            **extra_shapes,
        },
        **imperfections,
    }


def check_output_folder(folder: str | Path, *, overwrite: bool = False) -> Path:
    """Check, before any computation, that a simulation can be written to ``folder``; return it as
    a Path.

    Refused: a ``folder`` that is a file; a non-empty one unless ``overwrite`` (which replaces
    only :data:`OUTPUT_FILES` and :data:`OPTIONAL_OUTPUT_FILES`, never other files, so one of
    those names taken by a folder is refused too); one that cannot be created or written in (a
    real probe of the folder, or of its nearest existing parent when it does not exist yet).
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise ValueError(f"{folder} is not empty; choose another folder or pass --overwrite")
    existing = folder.resolve()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{folder}: cannot create it, {existing} is a file")
    check_writable_folder(existing, str(folder))
    if folder.is_dir():
        for name in OUTPUT_FILES + OPTIONAL_OUTPUT_FILES:
            check_output_file(folder / name, overwrite=True)
    return folder


def output_bytes(config: SimulationConfig) -> int:
    """Bytes of the files :func:`write_simulation` writes for ``config``, about (float32 arrays,
    the headers and text files left out): truth ``T Z Y X`` (and, with a field margin ``m``, the
    padded ``T Z (Y + 2m) (X + 2m)``), PSF ``V Z c^2`` (``c = 2 r + 1``, the system's crop),
    sensor ``T H W``, views ``T V Y X``, dark frames ``D H W`` and a flat ``H W``. Known from the
    configuration, so a disk without room is refused before the simulation runs."""
    system = load_system(config.system)
    depths = len(parse_depths(config.depths_um))
    frames, size, margin = config.frames, config.view_size, config.field_margin_px
    height, width = system.sensor_shape
    crop = 2 * system.crop_radius_px + 1
    voxels = frames * depths * size * size
    if margin:
        voxels += frames * depths * (size + 2 * margin) ** 2
    pixels = frames * height * width + frames * system.n_lenslets * size * size
    pixels += system.n_lenslets * depths * crop * crop
    if config.imperfections is not None:
        flat = 1 if config.imperfections.flat else 0
        pixels += (config.imperfections.dark_frames + flat) * height * width
    return 4 * (voxels + pixels)


def write_simulation(result: Simulation, folder: str | Path, *, overwrite: bool = False) -> Path:
    """Write the files of the module docstring into ``folder``.

    A non-empty ``folder`` is refused unless ``overwrite`` (then only fgat's files are replaced,
    and fgat's optional files that this simulation does not have are removed, so none of another
    run's is left beside it). A write that fails (a full disk) removes the files this call wrote
    and the folder when this call made it: no partial simulation is left.
    """
    folder = check_output_folder(folder, overwrite=overwrite)
    made = [part for part in (folder, *folder.absolute().parents) if not part.exists()]
    folder.mkdir(parents=True, exist_ok=True)
    written: list[str] = []
    try:
        _write_files(result, folder, written)
    except BaseException:
        for name in written:
            (folder / name).unlink(missing_ok=True)
        for part in made:  # the folders this call made, deepest first
            with contextlib.suppress(OSError):
                part.rmdir()
        raise
    return folder


def _write_files(result: Simulation, folder: Path, written: list[str]) -> None:
    """The files of :func:`write_simulation` into the existing ``folder``; the name of each one
    written is appended to ``written`` as soon as it is there."""
    voxel = result.voxel_size_um
    time = "T" if result.is_sequence else ""
    stack = partial(
        write_tiff, voxel_size_um=voxel, metadata=volume_entries("up", result.depths_um)
    )
    psf_entries = volume_entries("up", result.depths_um, content="psf")
    arrays = {
        "truth.ome.tif": (stack, result.truth, {"axes": time + "ZYX"}),
        "psf.ome.tif": (stack, result.psf, {"axes": "CZYX", "metadata": psf_entries}),
        "sensor.ome.tif": (write_tiff, result.sensor, {"axes": time + "YX"}),
        "views.ome.tif": (
            write_tiff,
            result.views,
            {"axes": time + "CYX", "voxel_size_um": voxel[1:]},
        ),
        "truth_padded.ome.tif": (stack, result.truth_padded, {"axes": time + "ZYX"}),
        "dark.ome.tif": (write_tiff, result.dark, {"axes": "TYX"}),
        "flat.ome.tif": (write_tiff, result.flat, {"axes": "YX"}),
    }
    for name, (write, array, options) in arrays.items():
        if array is not None:
            write(folder / name, array, **options)
            written.append(name)
    write_centers(folder / "centers.csv", result.centers)
    written.append("centers.csv")
    drawn = result.imperfections
    if drawn is not None and len(drawn.hot_pixels):
        counts = float(result.config.imperfections.hot_pixel_counts)
        lines = ["row,col,counts"] + [f"{row},{col},{counts:g}" for row, col in drawn.hot_pixels]
        with atomic_path(folder / "hot_pixels.csv") as temporary:
            temporary.write_text("\n".join(lines) + "\n")
        written.append("hot_pixels.csv")
    for name in set(OPTIONAL_OUTPUT_FILES) - set(written):
        stale = folder / name
        if stale.is_file():
            stale.unlink()
    with atomic_path(folder / "params.yaml") as temporary:
        temporary.write_text(yaml.safe_dump(_parameters(result), sort_keys=False))
    written.append("params.yaml")
