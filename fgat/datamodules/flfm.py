"""FLFMDataModule: a measured FLFM image or sequence with its lenslet centres and optics."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import yaml
from lightning.pytorch.utilities import rank_zero_info

from fgat.datamodules.scene import SceneDataModule
from fgat.io import parse_overrides, read_tiff, read_voxel_size, require
from fgat.optics.lenslets import detect_lenslet_centers, largest_view_size
from fgat.optics.operator import crop_views
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.reconstruction.scene import Scene, normalized_measurement, reference_index
from fgat.simulation import read_centers


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
    centers : str, optional
        Lenslet centres (``row,col`` CSV, 0-based, or MATLAB ``.mat``, 1-based).
    brightfield : str, optional
        Brightfield image of the MLA to detect the centres from when ``centers`` is not given.
    n_lenslets : int
        Lenslets to detect.
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
        Lateral size ``Y = X`` of the views and of the volume, pixels. By default, first that of
        the ``truth`` (its last axis), else the ``view_size`` of the ``params.yaml`` that
        ``python -m fgat simulate`` wrote beside the measurement, else the largest square that
        fits between the centres (as ``python -m fgat deconvolve`` does); the log says which.
    background : float
        Camera offset subtracted before reconstruction (counts).
    truth : str, optional
        Ground truth for metrics: a volume ``(Z, Y, X)`` (the reference frame), or one per frame
        ``(T, Z, Y, X)`` of a sequence.
    """

    def __init__(
        self,
        measurement: str,
        frame: int | None = None,
        channel: int | None = None,
        centers: str | None = None,
        brightfield: str | None = None,
        n_lenslets: int = 7,
        psf: str | None = None,
        system: str | None = None,
        depths_um: str | list | None = None,
        zernike: dict | None = None,
        intercepts: dict | None = None,
        slopes: dict | None = None,
        view_size: int | None = None,
        background: float = 0.0,
        truth: str | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()  # logged with the model's (MLflow params)
        self.measurement_path = _existing("measurement", measurement)
        self.centers_path = _existing("centers", centers)
        self.brightfield_path = _existing("brightfield", brightfield)
        self.psf_path = _existing("psf", psf)
        self.truth_path = _existing("truth", truth)
        if centers is None and brightfield is None:
            raise ValueError(
                "data: give lenslet 'centers' (a file) or a 'brightfield' image to detect them from"
            )
        if psf is None and (system is None or depths_um is None):
            raise ValueError("data: give a 'psf' file, or an optics 'system' with 'depths_um'")
        if system is not None:
            try:
                load_system(system)  # fails fast on an unknown system
            except ValueError as error:
                raise ValueError(f"data.system: {error}") from None
            except FileNotFoundError as error:
                raise FileNotFoundError(f"data.system: {error}") from None
        for name, value in (("frame", frame), ("channel", channel)):
            require(value is None or value >= 0, f"data.{name}", value, "an index >= 0, or null")
        require(n_lenslets >= 1, "data.n_lenslets", n_lenslets, "a positive integer")
        require(
            view_size is None or view_size >= 1,
            "data.view_size",
            view_size,
            "a positive number of pixels, or null",
        )
        require(
            math.isfinite(background) and background >= 0,
            "data.background",
            background,
            "a camera offset >= 0 (counts)",
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
        image = images[reference]
        if self.centers_path is not None:
            centers = read_centers(self.centers_path)
        else:
            centers = detect_lenslet_centers(
                read_tiff(self.brightfield_path, ndim=2), self.n_lenslets
            )
        optics = None
        if self.psf_path is not None:
            psf = read_tiff(self.psf_path, ndim=4, axes="(V, Z, h, w)", nonnegative=True).astype(
                np.float32
            )
            sizes = read_voxel_size(self.psf_path)
            voxel = tuple(sizes.get(axis, 1.0) for axis in "ZYX")
        else:
            system = load_system(self.system)
            optics = OpticsSpec(
                system, tuple(self.depths), centers, **{k: v or {} for k, v in self.optics.items()}
            )
            psf = optics.psf()
            voxel = system.grid_voxel_size_um(self.depths)
        if len(centers) != psf.shape[0]:
            raise ValueError(
                f"{len(centers)} lenslet centres but the PSF stack has {psf.shape[0]} views"
            )
        truth = (
            None
            if self.truth_path is None
            else read_tiff(self.truth_path, ndim=(3, 4), axes="(Z, Y, X) or (T, Z, Y, X)")
        )
        size = self._view_size(truth, centers, image.shape)
        frames, scale = normalized_measurement(
            crop_views(torch.from_numpy(images), centers, size).numpy(), self.background, reference
        )
        sequence = (
            {"frames": frames, "times": np.linspace(0.0, 1.0, len(frames)), "reference": reference}
            if len(frames) > 1
            else {}
        )
        if truth is not None:
            expected = (
                (psf.shape[1], size, size)
                if truth.ndim == 3
                else (len(frames), psf.shape[1], size, size)
            )
            if truth.shape != expected:
                raise ValueError(
                    f"data.truth: {self.truth_path} has shape {truth.shape}, expected {expected} "
                    "((T,) PSF depths, view size, view size)"
                )
        if truth is not None and truth.ndim == 4:
            sequence["truth_frames"], truth = truth, truth[reference]
        return Scene(
            measurement=frames[reference],
            scale=scale,
            psf=psf,
            voxel_size_um=voxel,
            truth=truth,
            name=Path(self.measurement_path).name,
            optics=optics,
            **sequence,
        )

    def _view_size(
        self, truth: np.ndarray | None, centers: np.ndarray, sensor_shape: tuple[int, int]
    ) -> int:
        """``view_size``, else the truth's lateral size, else the simulation's, else the largest
        square between the centres (see the class docstring); logged with its origin."""
        if self.view_size is not None:
            return self.view_size
        if truth is not None:
            size, origin = truth.shape[-1], f"the lateral size of the truth {self.truth_path}"
        elif (simulated := simulation_view_size(self.measurement_path)) is not None:
            size, origin = (
                simulated,
                f"the simulation's {Path(self.measurement_path).parent / 'params.yaml'}",
            )
        else:
            size, origin = (
                largest_view_size(centers, sensor_shape),
                "the largest square between the lenslet centres",
            )
        rank_zero_info(
            f"fgat: views and volume {size} x {size} px, from {origin} "
            "(set data.view_size to change)"
        )
        return size


def simulation_view_size(measurement: str | Path) -> int | None:
    """The ``view_size`` of the ``params.yaml`` written by ``python -m fgat simulate`` in the
    measurement's folder; ``None`` without one (a ``params.yaml`` of another program is ignored)."""
    params = Path(measurement).parent / "params.yaml"
    if not params.is_file():
        return None
    try:
        content = yaml.safe_load(params.read_text())
    except yaml.YAMLError:
        return None
    config = content.get("config") if isinstance(content, dict) else None
    size = config.get("view_size") if isinstance(config, dict) else None
    return size if isinstance(size, int) and size >= 1 else None
