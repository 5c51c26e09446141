"""FLFMDataModule: a measured FLFM image or sequence with its lenslet centres and optics."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from lightning.pytorch.utilities import rank_zero_info

from fgat._core.resources import check_memory
from fgat._core.validation import parse_overrides, require
from fgat.app.datamodules.scene import SceneDataModule
from fgat.instrument.calibration import read_calibration
from fgat.instrument.measurement import measurement_model
from fgat.instrument.views import check_truth_shape, choose_view_size, simulation_view_size
from fgat.io.images import read_tiff, tiff_shape
from fgat.optics.acquisition import GUARD_ENERGY
from fgat.optics.systems import load_system, parse_depths
from fgat.recon.scene import Scene, normalized_measurement, reference_index


def _existing(field: str, path: str | None) -> str | None:
    if path is not None and not Path(path).is_file():
        raise FileNotFoundError(f"data.{field}: file {path} does not exist")
    return path


class FLFMDataModule(SceneDataModule):
    """A sensor image ``(H, W)`` or a TIFF sequence ``(T, H, W)`` / ``(T, C, H, W)``.

    The static stage reconstructs the reference frame; the dynamic stage gets every frame at
    normalised times ``k / (T - 1)``. A multi-channel sequence is reconstructed one ``channel``
    at a time (``python -m fgat pipeline --channels`` runs them all and merges the results).

    Parameters
    ----------
    measurement : str
        Sensor image ``(H, W)``, sequence ``(T, H, W)`` or multi-channel sequence ``(T, C, H, W)``
        (TIFF).
    frame : int, optional
        Reference frame of a sequence; default the middle one (``T // 2``).
    channel : int, optional
        Channel of a ``(T, C, H, W)`` sequence (required when ``C > 1``).
    calibration : str, optional
        A folder written by ``python -m fgat calibrate``: lenslet centres, and where present the
        per-view gains, the camera (offset, read noise, hot pixels, flat field) and the depth
        axis. Explicit ``centers``, ``gains``, ``background``, ``dark`` and ``depth_axis`` take
        precedence over its entries.
    centers : str, optional
        Lenslet centres (``row,col`` CSV, 0-based, or MATLAB ``.mat``, 1-based).
    brightfield : str, optional
        Brightfield image of the MLA to detect the centres from when neither ``calibration`` nor
        ``centers`` is given.
    n_lenslets : int, optional
        Lenslets to detect in ``brightfield``; default the ``system``'s count.
    psf : str, optional
        PSF stack ``(V, Z, h, w)`` OME-TIFF; otherwise computed from ``system`` and ``depths_um``.
    system : str, optional
        Shipped system name or system YAML: the PSF is the JPGM of that system at the centres.
    depths_um : str or list, optional
        PSF planes for ``system`` (``"start:stop:count"`` or values, um).
    zernike, intercepts, slopes : dict, optional
        Optics of that JPGM: Noll index -> waves, view -> ``[row, col]`` pixels (default
        aberration-free and unshifted).
    view_size : int, optional
        Lateral size ``Y = X`` of the views and of the volume, pixels. By default the
        ``view_size`` of the ``params.yaml`` that ``python -m fgat simulate`` wrote beside the
        measurement, else that of the ``truth`` (its last axis), else the largest square that
        fits between the centres (:func:`fgat.instrument.views.choose_view_size`, as ``python -m
        fgat deconvolve`` does); the log says which. A ``truth`` of another shape is refused.
    background : float, optional
        Camera offset subtracted before reconstruction (counts); default the offset of the
        camera model (``dark`` or the calibration), else 0.
    dark : str, optional
        Dark frame(s) ``(H, W)`` or ``(T, H, W)`` TIFF: the camera offset and hot pixels
        (:func:`fgat.instrument.camera.camera_from_dark`); hot pixels are left out of every loss and
        of RL/SHB.
    gains : list of float, optional
        Relative per-view gains ``(V,)`` applied in the forward model; default the
        calibration's, else none (every view 1). ``model.estimate_gains`` refines them.
    guard_px : int or "auto"
        Guard band: the volume is reconstructed on a grid this many pixels wider on each lateral
        side than the views and cropped on output, so light from objects beyond the field of
        view is not forced into the border voxels. ``"auto"``: the radius holding 99% of the PSF
        stack's energy (:func:`fgat.optics.acquisition.psf_support_radius`), at most half the
        view size.
    depth_axis : {"up", "down"}, optional
        ``"down"`` reverses the depth planes, so that volume index 0 is the last of
        ``depths_um`` (the convention of some other FLFM codes); default the calibration's,
        else ``"up"`` (index 0 is the first, most negative depth).
    truth : str, optional
        Ground truth for metrics: a volume ``(Z, Y, X)`` (the reference frame), or one per frame
        ``(T, Z, Y, X)`` of a sequence.
    frame_interval_s : float, optional
        Seconds between the sequence's frames: the time axis of the volume series written
        (in frames without it).
    """

    def __init__(
        self,
        measurement: str,
        frame: int | None = None,
        channel: int | None = None,
        calibration: str | None = None,
        centers: str | None = None,
        brightfield: str | None = None,
        n_lenslets: int | None = None,
        psf: str | None = None,
        system: str | None = None,
        depths_um: str | list | None = None,
        zernike: dict | None = None,
        intercepts: dict | None = None,
        slopes: dict | None = None,
        view_size: int | None = None,
        background: float | None = None,
        dark: str | None = None,
        gains: list[float] | None = None,
        guard_px: int | str = "auto",
        depth_axis: str | None = None,
        truth: str | None = None,
        frame_interval_s: float | None = None,
    ) -> None:
        super().__init__(frame_interval_s)
        self.save_hyperparameters()  # logged with the model's (MLflow params)
        self.measurement_path = _existing("measurement", measurement)
        self.centers_path = _existing("centers", centers)
        self.brightfield_path = _existing("brightfield", brightfield)
        self.psf_path = _existing("psf", psf)
        self.truth_path = _existing("truth", truth)
        self.dark_path = _existing("dark", dark)
        self.calibration = None if calibration is None else read_calibration(calibration)
        if centers is None and brightfield is None and calibration is None:
            raise ValueError(
                "data: give a 'calibration' folder (python -m fgat calibrate), lenslet 'centers' "
                "(a file) or a 'brightfield' image to detect them from"
            )
        if psf is None and (system is None or depths_um is None):
            raise ValueError("data: give a 'psf' file, or an optics 'system' with 'depths_um'")
        self.optics_system = None
        if system is not None:
            try:
                self.optics_system = load_system(system)  # fails fast on an unknown system
            except ValueError as error:
                raise ValueError(f"data.system: {error}") from None
            except FileNotFoundError as error:
                raise FileNotFoundError(f"data.system: {error}") from None
        for name, value in (("frame", frame), ("channel", channel)):
            require(value is None or value >= 0, f"data.{name}", value, "an index >= 0, or null")
        if n_lenslets is None and self.optics_system is not None:
            n_lenslets = self.optics_system.n_lenslets
        require(
            n_lenslets is None or n_lenslets >= 1,
            "data.n_lenslets",
            n_lenslets,
            "a positive integer, or null (the system's)",
        )
        if brightfield is not None and centers is None and calibration is None:
            require(
                n_lenslets is not None,
                "data.n_lenslets",
                n_lenslets,
                "the lenslets to detect in the brightfield image (or give data.system)",
            )
        require(
            view_size is None or view_size >= 1,
            "data.view_size",
            view_size,
            "a positive number of pixels, or null",
        )
        require(
            background is None or (math.isfinite(background) and background >= 0),
            "data.background",
            background,
            "a camera offset >= 0 (counts), or null (the camera model's)",
        )
        require(
            guard_px == "auto" or (isinstance(guard_px, int) and guard_px >= 0),
            "data.guard_px",
            guard_px,
            "a number of pixels >= 0, or 'auto'",
        )
        require(
            depth_axis in (None, "up", "down"),
            "data.depth_axis",
            depth_axis,
            "'up', 'down' or null (the calibration's)",
        )
        if gains is not None:
            require(
                all(isinstance(g, (int, float)) and math.isfinite(g) and g > 0 for g in gains),
                "data.gains",
                gains,
                "a list of positive per-view gains",
            )
        self.frame, self.channel, self.n_lenslets, self.system = frame, channel, n_lenslets, system
        self.optics = parse_overrides(
            {"zernike": zernike, "intercepts": intercepts, "slopes": slopes}
        )
        try:
            self.depths = parse_depths(depths_um) if depths_um is not None else None
        except ValueError as error:
            raise ValueError(f"data.depths_um: {error}") from None
        self.view_size, self.background = view_size, background
        self.gains, self.guard_px, self.depth_axis = gains, guard_px, depth_axis
        self._check_input_sizes()
        self._check_truth_lateral_size()

    def _check_truth_lateral_size(self) -> None:
        """Refuse, from its TIFF header and before anything is built, a truth whose lateral size
        is not a view size known already (``data.view_size``, or the simulation's); its whole
        shape is checked against the PSF's depths as the data is set up."""
        if self.truth_path is None:
            return
        size = self.view_size or simulation_view_size(self.measurement_path)
        if size is None:
            return
        params = Path(self.measurement_path).parent / "params.yaml"
        origin = "data.view_size" if self.view_size else f"the simulation's {params}"
        shape, _ = tiff_shape(self.truth_path)
        expected = (*shape[:-2], size, size)
        check_truth_shape("data.truth", self.truth_path, shape, expected, origin)

    def _check_input_sizes(self) -> None:
        """Refuse inputs that together need more memory than the machine has, from their TIFF
        headers (:func:`fgat.io.images.tiff_shape`): before their contents are read or hashed for
        the run's fingerprint. Each counts as read and as its float32 copy."""
        files = {
            "data.measurement": self.measurement_path,
            "data.truth": self.truth_path,
            "data.dark": self.dark_path,
        }
        sizes = {}
        for field, path in files.items():
            if path is not None:
                shape, dtype = tiff_shape(path)
                sizes[f"{field} {path} {shape} {dtype}"] = math.prod(shape) * (dtype.itemsize + 4)
        if sizes:
            check_memory(
                ", ".join(sizes),
                sum(sizes.values()),
                hint="a shorter sequence, or a crop of the sensor",
            )

    def _images(self) -> np.ndarray:
        """The sensor frames ``(T, H, W)`` of the chosen channel (``T = 1`` for one image)."""
        path = self.measurement_path
        data = read_tiff(path, ndim=(2, 3, 4), axes="(H, W), (T, H, W) or (T, C, H, W)")
        if data.ndim == 4:
            channels = data.shape[1]
            if self.channel is None and channels > 1:
                raise ValueError(
                    f"{path} has {channels} channels (T, C, H, W) = {data.shape}: choose one with "
                    f"data.channel (0..{channels - 1}), or run them all with "
                    "'python -m fgat pipeline --channels all'"
                )
            channel = self.channel or 0
            if not 0 <= channel < channels:
                raise ValueError(
                    f"data.channel {channel} is outside the {channels} channels of {path}"
                )
            data = data[:, channel]
        elif self.channel not in (None, 0):
            raise ValueError(
                f"data.channel {self.channel}: {path} has no channel axis (shape {data.shape})"
            )
        return data.reshape(-1, *data.shape[-2:]).astype(np.float32)

    def make_scene(self) -> Scene:
        images = self._images()
        reference = reference_index(
            self.frame, len(images), f"data.frame ({self.measurement_path})"
        )
        model = measurement_model(
            calibration=self.calibration,
            centers=self.centers_path,
            brightfield=self.brightfield_path,
            n_lenslets=self.n_lenslets,
            psf=self.psf_path,
            system=self.optics_system,
            depths_um=self.depths,
            optics={k: v or {} for k, v in self.optics.items()},
            background=self.background,
            dark=self.dark_path,
            gains=self.gains,
            depth_axis=self.depth_axis,
        )
        psf = model.psf
        truth = (
            None
            if self.truth_path is None
            else read_tiff(self.truth_path, ndim=(3, 4), axes="(Z, Y, X) or (T, Z, Y, X)")
        )
        size, origin = self._view_size(truth, model.centers, images.shape[-2:])
        if truth is not None:
            expected = (len(images),) * (truth.ndim == 4) + (psf.shape[1], size, size)
            check_truth_shape("data.truth", self.truth_path, truth.shape, expected, origin)
        views, mask = model.views(images, size)
        frames, scale = normalized_measurement(views, 0.0, reference, mask)
        sequence = (
            {"frames": frames, "times": np.linspace(0.0, 1.0, len(frames)), "reference": reference}
            if len(frames) > 1
            else {}
        )
        if truth is not None and truth.ndim == 4:
            sequence["truth_frames"], truth = truth, truth[reference]
        return Scene(
            measurement=frames[reference],
            scale=scale,
            psf=psf,
            voxel_size_um=model.voxel_size_um,
            truth=truth,
            name=Path(self.measurement_path).name,
            optics=model.optics,
            gains=model.gains,
            mask=mask,
            guard_px=self._guard(model, size),
            depth_axis=model.depth_axis,
            depths_um=model.depths_um,
            **sequence,
        )

    def _guard(self, model, size: int) -> int:
        """``data.guard_px`` in pixels (``"auto"`` resolved by the measurement model), logged."""
        guard = model.guard(self.guard_px, size)
        origin = (
            f"the PSF's {GUARD_ENERGY:.0%}-energy radius, at most half the view"
            if self.guard_px == "auto"
            else "data.guard_px"
        )
        rank_zero_info(
            f"fgat: volume reconstructed {guard} px beyond the {size} x {size} views on every "
            f"side and cropped on output (guard band from {origin})"
        )
        return guard

    def _view_size(
        self, truth: np.ndarray | None, centers: np.ndarray, sensor_shape: tuple[int, int]
    ) -> tuple[int, str]:
        """The views' size and its origin (:func:`fgat.instrument.views.choose_view_size`),
        logged."""
        size, origin = choose_view_size(
            self.view_size,
            "data.view_size",
            self.measurement_path,
            None if truth is None else (self.truth_path, truth.shape),
            centers,
            sensor_shape,
        )
        rank_zero_info(
            f"fgat: views and volume {size} x {size} px, from {origin} "
            "(set data.view_size to change)"
        )
        return size, origin
