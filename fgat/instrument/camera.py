"""Camera model of an FLFM sensor: offset, read noise, defective pixels, pixel sensitivity.

A :class:`CameraModel` turns raw counts into offset-free, flat-fielded intensities
(:meth:`CameraModel.correct`) and says which pixels to trust (:meth:`CameraModel.valid`). It is
measured from dark frames (:func:`camera_from_dark`, the reference), or estimated from an FLFM
image alone (:func:`camera_from_image`: the dark gaps between the lenslets' views stand in for a
dark frame). :func:`flat_field` gives the relative pixel sensitivity from a uniformly lit frame.

A calibration folder stores the model as numbers in ``calibration.yaml`` (:func:`write_camera`,
:func:`read_camera`) and its maps as ``hot_pixels.ome.tif`` (uint8, 1 = defective) and
``flat.ome.tif`` (float32), both ``(H, W)``.

Plain NumPy/SciPy; counts are camera digital numbers (ADU).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage, stats

from fgat._core.validation import check_number
from fgat.io.images import read_tiff, write_tiff

MAD_TO_STD = 1.4826  # standard deviation of a normal distribution per median absolute deviation
HOT_PIXEL_SIGMA = 8.0  # a hot pixel stands this many noise standard deviations above its level
NOISY_PIXEL_FACTOR = 4.0  # a noisy (e.g. telegraph) pixel's temporal std over the read noise
NOISY_PIXEL_FALSE_RATE = 1e-9  # per-pixel false-alarm rate of the temporal-std test
SPIKE_NEIGHBOUR = 2.0  # a spike rises this many times more than its brightest neighbour
SPIKE_CURVATURE = 4.0  # a spike rises this many times more than its neighbours above the next ring
MIN_FLAT = 0.05  # pixels less sensitive than this (relative) are dead: not divided, not valid
DARK_FRACTION = 0.1  # share of an image's blocks taken as its darkest region
BLOCK = 16  # block side (pixels) of the dark-region search
MAX_HOT_PIXEL_SHARE = 0.01  # more hot pixels than this share of a sensor: no dark frame
DARK_LEVEL_SIGMA = 5.0  # a dark level this many read-noise std above an image's background: wrong
MIN_LIT_SHARE = 0.01  # an image with less than this share above the dark level is refused
HOT_PIXEL_FILE = "hot_pixels.ome.tif"
FLAT_FILE = "flat.ome.tif"


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Offset, read noise, defective pixels and pixel sensitivity of a camera.

    Attributes
    ----------
    offset : float
        Dark level (bias plus any constant background), counts.
    read_noise : float
        Standard deviation of a dark pixel, counts.
    hot_pixels : numpy.ndarray or None
        ``(H, W)`` bool, True at defective (hot, noisy) pixels; ``None``: none known.
    flat : numpy.ndarray or None
        ``(H, W)`` relative sensitivity (mean 1, :func:`flat_field`); ``None``: uniform.
    """

    offset: float
    read_noise: float
    hot_pixels: np.ndarray | None = None
    flat: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("offset", "read_noise"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise ValueError(f"camera {name} must be a number (counts), got {value!r}")
            if not math.isfinite(value) or (name == "read_noise" and value < 0):
                bound = " and >= 0" if name == "read_noise" else ""
                raise ValueError(f"camera {name} must be finite{bound} (counts), got {value}")
            object.__setattr__(self, name, float(value))
        if self.hot_pixels is not None:
            hot = np.asarray(self.hot_pixels)
            if hot.ndim != 2 or not np.isin(hot, (0, 1)).all():
                raise ValueError(
                    f"camera hot_pixels must be an (H, W) mask of 0/1 or bool, got shape "
                    f"{hot.shape} dtype {hot.dtype}"
                )
            object.__setattr__(self, "hot_pixels", hot.astype(bool))
        if self.flat is not None:
            flat = np.asarray(self.flat, dtype=np.float64)
            if flat.ndim != 2 or not np.isfinite(flat).all() or flat.min() < 0:
                raise ValueError(
                    f"camera flat must be a finite, non-negative (H, W) array, got shape "
                    f"{flat.shape}"
                )
            object.__setattr__(self, "flat", flat)
        if (
            self.hot_pixels is not None
            and self.flat is not None
            and self.hot_pixels.shape != self.flat.shape
        ):
            raise ValueError(
                f"camera hot_pixels {self.hot_pixels.shape} and flat {self.flat.shape} "
                "have different shapes"
            )

    @property
    def sensor_shape(self) -> tuple[int, int] | None:
        """``(H, W)`` of the maps, ``None`` when the model has none."""
        for array in (self.hot_pixels, self.flat):
            if array is not None:
                return tuple(int(n) for n in array.shape)
        return None

    def _check_shape(self, shape: tuple[int, ...], what: str) -> None:
        expected = self.sensor_shape
        if expected is not None and tuple(shape[-2:]) != expected:
            raise ValueError(
                f"the camera model is for a {expected[0]} x {expected[1]} sensor (its hot-pixel "
                f"or flat map), but the {what} is {shape[-2]} x {shape[-1]} (shape {tuple(shape)})"
            )

    def correct(self, image) -> np.ndarray:
        """``(image - offset) / flat`` as float64, for an image ``(H, W)`` or frames
        ``(..., H, W)``; pixels with ``flat < MIN_FLAT`` (dead) are not divided (they are not
        :meth:`valid`)."""
        image = np.asarray(image, dtype=np.float64)
        if image.ndim < 2:
            raise ValueError(f"expected an image (..., H, W), got shape {image.shape}")
        self._check_shape(image.shape, "image")
        corrected = image - self.offset
        if self.flat is not None:
            corrected = corrected / np.where(self.flat >= MIN_FLAT, self.flat, 1.0)
        return corrected

    def valid(self, shape) -> np.ndarray:
        """``(H, W)`` float64 mask for images of ``shape`` ``(..., H, W)``: 1 where a pixel can be
        trusted, 0 at hot pixels and dead ones (``flat < MIN_FLAT``)."""
        shape = tuple(int(n) for n in shape)
        if len(shape) < 2:
            raise ValueError(f"expected an image shape (..., H, W), got {shape}")
        self._check_shape(shape, "image")
        mask = np.ones(shape[-2:])
        if self.hot_pixels is not None:
            mask[self.hot_pixels] = 0.0
        if self.flat is not None:
            mask[self.flat < MIN_FLAT] = 0.0
        return mask


def _frames(data, name: str) -> np.ndarray:
    """``data`` as float64 frames ``(T, H, W)`` from ``(H, W)`` or ``(T, H, W)``, finite."""
    data = np.asarray(data, dtype=np.float64)
    if data.ndim not in (2, 3) or data.size == 0:
        raise ValueError(f"{name} must be (H, W) or (T, H, W), got shape {data.shape}")
    if not np.isfinite(data).all():
        raise ValueError(f"{name} contains NaN or Inf values")
    return data if data.ndim == 3 else data[None]


def _mad_std(values: np.ndarray) -> float:
    """Robust standard deviation: median absolute deviation from the median times 1.4826."""
    return float(MAD_TO_STD * np.median(np.abs(values - np.median(values))))


def camera_from_dark(
    dark,
    *,
    hot_sigma: float = HOT_PIXEL_SIGMA,
    noisy_factor: float = NOISY_PIXEL_FACTOR,
) -> CameraModel:
    """Camera model from dark frames (shutter closed, the exposure of the data).

    Parameters
    ----------
    dark : array-like
        ``(H, W)`` dark frame or ``(T, H, W)`` dark frames, counts.
    hot_sigma : float
        A pixel is hot when its (time-averaged) dark level exceeds ``offset + hot_sigma *
        read_noise`` (default 8: a normal pixel gets there with probability ~1e-15).
    noisy_factor : float
        With ``T > 1``, a pixel is also defective when its temporal standard deviation exceeds
        ``noisy_factor * read_noise`` (default 4; raised for few frames so that a normal pixel
        passes the test with probability ``1 - 1e-9``).

    Returns
    -------
    CameraModel
        ``offset``: median of the (time-averaged) dark levels; ``read_noise``: with ``T > 1``,
        the median of the per-pixel temporal variances, unbiased for ``T - 1`` degrees of
        freedom (chi-square median), square-rooted; with one frame the spatial robust std
        (1.4826 MAD, which includes fixed-pattern noise); ``hot_pixels`` (``None`` when none);
        no flat.
    """
    frames = _frames(dark, "dark")
    mean = frames.mean(axis=0)
    offset = float(np.median(mean))
    count = len(frames)
    if count > 1:
        variance = frames.var(axis=0, ddof=1)
        dof = count - 1
        read_noise = math.sqrt(float(np.median(variance)) * dof / stats.chi2.median(dof))
    else:
        read_noise = _mad_std(mean)
    hot = mean > offset + hot_sigma * read_noise
    if count > 1:
        bound = math.sqrt(stats.chi2.isf(NOISY_PIXEL_FALSE_RATE, dof) / dof)
        hot |= variance > (max(noisy_factor, bound) * read_noise) ** 2
    return CameraModel(offset, read_noise, hot if hot.any() else None)


def dark_frame_warning(dark: CameraModel, image, name: str = "the dark frame") -> str | None:
    """Check a camera model measured from dark frames (:func:`camera_from_dark`) against the
    FLFM ``image`` ``(H, W)`` or frames ``(T, H, W)`` it is to correct; ``name`` names the dark
    file in the messages.

    A dark frame (shutter closed, the exposure of the data) lies at or below every pixel of the
    image, within noise: the image's own dark regions (:func:`camera_from_image`) hold the same
    offset plus any stray light. Sensors have well under 1 % defective pixels.

    Returns
    -------
    str or None
        A warning when the dark level stands more than :data:`DARK_LEVEL_SIGMA` times its read
        noise above the image's background (the corrected background would be negative),
        or when more than :data:`MAX_HOT_PIXEL_SHARE` of the pixels are hot (a frame with
        light in it); ``None`` when neither.

    Raises
    ------
    ValueError
        Less than :data:`MIN_LIT_SHARE` of the image lies above the dark level: subtracting it
        would leave the image negative (nearly) everywhere.
    """
    mean = _frames(image, "image").mean(axis=0)
    lit = float((mean > dark.offset).mean())
    if lit < MIN_LIT_SHARE:
        raise ValueError(
            f"{name}: its level {dark.offset:.4g} counts lies above {1 - lit:.1%} of the image's "
            f"pixels (image median {float(np.median(mean)):.4g} counts), so the corrected image "
            f"would be negative nearly everywhere (at most {1 - MIN_LIT_SHARE:.0%} allowed): "
            "expected frames with the shutter closed at the exposure of the image"
        )
    problems = []
    background = camera_from_image(mean)
    excess = dark.offset - background.offset
    if excess > DARK_LEVEL_SIGMA * dark.read_noise:
        problems.append(
            f"its level {dark.offset:.4g} counts lies {excess:.4g} counts above the image's own "
            f"background {background.offset:.4g} counts (its darkest regions; at most "
            f"{DARK_LEVEL_SIGMA:g} read noise std, {DARK_LEVEL_SIGMA * dark.read_noise:.3g} "
            "counts, expected), which the correction makes negative"
        )
    hot = 0 if dark.hot_pixels is None else int(dark.hot_pixels.sum())
    if hot > MAX_HOT_PIXEL_SHARE * mean.size:
        problems.append(
            f"{hot} hot pixels, {hot / mean.size:.1%} of the sensor (a camera has under "
            f"{MAX_HOT_PIXEL_SHARE:.0%}), all left out of every fit"
        )
    if not problems:
        return None
    return (
        f"{name}: " + "; ".join(problems) + ": is it a dark frame (shutter closed, the exposure "
        "of the image)?"
    )


def _blocks(image: np.ndarray, block: int) -> np.ndarray:
    """``(N, block^2)`` pixels of the whole ``block x block`` tiles of ``image`` ``(H, W)``."""
    rows, cols = image.shape[0] // block, image.shape[1] // block
    tiles = image[: rows * block, : cols * block].reshape(rows, block, cols, block)
    return tiles.transpose(0, 2, 1, 3).reshape(rows * cols, block * block)


def _dark_blocks(mean: np.ndarray, block: int) -> np.ndarray:
    """``(N,)`` bool: which tiles of ``mean`` ``(H, W)`` hold no signal, those whose median lies
    within three standard errors of the darkest tenth of tile medians."""
    tiles = _blocks(mean, block)
    medians = np.median(tiles, axis=1)
    floor = np.quantile(medians, DARK_FRACTION)
    noise = _mad_std(tiles[medians <= floor])
    # median of block^2 pixels: standard error 1.2533 sigma / block
    return medians <= floor + 3.0 * 1.2533 * noise / block


def dark_background(image) -> tuple[float, float]:
    """Level (median, counts) and noise (robust standard deviation, 1.4826 MAD; the plain one
    when the MAD is 0) of the dark region of an image ``(H, W)``: its 16 x 16 blocks whose
    median lies within three standard errors of the darkest tenth of block medians, as in
    :func:`camera_from_image`."""
    image = _frames(image, "image").mean(axis=0)
    block = max(1, min(BLOCK, *image.shape))
    pixels = _blocks(image, block)[_dark_blocks(image, block)]
    level = float(np.median(pixels))
    noise = _mad_std(pixels)
    return level, noise if noise > 0 else float(pixels.std())


def _spike_excess(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's excess over the median of its 8 neighbours, its brightest neighbour's
    excess over that median, and the drop from that median to the median of the next ring
    (the 16 pixels at Chebyshev distance 2), ``(H, W)`` each."""
    ring1 = np.ones((3, 3), dtype=bool)
    ring1[1, 1] = False
    ring2 = np.ones((5, 5), dtype=bool)
    ring2[1:4, 1:4] = False
    near = ndimage.median_filter(image, footprint=ring1, mode="mirror")
    brightest = ndimage.maximum_filter(image, footprint=ring1, mode="mirror")
    far = ndimage.median_filter(image, footprint=ring2, mode="mirror")
    return image - near, brightest - near, near - far


def camera_from_image(image, *, hot_sigma: float = HOT_PIXEL_SIGMA) -> CameraModel:
    """Camera model estimated from an FLFM image alone (no dark frame): an estimate.

    The image is tiled in 16 x 16 blocks; the darkest tenth of block medians and every block
    within three standard errors of them form the dark region (the gaps between the lenslets'
    views and the sensor's corners, which hold no sample light). Valid when at least a tenth
    of the sensor is dark.

    Parameters
    ----------
    image : array-like
        ``(H, W)`` image or ``(T, H, W)`` frames, counts.
    hot_sigma : float
        Threshold of the hot-pixel test in local noise standard deviations (default 8).

    Returns
    -------
    CameraModel
        ``offset``: median of the (time-averaged) dark region; ``read_noise``: the median over
        frames of the dark region's robust std (1.4826 MAD) -- the noise of a dark pixel, which
        includes the shot noise of any background light there; ``hot_pixels``: isolated
        spikes of the (time-averaged) image, pixels whose excess over the median of their 8
        neighbours is more than ``hot_sigma`` local noise standard deviations (1.4826 times
        the median absolute excess over the 5 x 5 neighbourhood, at least the dark region's),
        more than twice their brightest neighbour's excess, and more than 4 times the drop
        from those neighbours to the next ring, which the peak of a PSF sampled at or above
        Nyquist never reaches (``None`` when none); a hot pixel on bright structure is found
        only where it stands out of that structure's shot noise. No flat.
    """
    frames = _frames(image, "image")
    mean = frames.mean(axis=0)
    block = max(1, min(BLOCK, *mean.shape))
    dark = _dark_blocks(mean, block)
    offset = float(np.median(_blocks(mean, block)[dark]))
    read_noise = float(np.median([_mad_std(_blocks(frame, block)[dark]) for frame in frames]))
    excess, neighbour, curvature = _spike_excess(mean)
    dark_noise = _mad_std(_blocks(excess, block)[dark])
    local = MAD_TO_STD * ndimage.median_filter(np.abs(excess), size=5, mode="mirror")
    hot = (
        (excess > hot_sigma * np.maximum(local, dark_noise))
        & (excess > SPIKE_NEIGHBOUR * neighbour)
        & (excess > SPIKE_CURVATURE * np.maximum(curvature, 0))
    )
    return CameraModel(offset, read_noise, hot if hot.any() else None)


def flat_field(flat_image, dark=None) -> np.ndarray:
    """Relative pixel sensitivity ``(H, W)`` (mean 1) from a uniformly lit frame.

    Parameters
    ----------
    flat_image : array-like
        ``(H, W)`` or ``(T, H, W)`` frames (averaged) of uniform illumination (no MLA pattern:
        the sensor's own response), counts.
    dark : array-like or float, optional
        Dark frame(s) ``(H, W)`` / ``(T, H, W)`` (averaged) or a constant offset, counts,
        subtracted first.
    """
    mean = _frames(flat_image, "flat image").mean(axis=0)
    if dark is not None:
        level = np.asarray(dark, dtype=np.float64)
        if level.ndim:
            level = _frames(level, "dark").mean(axis=0)
            if level.shape != mean.shape:
                raise ValueError(
                    f"dark frame {level.shape} and flat image {mean.shape} differ in shape"
                )
        mean = mean - level
    average = float(mean.mean())
    if not average > 0:
        raise ValueError(f"the flat image has no light above the dark level (mean {average:g})")
    return np.clip(mean / average, 0.0, None)


def write_camera(model: CameraModel, folder) -> dict:
    """Write the camera's maps into ``folder`` (``hot_pixels.ome.tif`` when it has hot pixels,
    ``flat.ome.tif`` when it has a flat; atomically) and return its ``calibration.yaml``
    record: ``offset`` and ``read_noise`` (counts), ``hot_pixels`` and ``flat`` (file names in
    the folder, or null) and ``hot_pixel_count``."""
    folder = Path(folder)
    record = {
        "offset": float(model.offset),
        "read_noise": float(model.read_noise),
        "hot_pixels": None,
        "hot_pixel_count": 0,
        "flat": None,
    }
    if model.hot_pixels is not None and model.hot_pixels.any():
        write_tiff(folder / HOT_PIXEL_FILE, model.hot_pixels.astype(np.uint8), axes="YX")
        record["hot_pixels"] = HOT_PIXEL_FILE
        record["hot_pixel_count"] = int(model.hot_pixels.sum())
    if model.flat is not None:
        write_tiff(folder / FLAT_FILE, model.flat.astype(np.float32), axes="YX")
        record["flat"] = FLAT_FILE
    return record


CAMERA_FIELDS = ("offset", "read_noise", "hot_pixels", "hot_pixel_count", "flat", "source")


def read_camera(record, folder, source: str) -> CameraModel:
    """The :class:`CameraModel` of a ``camera`` record of ``calibration.yaml`` (see
    :func:`write_camera`) whose map files lie in ``folder``; errors name ``source`` (the YAML
    file) and the field, or the map file."""
    if not isinstance(record, dict):
        raise ValueError(f"{source}: camera: expected a mapping of {list(CAMERA_FIELDS)}")
    unknown = sorted(set(record) - set(CAMERA_FIELDS))
    if unknown:
        raise ValueError(f"{source}: camera: unknown field(s) {unknown}")
    numbers = {}
    for name in ("offset", "read_noise"):
        if name not in record:
            raise ValueError(f"{source}: camera.{name} is missing")
        numbers[name] = check_number(
            f"{source}: camera.{name}", record[name], minimum=0 if name == "read_noise" else None
        )
    maps = {}
    for name in ("hot_pixels", "flat"):
        file = record.get(name)
        if file is None:
            maps[name] = None
            continue
        if not isinstance(file, str):
            raise ValueError(f"{source}: camera.{name} must be a file name, got {file!r}")
        path = Path(folder) / file
        if not path.is_file():
            raise FileNotFoundError(f"{source}: camera.{name}: {path} does not exist")
        maps[name] = read_tiff(path, ndim=2, axes="(H, W)", nonnegative=True)
    try:
        model = CameraModel(**numbers, **maps)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from None
    count = record.get("hot_pixel_count")
    found = 0 if model.hot_pixels is None else int(model.hot_pixels.sum())
    if count is not None and count != found:
        raise ValueError(
            f"{source}: camera.hot_pixel_count is {count!r}, but {record.get('hot_pixels')} "
            f"marks {found} pixel(s)"
        )
    return model
