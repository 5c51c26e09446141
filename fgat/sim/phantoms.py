"""Synthetic fluorescence scenes and the FLFM measurement model.

Every phantom is a float32 NumPy volume ``(Z, Y, X)`` with values in ``[0, 1]``, reproducible
from its ``seed``, on any grid. Sizes are in voxels.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from fgat._core.validation import check_number
from fgat.io.images import read_tiff

# Random sequential addition cannot fill more than the densest packing of spheres (Kepler).
KEPLER_DENSITY = np.pi / (3 * np.sqrt(2))


def _range(
    name: str, value, *, minimum: float | None = None, above: float | None = None
) -> tuple[float, float]:
    """A ``(low, high)`` pair of finite numbers with ``low <= high``, or ``ValueError`` naming
    ``name``."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ValueError(f"{name} must be two numbers (low, high), got {value!r}")
    low, high = (check_number(name, v, minimum=minimum, above=above) for v in value)
    if low > high:
        raise ValueError(f"{name} must be (low, high) with low <= high, got {value!r}")
    return low, high


def _vector(
    name: str, value, size: int, *, minimum: float | None = None, broadcast: bool = True
) -> np.ndarray:
    """``size`` finite numbers (or one, repeated, when ``broadcast``), or ``ValueError`` naming
    ``name``."""
    values = np.atleast_1d(np.asarray(value, dtype=object))
    if values.ndim != 1 or len(values) not in ((1, size) if broadcast else (size,)):
        raise ValueError(
            f"{name} must be {'one number or ' if broadcast else ''}{size} numbers, got {value!r}"
        )
    return np.broadcast_to(
        np.array([check_number(name, v, minimum=minimum) for v in values]), (size,)
    )


def _times(times) -> np.ndarray:
    """Normalised times ``(T,)``: finite numbers, at least one."""
    values = np.asarray(times, dtype=np.float64).reshape(-1)
    if values.size == 0 or not np.isfinite(values).all():
        raise ValueError(f"times must be one or more finite numbers, got {times!r}")
    return values


def _shape3(shape: Sequence[int]) -> tuple[int, int, int]:
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"shape must be three positive sizes (Z, Y, X), got {shape!r}")
    return shape


def _grid(shape: tuple[int, int, int]) -> tuple[np.ndarray, ...]:
    return tuple(np.arange(n, dtype=np.float32) for n in shape)


def _add_gaussian(volume: np.ndarray, center: np.ndarray, sigma: float, amplitude: float) -> None:
    """Add ``amplitude exp(-|x - c|^2 / (2 sigma^2))`` inside its 4-sigma box, in place."""
    radius = max(1, int(np.ceil(4 * sigma)))
    low = np.maximum(np.floor(center).astype(int) - radius, 0)
    high = np.minimum(np.floor(center).astype(int) + radius + 1, volume.shape)
    if np.any(high <= low):
        return
    axes = [np.arange(lo, hi, dtype=np.float32) - c for lo, hi, c in zip(low, high, center)]
    profile = [np.exp(-0.5 * (a / sigma) ** 2) for a in axes]
    volume[low[0] : high[0], low[1] : high[1], low[2] : high[2]] += amplitude * (
        profile[0][:, None, None] * profile[1][None, :, None] * profile[2][None, None, :]
    )


