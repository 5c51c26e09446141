"""PhantomDataModule: a simulated measurement (or sequence) of a phantom, with its truth."""

from __future__ import annotations

from pathlib import Path

from fgat.app.datamodules.scene import SceneDataModule
from fgat.app.modules.shell import plain_hyperparameters
from fgat.io.yaml_files import check_fields
from fgat.optics.systems import load_system
from fgat.recon.scene import Scene, phantom_scene, reference_index
from fgat.sim.simulation import SimulationConfig


def simulation_config(fields: SimulationConfig | dict | None) -> SimulationConfig:
    """``data.simulation`` as a checked :class:`~fgat.sim.simulation.SimulationConfig` (system
    included), errors naming the field."""
    if not isinstance(fields, SimulationConfig):
        check_fields("data.simulation", SimulationConfig, fields)
    try:
        config = (
            fields if isinstance(fields, SimulationConfig) else SimulationConfig(**(fields or {}))
        )
        config.validate()
        load_system(config.system)
    except ValueError as error:
        raise ValueError(f"data.simulation: {error}") from None
    except FileNotFoundError as error:
        raise FileNotFoundError(f"data.simulation: {error}") from None
    return config


class PhantomDataModule(SceneDataModule):
    """Simulate an FLFM measurement of a phantom (see
    :class:`fgat.sim.simulation.SimulationConfig`).

    A dynamic phantom with ``frames > 1`` gives a sequence with the truth of every frame (and at
    any time between frames); the static stage reconstructs its reference frame.

    Parameters
    ----------
    simulation : SimulationConfig
        System, depths, phantom, frames, aberrations, shifts, noise, seed (a mapping of its
        fields in a config).
    psf : str
        PSF the reconstruction uses: ``"true"`` (the simulation's, optics known), ``"ideal"``
        (aberration-free JPGM of the same system, as 3DGAT assumes) or a PSF OME-TIFF path.
    reference_frame : int, optional
        Reference frame ``t_ref`` of a sequence; default the middle one (``T // 2``).
    frame_interval_s : float, optional
        Seconds between frames, for the time axis of the series written
        (:class:`~fgat.app.datamodules.scene.SceneDataModule`).
    """

    def __init__(
        self,
        simulation: SimulationConfig | None = None,
        psf: str = "true",
        reference_frame: int | None = None,
        frame_interval_s: float | None = None,
    ) -> None:
        super().__init__(frame_interval_s)
        self.save_hyperparameters()  # logged with the model's (MLflow params)
        self.config = simulation_config(simulation)
        plain_hyperparameters(self)
        if psf not in ("true", "ideal") and not str(psf).lower().endswith((".tif", ".tiff")):
            raise ValueError(f"data.psf must be 'true', 'ideal' or a PSF TIFF path, got {psf!r}")
        if psf not in ("true", "ideal") and not Path(psf).is_file():
            raise FileNotFoundError(f"data.psf: file {psf} does not exist")
        self.psf_choice = psf
        self.reference = reference_index(
            reference_frame, self.config.frames, "data.reference_frame"
        )

    def make_scene(self) -> Scene:
        return phantom_scene(
            self.config, self.psf_choice, self.reference if self.config.frames > 1 else None
        )
