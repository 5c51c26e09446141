"""PhantomDataModule: a simulated measurement (or sequence) of a phantom, with its truth."""

from __future__ import annotations

from pathlib import Path

import torch

from fgat.datamodules.scene import FLFMScene, SceneDataModule, normalized_measurement, reference_index
from fgat.io import check_fields, read_tiff
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system, parse_depths
from fgat.simulation import SimulationConfig, make_phantom, simulate, true_optics


def simulation_config(fields: dict | None) -> SimulationConfig:
    """``data.simulation`` as a checked :class:`~fgat.simulation.SimulationConfig` (system
    included), errors naming the field."""
    check_fields("data.simulation", SimulationConfig, fields)
    try:
        config = SimulationConfig(**(fields or {}))
        config.validate()
        load_system(config.system)
    except ValueError as error:
        raise ValueError(f"data.simulation: {error}") from None
    except FileNotFoundError as error:
        raise FileNotFoundError(f"data.simulation: {error}") from None
    return config


class PhantomDataModule(SceneDataModule):
    """Simulate an FLFM measurement of a phantom (see :class:`fgat.simulation.SimulationConfig`).

    A dynamic phantom with ``frames > 1`` gives a sequence with the truth of every frame (and at
    any time between frames); the static stage reconstructs its reference frame.

    Parameters
    ----------
    simulation : dict
        :class:`~fgat.simulation.SimulationConfig` fields (system, depths, phantom, frames,
        aberrations, shifts, noise, seed).
    psf : str
        PSF the reconstruction uses: ``"true"`` (the simulation's, optics known), ``"ideal"``
        (aberration-free JPGM of the same system, as 3DGAT assumes) or a PSF OME-TIFF path.
    reference_frame : int, optional
        Reference frame ``t_ref`` of a sequence; default the middle one (``T // 2``).
    """

    def __init__(self, simulation: dict | None = None, psf: str = "true", reference_frame: int | None = None) -> None:
        super().__init__()
        self.save_hyperparameters()  # logged with the model's (MLflow params)
        self.config = simulation_config(simulation)
        if psf not in ("true", "ideal") and not str(psf).lower().endswith((".tif", ".tiff")):
            raise ValueError(f"data.psf must be 'true', 'ideal' or a PSF TIFF path, got {psf!r}")
        if psf not in ("true", "ideal") and not Path(psf).is_file():
            raise FileNotFoundError(f"data.psf: file {psf} does not exist")
        self.psf_choice = psf
        self.reference = reference_index(reference_frame, self.config.frames, "data.reference_frame")

    def make_scene(self) -> FLFMScene:
        result = simulate(self.config)
        reference = self.reference if result.is_sequence else None
        views, scale = normalized_measurement(result.views, self.config.background, reference)
        depths = parse_depths(self.config.depths_um)
        truth_optics = true_optics(self.config, result.system.n_lenslets)
        optics = None
        if self.psf_choice == "true":
            psf = result.psf
            optics = {"system": result.system, "depths_um": depths, "centers_px": result.centers, **truth_optics}
        elif self.psf_choice == "ideal":
            optics = {"system": result.system, "depths_um": depths, "centers_px": result.centers}
            with torch.no_grad():
                psf = JPGM.with_parameters(**optics)().numpy()
        else:
            psf = read_tiff(self.psf_choice, ndim=4, axes="(V, Z, h, w)", nonnegative=True)
            if psf.shape[:2] != result.psf.shape[:2]:
                raise ValueError(f"{self.psf_choice}: {psf.shape[:2]} (views, depths), expected {result.psf.shape[:2]}")
        measurement, truth, sequence = views, result.truth, {}
        if result.is_sequence:
            measurement, truth = views[reference], result.truth[reference]
            sequence = {"frames": views, "times": result.times, "reference": reference, "truth_frames": result.truth,
                        "truth_at": lambda times: make_phantom(self.config, truth.shape, times)}
        return FLFMScene(measurement=measurement, scale=scale, psf=psf, voxel_size_um=result.voxel_size_um,
                         truth=truth, name=f"{self.config.phantom['kind']} phantom", optics=optics,
                         truth_optics=truth_optics, **sequence)