def bead_positions(
    shape: Sequence[int],
    n_beads: int,
    *,
    min_spacing: float = 0.0,
    margin: float | Sequence[float] = 0.0,
    rng: np.random.Generator,
    keep: Callable[[np.ndarray], bool] | None = None,
) -> np.ndarray:
    """Random positions ``(N, 3)`` (z, y, x) at least ``min_spacing`` apart and ``margin`` (one
    value or one per axis) from the border, by rejection sampling; with ``keep``, only positions
    ``(3,)`` for which it is true (e.g. outside an object).

    Requests that cannot be met are refused before sampling: more beads than voxels in the
    allowed region, or, with ``min_spacing``, more spheres of diameter ``min_spacing`` than the
    densest packing fits in the region grown by ``min_spacing / 2`` on every side. A request
    that sampling fails to meet (1000 draws per bead) raises as well.
    """
    shape = np.asarray(_shape3(shape), dtype=np.float64)
    n_beads = check_number("n_beads", n_beads, integer=True, minimum=1)
    min_spacing = check_number("min_spacing", min_spacing, minimum=0)
    low = _vector("margin", margin, 3, minimum=0).astype(np.float64)
    high = shape - 1 - low
    size = tuple(int(n) for n in shape)
    if np.any(high < low):
        raise ValueError(f"margin {margin} leaves no room in a volume of shape {size}")
    voxels = int(np.prod(np.floor(high - low) + 1))
    if n_beads > voxels:
        raise ValueError(
            f"n_beads = {n_beads} is more than the {voxels} voxels where beads can go in shape "
            f"{size} (margin {margin}); at most one bead per voxel"
        )
    if min_spacing > 0:
        fit = int(KEPLER_DENSITY * np.prod(high - low + min_spacing) / (np.pi * min_spacing**3 / 6))
        if n_beads > fit:
            raise ValueError(
                f"n_beads = {n_beads} beads {min_spacing:g} voxels apart cannot fit in shape "
                f"{size} (margin {margin}): at most {fit} even densely packed; lower n_beads or "
                "min_spacing"
            )
    if min_spacing == 0 and keep is None:
        return rng.uniform(low, high, (n_beads, 3))
    positions = np.empty((n_beads, 3))
    placed = attempts = 0
    while placed < n_beads:
        attempts += 1
        if attempts > 1000 * n_beads:
            raise ValueError(
                f"could not place {n_beads} beads {min_spacing:g} voxels apart in shape {size} "
                f"(placed {placed} in {attempts - 1} draws); lower n_beads or min_spacing"
            )
        candidate = rng.uniform(low, high)
        if (keep is None or keep(candidate)) and (
            placed == 0
            or np.linalg.norm(positions[:placed] - candidate, axis=1).min() >= min_spacing
        ):
            positions[placed] = candidate
            placed += 1
    return positions


