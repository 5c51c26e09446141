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

A dynamic phantom (``moving_beads``, ``beating_shell``) with ``frames > 1`` gives a sequence: the
truth is ``(T, Z, Y, X)``, the sensor ``(T, H, W)`` and the views ``(T, V, Y, X)``, at the
normalised times :func:`frame_times` (the same optics and one photon scale for every frame).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml

from fgat import __version__
from fgat.io import (
    atomic_path,
    check_fields,
    check_output_file,
    check_writable_folder,
    coerce_fields,
    parse_overrides,
    write_tiff,
    yaml_fields,
)
from fgat.optics.calibration import check_view_order
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM, check_optics
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import FLFMSystem, load_system, parse_depths
from fgat.optics.zernike import DEFAULT_INDICES
from fgat.phantoms import (
    beads,
    beating_shell,
    line_sphere,
    moving_beads,
    noisy_measurement,
    reticular,
)
from fgat.resources import check_memory, operator_memory

PHANTOMS = {
    "beads": beads,
    "line_sphere": line_sphere,
    "reticular": reticular,
    "moving_beads": moving_beads,
    "beating_shell": beating_shell,
}
DYNAMIC_PHANTOMS = ("moving_beads", "beating_shell")  # functions of (shape, times, ...)
OUTPUT_FILES = (
    "truth.ome.tif",
    "psf.ome.tif",
    "sensor.ome.tif",
    "views.ome.tif",
    "centers.csv",
    "params.yaml",
)


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
        ``kind`` (``beads``, ``line_sphere``, ``reticular``, or the dynamic ``moving_beads`` and
        ``beating_shell``) and that phantom's keyword arguments (``seed`` defaults to the
        simulation seed where the phantom takes one).
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
    photons: float | None = 1000.0
    background: float = 0.0
    read_noise: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("phantom", "zernike", "intercepts", "slopes", "aberrations"):
            setattr(self, name, parse_overrides(getattr(self, name)))
        coerce_fields(self)
        if isinstance(self.aberrations, dict):
            check_fields("aberrations", Aberrations, self.aberrations)
            self.aberrations = Aberrations(**self.aberrations)

    @classmethod
    def from_yaml(cls, path: str | Path) -> SimulationConfig:
        """Read a config file; errors name the file and the field."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"simulation config {path} does not exist")
        fields = yaml_fields(path.read_text(), str(path), cls)
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
        parse_depths(self.depths_um)


def check_phantom_options(phantom: dict) -> None:
    """Raise ``ValueError`` if ``phantom`` (``kind`` and keyword options) names an option its
    function does not take, or lacks one it requires, listing the valid options (from the
    function's signature; the shape and times are the simulation's)."""
    kind = phantom["kind"]
    parameters = {
        name: parameter
        for name, parameter in inspect.signature(PHANTOMS[kind]).parameters.items()
        if name not in ("shape", "times")
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
    ``views`` have a leading time axis, acquired at ``times`` (normalised, ``(T,)``)."""

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


def make_phantom(config: SimulationConfig, shape: tuple[int, int, int], times=None) -> np.ndarray:
    """The ground truth of ``config.phantom`` on ``shape``: ``(Z, Y, X)`` for a static phantom or
    a single frame, ``(T, Z, Y, X)`` for a dynamic one at ``times`` (normalised; default
    :func:`frame_times` of ``config.frames``)."""
    options = {key: value for key, value in config.phantom.items() if key != "kind"}
    kind = config.phantom["kind"]
    check_phantom_options(config.phantom)
    try:
        if kind == "reticular":
            return reticular(options["path"], shape)
        if kind != "beating_shell":  # the shell is deterministic
            options.setdefault("seed", config.seed)
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


def true_psf_model(config: SimulationConfig, system: FLFMSystem, depths: list[float]) -> JPGM:
    """The JPGM with the configuration's true aberrations and shifts set (float64)."""
    return OpticsSpec(system, tuple(depths), **true_optics(config, system.n_lenslets)).jpgm(
        dtype=torch.float64
    )


def simulate(config: SimulationConfig) -> Simulation:
    """Phantom, PSF stack, noise-free views, sensor image with noise, and the views cropped from it.

    Everything that can be known from the configuration is checked first (fields, optics, views
    on the sensor, sampling, memory: :func:`simulation_memory`), so a request that cannot succeed
    fails before the phantom is drawn.
    """
    config.validate()
    system = load_system(config.system)
    depths = parse_depths(config.depths_um)
    shape = (len(depths), config.view_size, config.view_size)
    model = true_psf_model(config, system, depths)
    model.check_sampling()
    centers = system.lenslet_centers_px()
    # Raises if a view leaves the sensor (the sensor stood in for by a zero-stride tensor).
    FLFMOperator.views_from_sensor(
        torch.zeros(()).expand(system.sensor_shape), centers, config.view_size
    )
    check_memory(
        "the phantom, PSF stack and forward model",
        simulation_memory(config, model, shape),
        hint="reduce view_size, depths_um or frames",
    )
    truth = make_phantom(config, shape)
    with torch.no_grad():
        psf = model()
    operator = FLFMOperator(psf, shape)
    clean = [
        FLFMOperator.sensor(
            operator.forward(torch.from_numpy(volume).double()).clamp(min=0),
            centers,
            system.sensor_shape,
        ).numpy()
        for volume in truth.reshape(-1, *shape)
    ]
    sensor = camera(clean, config).reshape(*truth.shape[:-3], *system.sensor_shape)
    views = FLFMOperator.views_from_sensor(
        torch.from_numpy(sensor), centers, config.view_size
    ).numpy()
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
    )


