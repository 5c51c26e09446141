"""PhantomDataModule: a simulated measurement of a phantom, with its truth."""

from __future__ import annotations

import torch

from fgat.datamodules.scene import FLFMScene, SceneDataModule, normalized_measurement
from fgat.io import read_tiff
from fgat.optics.psf import JPGM
from fgat.optics.systems import parse_depths
from fgat.simulation import SimulationConfig, simulate, true_optics


class PhantomDataModule(SceneDataModule):
    """Simulate an FLFM measurement of a phantom (see :class:`fgat.simulation.SimulationConfig`).

    Parameters
    ----------
    simulation : dict
        :class:`~fgat.simulation.SimulationConfig` fields (system, depths, phantom, aberrations,
        shifts, noise, seed).
    psf : str
        PSF the reconstruction uses: ``"true"`` (the simulation's, optics known), ``"ideal"``
        (aberration-free JPGM of the same system, as 3DGAT assumes) or a PSF OME-TIFF path.
    """

    def __init__(self, simulation: dict | None = None, psf: str = "true") -> None:
        super().__init__()
        self.save_hyperparameters()  # logged with the model's (MLflow params)
        self.config = SimulationConfig(**(simulation or {}))
        self.config.validate()
        if psf not in ("true", "ideal") and not str(psf).lower().endswith((".tif", ".tiff")):
            raise ValueError(f"data.psf must be 'true', 'ideal' or a PSF TIFF path, got {psf!r}")
        self.psf_choice = psf

    def make_scene(self) -> FLFMScene:
        result = simulate(self.config)
        measurement, scale = normalized_measurement(result.views, self.config.background)
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
        return FLFMScene(measurement=measurement, scale=scale, psf=psf, voxel_size_um=result.voxel_size_um,
                         truth=result.truth, name=f"{self.config.phantom['kind']} phantom", optics=optics,
                         truth_optics=truth_optics)