def beads(
    shape: Sequence[int],
    n_beads: int,
    *,
    sigma: float = 0.0,
    intensity_range: tuple[float, float] = (0.5, 1.0),
    min_spacing: float = 0.0,
    margin: float | Sequence[float] = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Beads at random positions: single-voxel points (``sigma = 0``) or Gaussians of std ``sigma``.

    Parameters
    ----------
    shape : (Z, Y, X)
        Volume size in voxels.
    n_beads : int
        Number of beads.
    sigma : float
        Gaussian standard deviation in voxels; 0 puts each bead on its nearest voxel.
    intensity_range : (float, float)
        Peak intensities are uniform in this range (then the volume is scaled to max 1).
    min_spacing : float
        Minimum distance between beads, voxels.
    margin : float or (float, float, float)
        Minimum distance from the border, voxels (one value or per axis z, y, x).
    seed : int
        Random seed; the same seed gives the same volume.
    """
    shape = _shape3(shape)
    sigma = check_number("sigma", sigma, minimum=0)
    intensity_range = _range("intensity_range", intensity_range, minimum=0)
    rng = np.random.default_rng(check_number("seed", seed, integer=True, minimum=0))
    positions = bead_positions(shape, n_beads, min_spacing=min_spacing, margin=margin, rng=rng)
    intensities = rng.uniform(*intensity_range, size=len(positions))
    volume = np.zeros(shape, dtype=np.float32)
    for position, intensity in zip(positions, intensities):
        if sigma > 0:
            _add_gaussian(volume, position, sigma, intensity)
        else:
            z, y, x = np.round(position).astype(int)
            volume[z, y, x] += intensity
    return _unit_max(volume)


def _unit_max(volume: np.ndarray) -> np.ndarray:
    peak = volume.max()
    return (volume / peak).astype(np.float32) if peak > 0 else volume.astype(np.float32)


def _segment_distance(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Distance of ``(..., 3)`` points to the segment ``start``-``end``."""
    direction = end - start
    t = np.clip(((points - start) @ direction) / max(direction @ direction, 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (start + t[..., None] * direction), axis=-1)


def line_sphere(
    shape: Sequence[int],
    *,
    n_lines: int = 6,
    n_spheres: int = 6,
    line_width: float = 1.0,
    radius_range: tuple[float, float] = (3.0, 8.0),
    shell_width: float = 1.5,
    hollow_fraction: float = 0.5,
    seed: int = 0,
) -> np.ndarray:
    """Line-and-sphere phantom (Fig. S11a): straight filaments and filled or hollow spheres.

    Lines run between two random points on the volume's faces with a Gaussian cross-section of
    std ``line_width``; spheres have radii in ``radius_range``, and a fraction
    ``hollow_fraction`` of them are shells of thickness ``shell_width`` (voxels). Edges are
    smoothed over one voxel so the phantom is band-limited enough for a grid.
    """
    shape = _shape3(shape)
    n_lines = check_number("n_lines", n_lines, integer=True, minimum=0)
    n_spheres = check_number("n_spheres", n_spheres, integer=True, minimum=0)
    if n_lines + n_spheres == 0:
        raise ValueError("n_lines and n_spheres are both 0: the phantom would be empty")
    line_width = check_number("line_width", line_width, above=0)
    radius_range = _range("radius_range", radius_range, above=0)
    shell_width = check_number("shell_width", shell_width, above=0)
    hollow_fraction = check_number("hollow_fraction", hollow_fraction, minimum=0, maximum=1)
    rng = np.random.default_rng(check_number("seed", seed, integer=True, minimum=0))
    points = np.stack(np.meshgrid(*_grid(shape), indexing="ij"), axis=-1)
    extent = np.asarray(shape, dtype=np.float64) - 1
    volume = np.zeros(shape, dtype=np.float32)
    for _ in range(n_lines):
        start, end = rng.uniform(0, extent), rng.uniform(0, extent)
        start[rng.integers(3)] = 0.0  # enter through a low face, leave through a high one
        axis = rng.integers(3)
        end[axis] = extent[axis]
        distance = _segment_distance(points, start, end)
        volume = np.maximum(
            volume, rng.uniform(0.6, 1.0) * np.exp(-0.5 * (distance / line_width) ** 2)
        )
    for _ in range(n_spheres):
        radius = rng.uniform(*radius_range)
        center = rng.uniform(radius, np.maximum(extent - radius, radius))
        distance = np.linalg.norm(points - center, axis=-1)
        inside = 0.5 * (1 - np.tanh((distance - radius) / 0.5))
        if rng.random() < hollow_fraction:
            inside *= 0.5 * (1 + np.tanh((distance - (radius - shell_width)) / 0.5))
        volume = np.maximum(volume, rng.uniform(0.6, 1.0) * inside)
    return _unit_max(volume)


def moving_beads(
    shape: Sequence[int],
    times: Sequence[float],
    n_beads: int,
    *,
    sigma: float = 1.0,
    velocity: Sequence[float] = (0.0, 4.0, 0.0),
    rotation_deg: float = 30.0,
    min_spacing: float = 0.0,
    margin: float | Sequence[float] = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Gaussian beads that translate and rotate rigidly over time, a truth volume per time point.

    At normalised time ``t`` a bead's canonical position ``p`` (voxels, (z, y, x)) moves to
    ``c + R(rotation_deg t) (p - c) + velocity t``: a rotation about the z axis through the volume
    centre ``c`` followed by a translation. Beads are drawn as by :func:`beads` (``seed``) at
    ``t = 0``; every frame is scaled by the same factor, so intensities are comparable across time.

    Returns
    -------
    numpy.ndarray
        ``(T, Z, Y, X)`` float32 volumes, maximum 1 over the whole sequence.
    """
    shape = _shape3(shape)
    times = _times(times)
    sigma = check_number("sigma", sigma, above=0)
    velocity = _vector("velocity", velocity, 3, broadcast=False)
    rotation_deg = check_number("rotation_deg", rotation_deg)
    rng = np.random.default_rng(check_number("seed", seed, integer=True, minimum=0))
    positions = bead_positions(shape, n_beads, min_spacing=min_spacing, margin=margin, rng=rng)
    intensities = rng.uniform(0.5, 1.0, size=len(positions))
    center = (np.asarray(shape, dtype=np.float64) - 1) / 2
    frames = np.zeros((len(times), *shape), dtype=np.float32)
    for frame, t in zip(frames, times):
        angle = np.deg2rad(rotation_deg) * t
        rotation = np.array(
            [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
        )
        moved = (
            center + (positions - center) @ rotation.T + np.asarray(velocity, dtype=np.float64) * t
        )
        for position, intensity in zip(moved, intensities):
            _add_gaussian(frame, position, sigma, intensity)
    return _unit_max(frames)


def sphere_lattice(n: int) -> np.ndarray:
    """``n`` quasi-uniform unit vectors (z, y, x) on the sphere (Fibonacci lattice)."""
    k = np.arange(n, dtype=np.float64) + 0.5
    z = 1 - 2 * k / n
    angle = np.pi * (1 + np.sqrt(5)) * k
    ring = np.sqrt(1 - z**2)
    return np.stack([z, ring * np.sin(angle), ring * np.cos(angle)], axis=1)


def beating_shell(
    shape: Sequence[int],
    times: Sequence[float],
    *,
    radii: Sequence[float] | None = None,
    thickness: float = 2.0,
    contraction: float = 0.25,
    beats: float = 1.0,
    nuclei: int = 0,
) -> np.ndarray:
    """An ellipsoidal shell that contracts and relaxes (a stand-in for a beating heart, Fig. S12).

    At normalised time ``t`` the shell's semi-axes are ``radii (1 - contraction sin^2(pi beats t))``
    (voxels, (z, y, x); default 0.35 of each size). With ``nuclei = 0`` the shell is a wall of
    ``thickness`` voxels with smooth (one-voxel) edges around the surface of the scaled ellipsoid;
    with ``nuclei = N`` it is ``N`` Gaussian blobs (sigma ``thickness / 2``, unit peak) at fixed
    points of the surface (:func:`sphere_lattice`) that move with it, as the labelled nuclei of
    the myl7:H2A-mCherry zebrafish heart in Fig. S12.

    Returns
    -------
    numpy.ndarray
        ``(T, Z, Y, X)`` float32 volumes in [0, 1].
    """
    shape = _shape3(shape)
    times = _times(times)
    thickness = check_number("thickness", thickness, above=0)
    radii = _vector(
        "radii", radii if radii is not None else [0.35 * n for n in shape], 3, broadcast=False
    )
    if np.any(radii <= thickness):
        raise ValueError(
            f"radii must be three semi-axes larger than the wall thickness {thickness}, got {radii}"
        )
    if not 0 <= check_number("contraction", contraction) < 1:
        raise ValueError(f"contraction must be in [0, 1), got {contraction}")
    beats = check_number("beats", beats)
    nuclei = check_number("nuclei", nuclei, integer=True, minimum=0)
    center = (np.asarray(shape, dtype=np.float64) - 1) / 2
    frames = np.zeros((len(times), *shape), dtype=np.float32)
    directions = sphere_lattice(nuclei) if nuclei else None
    points = (
        None if nuclei else np.stack(np.meshgrid(*_grid(shape), indexing="ij"), axis=-1) - center
    )
    for frame, t in zip(frames, times):
        scaled = radii * (1 - contraction * np.sin(np.pi * beats * t) ** 2)
        if nuclei:
            for position in center + directions * scaled:
                _add_gaussian(frame, position, thickness / 2, 1.0)
            np.minimum(frame, 1.0, out=frame)
            continue
        frame[:] = shell_wall(points, scaled, thickness, edge=0.5)
    return frames


def shell_wall(points: np.ndarray, radii, thickness: float, edge: float) -> np.ndarray:
    """A smooth ellipsoidal wall ``0.5 (1 - tanh((|d| - thickness / 2) / edge))`` at points
    ``(..., 3)`` (z, y, x) from the ellipsoid's centre, ``d = (|p / radii| - 1) mean(radii)`` the
    distance to the surface of semi-axes ``radii`` (exact for a sphere; for an ellipsoid the
    ellipsoidal radius times the mean semi-axis, so the wall is the difference of two homothetic
    ellipsoids). Every length in one unit (voxels or um). Returns ``(...)`` in [0, 1]."""
    radii = np.asarray(radii, dtype=np.float64)
    distance = (np.linalg.norm(points / radii, axis=-1) - 1) * radii.mean()
    return 0.5 * (1 - np.tanh((np.abs(distance) - thickness / 2) / edge))


def shell_beads(
    shape: Sequence[int],
    *,
    voxel_size_um: Sequence[float],
    diameter_um: float = 15.0,
    wall_um: float = 1.0,
    n_beads: int = 20,
    sigma: float = 1.0,
    intensity_range: tuple[float, float] = (0.5, 1.0),
    clearance_um: float = 2.0,
    min_spacing: float = 4.0,
    margin: float | Sequence[float] = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """A hollow fluorescent microsphere with beads around it: a spherical shell of outer diameter
    ``diameter_um`` and wall ``wall_um`` (um, round in the sample whatever the voxel sizes) at
    the volume's centre, its wall :func:`shell_wall` with unit peak and edges smoothed over half
    the coarsest voxel side, and ``n_beads`` Gaussian beads (std ``sigma`` voxels, peaks uniform
    in ``intensity_range``) drawn as by :func:`beads` at least ``clearance_um`` outside the
    wall. ``fgat simulate`` supplies ``voxel_size_um``, the grid's ``(dz, dy, dx)`` in um; with
    a field margin the phantom is drawn on the whole object, so beads fall beyond the views'
    field too.

    Parameters
    ----------
    shape : (Z, Y, X)
        Volume size in voxels.
    voxel_size_um : (dz, dy, dx)
        Voxel size in um.
    diameter_um, wall_um : float
        Outer diameter of the shell and thickness of its wall, um.
    n_beads : int
        Number of beads (0: the shell alone).
    sigma : float
        Bead standard deviation, voxels.
    intensity_range : (float, float)
        Bead peaks are uniform in this range (the wall's peak is 1).
    clearance_um : float
        Smallest distance from a bead centre to the wall's outer surface, um.
    min_spacing : float
        Minimum distance between beads, voxels.
    margin : float or (float, float, float)
        Minimum distance of the beads from the border, voxels (one value or per axis z, y, x).
    seed : int
        Random seed of the beads.

    Returns
    -------
    numpy.ndarray
        ``(Z, Y, X)`` float32 in [0, 1].
    """
    shape = _shape3(shape)
    voxel = _vector("voxel_size_um", voxel_size_um, 3, minimum=0, broadcast=False)
    if np.any(voxel <= 0):
        raise ValueError(f"voxel_size_um must be three positive sizes, got {voxel_size_um!r}")
    diameter_um = check_number("diameter_um", diameter_um, above=0)
    wall_um = check_number("wall_um", wall_um, above=0)
    if 2 * wall_um >= diameter_um:
        raise ValueError(
            f"wall_um = {wall_um:g} must be under half of diameter_um = {diameter_um:g}"
        )
    n_beads = check_number("n_beads", n_beads, integer=True, minimum=0)
    sigma = check_number("sigma", sigma, above=0)
    intensity_range = _range("intensity_range", intensity_range, minimum=0)
    clearance_um = check_number("clearance_um", clearance_um, minimum=0)
    rng = np.random.default_rng(check_number("seed", seed, integer=True, minimum=0))
    center = (np.asarray(shape, dtype=np.float64) - 1) / 2
    radius = (diameter_um - wall_um) / 2  # the wall's mid-surface
    points = (np.stack(np.meshgrid(*_grid(shape), indexing="ij"), axis=-1) - center) * voxel
    volume = shell_wall(points, [radius] * 3, wall_um, edge=0.5 * voxel.max()).astype(np.float32)
    if n_beads:
        reach = diameter_um / 2 + clearance_um
        positions = bead_positions(
            shape,
            n_beads,
            min_spacing=min_spacing,
            margin=margin,
            rng=rng,
            keep=lambda p: np.linalg.norm((p - center) * voxel) >= reach,
        )
        for position, intensity in zip(positions, rng.uniform(*intensity_range, len(positions))):
            _add_gaussian(volume, position, sigma, intensity)
    return _unit_max(volume)


def reticular(path: str | Path, shape: Sequence[int]) -> np.ndarray:
    """A ground-truth volume read from a TIFF (e.g. the 3DGAT reticular phantom), resampled by
    linear interpolation to ``shape`` and scaled to maximum 1."""
    from scipy.ndimage import zoom  # SciPy loaded when used: keeps start-up fast

    shape = _shape3(shape)
    volume = read_tiff(path, ndim=3, axes="(Z, Y, X)", nonnegative=True).astype(np.float32)
    factors = [n / m for n, m in zip(shape, volume.shape)]
    resampled = zoom(volume, factors, order=1, grid_mode=True, mode="nearest")
    return _unit_max(np.clip(resampled, 0, None))


def noisy_measurement(
    clean: np.ndarray,
    *,
    photons: float | None = None,
    background: float | np.ndarray = 0.0,
    read_noise: float = 0.0,
    seed: int | Sequence[int] = 0,
    offset: float = 0.0,
) -> np.ndarray:
    """Camera model on a noise-free image: scale, background offset, Poisson and read noise.

    Parameters
    ----------
    clean : numpy.ndarray
        Non-negative noise-free intensities (any shape).
    photons : float, optional
        Photon budget: the expected count at the brightest pixel. ``None`` keeps the clean
        intensities and adds no shot noise.
    background : float or numpy.ndarray
        Offset (counts) added to every pixel before the shot noise: a constant, or a map of
        ``clean``'s shape (e.g. the dark signal of hot pixels).
    read_noise : float
        Standard deviation of additive Gaussian read noise (counts).
    seed : int or sequence of int
        Random seed (a sequence, e.g. ``(seed, frame)``, seeds independent streams).
    offset : float
        Camera bias (counts) added after the shot noise: an electronic offset, without shot
        noise of its own (what a dark frame shows besides read noise).

    Returns
    -------
    numpy.ndarray
        float32 image in counts: ``Poisson(s clean + background) + offset +
        N(0, read_noise^2)``, ``s = photons / max(clean)``.
    """
    clean = np.asarray(clean, dtype=np.float64)
    if clean.min() < 0:
        raise ValueError("the clean image must be non-negative")
    rng = np.random.default_rng(seed)
    expected = clean
    if photons is not None:
        if not photons > 0:
            raise ValueError(f"photons must be positive, got {photons!r}")
        expected = clean * (photons / max(clean.max(), 1e-30))
    expected = expected + background
    image = rng.poisson(expected).astype(np.float64) if photons is not None else expected
    if offset:
        image = image + offset
    if read_noise > 0:
        image = image + rng.normal(0.0, read_noise, image.shape)
    return image.astype(np.float32)


def lenslet_flat(
    sensor_shape: Sequence[int],
    centers: np.ndarray,
    radius_px: float,
    gains: Sequence[float] | None = None,
    *,
    edge_px: float = 1.0,
) -> np.ndarray:
    """A noise-free white-light (flat-field) image of an MLA, ``(H, W)`` float64: every lenslet's
    elemental image a uniformly lit disk of radius ``radius_px`` around its centre ``(V, 2)``
    (row, col, sub-pixel) with a smooth edge (``0.5 (1 - tanh((d - radius) / edge_px))``), times
    its gain (default 1); overlapping disks add. Its maximum is about the largest gain."""
    height, width = (int(n) for n in sensor_shape)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    radius_px = check_number("radius_px", radius_px, above=0)
    edge_px = check_number("edge_px", edge_px, above=0)
    gains = _vector("gains", 1.0 if gains is None else gains, len(centers), minimum=0)
    image = np.zeros((height, width))
    reach = int(np.ceil(radius_px + 6 * edge_px))
    for center, gain in zip(centers, gains):
        low = np.maximum(np.floor(center).astype(int) - reach, 0)
        high = np.minimum(np.floor(center).astype(int) + reach + 2, (height, width))
        if np.any(high <= low):
            continue  # the disk misses the sensor
        distance = np.hypot(
            np.arange(low[0], high[0])[:, None] - center[0],
            np.arange(low[1], high[1])[None, :] - center[1],
        )
        disk = 0.5 * (1 - np.tanh((distance - radius_px) / edge_px))
        image[low[0] : high[0], low[1] : high[1]] += gain * disk
    return image