# Bytes per voxel a phantom function holds at its peak beyond its float32 frames: coordinate
# grids, distances and exponentials of the whole volume for the ones drawn analytically.
PHANTOM_SCRATCH_BYTES = {
    "beads": 8,
    "moving_beads": 8,
    "line_sphere": 64,
    "beating_shell": 72,
    "reticular": 8,
}


def simulation_memory(config: SimulationConfig, model: JPGM, shape: tuple[int, int, int]) -> int:
    """Peak memory of :func:`simulate` in bytes, a rough upper bound from the shapes.

    With ``T`` frames of ``N = Z Y X`` voxels: the phantom (``T N`` float32 frames, twice for
    the final scaling, plus :data:`PHANTOM_SCRATCH_BYTES` per voxel and 48 bytes per bead
    position), the float64 PSF stack (:meth:`fgat.optics.psf.JPGM.memory_bytes`), the float64
    forward operator and one projection (:func:`fgat.resources.operator_memory`) with the float64
    copy of one frame, and the sensor images (float64 clean, noisy and float32 stored, ``T H W``)
    and views (``T V Y X`` float32).
    """
    frames = config.frames
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
    views = frames * n_views * shape[1] * shape[2] * 4
    return int(phantom + model.memory_bytes() + forward + camera_images + views)


def camera(clean: list[np.ndarray], config: SimulationConfig) -> np.ndarray:
    """Noisy float32 sensor frames ``(T, H, W)`` from noise-free ones, one frame at a time (memory):
    one photon scale for the whole sequence (``config.photons`` expected counts at its brightest
    pixel) and independent noise per frame (seed ``(config.seed, k)``; a single frame uses
    ``config.seed``)."""
    if len(clean) == 1:
        return noisy_measurement(
            clean[0],
            photons=config.photons,
            background=config.background,
            read_noise=config.read_noise,
            seed=config.seed,
        )[None]
    peaks = [float(frame.max()) for frame in clean]
    top = max(max(peaks), 1e-30)
    return np.stack(
        [
            noisy_measurement(
                frame,
                background=config.background,
                read_noise=config.read_noise,
                photons=None if config.photons is None else config.photons * max(peak / top, 1e-12),
                seed=[config.seed, k],
            )
            for k, (frame, peak) in enumerate(zip(clean, peaks))
        ]
    )


def write_centers(path: str | Path, centers: np.ndarray) -> None:
    """Write lenslet centres ``(V, 2)`` as ``row,col`` CSV (0-based pixels), atomically."""
    lines = ["row,col"] + [
        f"{row:.6f},{col:.6f}" for row, col in np.asarray(centers, dtype=np.float64)
    ]
    with atomic_path(path) as temporary:
        temporary.write_text("\n".join(lines) + "\n")


CENTER_HEADERS = {"row,col": (0, 1), "col,row": (1, 0)}


def read_centers(path: str | Path) -> np.ndarray:
    """Lenslet centres ``(V, 2)`` (row, col), 0-based, from a CSV or a MATLAB ``.mat``.

    A CSV starts with a header naming its columns, ``row,col`` or ``col,row`` (case and spaces
    ignored), then one line per view; a ``.mat`` holds one ``(V, 2)`` (row, col) array in
    MATLAB's 1-based indices, converted. Every user of centres gets them checked: finite, and
    no two closer than one pixel (each view needs its own lenslet).
    """
    from fgat.io import read_mat

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
                f"{path}: header {lines[0]!r}; expected 'row,col' or 'col,row' "
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


def _parameters(result: Simulation) -> dict:
    config = dataclasses.asdict(result.config)
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
        },
    }


def check_output_folder(folder: str | Path, *, overwrite: bool = False) -> Path:
    """Check, before any computation, that a simulation can be written to ``folder``; return it as
    a Path.

    Refused: a ``folder`` that is a file; a non-empty one unless ``overwrite`` (which replaces
    only :data:`OUTPUT_FILES`, never other files, so one of those names taken by a folder is
    refused too); one that cannot be created or written in (a real probe of the folder, or of
    its nearest existing parent when it does not exist yet).
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
        for name in OUTPUT_FILES:
            check_output_file(folder / name, overwrite=True)
    return folder


def write_simulation(result: Simulation, folder: str | Path, *, overwrite: bool = False) -> Path:
    """Write the files of the module docstring into ``folder``.

    A non-empty ``folder`` is refused unless ``overwrite`` (then only fgat's files are replaced).
    """
    folder = check_output_folder(folder, overwrite=overwrite)
    folder.mkdir(parents=True, exist_ok=True)
    voxel = result.voxel_size_um
    time = "T" if result.is_sequence else ""
    write_tiff(folder / "truth.ome.tif", result.truth, axes=time + "ZYX", voxel_size_um=voxel)
    write_tiff(folder / "psf.ome.tif", result.psf, axes="CZYX", voxel_size_um=voxel)
    write_tiff(folder / "sensor.ome.tif", result.sensor, axes=time + "YX")
    write_tiff(folder / "views.ome.tif", result.views, axes=time + "CYX", voxel_size_um=voxel[1:])
    write_centers(folder / "centers.csv", result.centers)
    with atomic_path(folder / "params.yaml") as temporary:
        temporary.write_text(yaml.safe_dump(_parameters(result), sort_keys=False))
    return folder
