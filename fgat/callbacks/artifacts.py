"""Files a reconstruction leaves behind: volume, Gaussians and MIP figures (also in MLflow)."""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
import torch
import yaml

from fgat.callbacks.mlflow import mlflow_loggers
from fgat.io import atomic_path, write_tiff
from fgat.modules.static import optics_metrics
from fgat.optics.psf import JPGM
from fgat.optics.zernike import wavefront_map
from fgat.plots import plot_coefficients, plot_mips, plot_psf_stack, plot_pupil_phases


class ReconstructionArtifacts(pl.Callback):
    """At the end of training write, under ``<default_root_dir>/results/<run>``:

    * ``volume.ome.tif``: the reconstruction ``(Z, Y, X)`` in measurement counts, with voxel sizes;
    * ``gaussians.pt``: the Gaussian set (see :meth:`fgat.gaussians.cloud.GaussianCloud.save`);
    * ``shb.ome.tif``: the SHB baseline the validation compares against, in counts;
    * with JPGM self-estimation, ``psf.ome.tif`` (the estimated PSF stack), ``optics.yaml``
      (its Zernike coefficients in waves and lenslet shifts in pixels), ``pupil_phase.png``,
      ``zernike.png`` and ``psf_<ideal|estimated|truth>.png``;
    * ``mips.png``: x-y and x-z MIPs of the reconstruction, the SHB baseline and the truth.

    Every file is also logged to the run of each MLflow logger.
    """

    def on_train_end(self, trainer, pl_module) -> None:
        if not trainer.is_global_zero:
            return
        loggers = mlflow_loggers(trainer)
        run = loggers[0].run_id if loggers else "latest"
        folder = Path(trainer.default_root_dir) / "results" / str(run)
        folder.mkdir(parents=True, exist_ok=True)
        scene = pl_module.scene
        volume = pl_module.cloud().detach().cpu().numpy() * scene.scale
        write_tiff(folder / "volume.ome.tif", volume, axes="ZYX", voxel_size_um=scene.voxel_size_um)
        pl_module.cloud.save(folder / "gaussians.pt")
        if getattr(pl_module, "jpgm", None) is not None:  # the self-estimated optics
            self._optics_files(pl_module, folder)
        panels = {"4DGAT static (Gaussians)": volume}
        if pl_module.hparams.baseline_iterations:
            baseline = pl_module.baseline.cpu().numpy() * scene.scale
            write_tiff(folder / "shb.ome.tif", baseline, axes="ZYX", voxel_size_um=scene.voxel_size_um)
            panels[f"SHB {pl_module.hparams.baseline_iterations} it."] = baseline
        if scene.truth is not None:
            panels["ground truth"] = scene.truth
        plot_mips(panels, folder / "mips.png", title=scene.name, voxel_size_um=scene.voxel_size_um)
        for logger in loggers:
            for path in sorted(folder.iterdir()):
                logger.experiment.log_artifact(logger.run_id, str(path))
        pl_module.print(f"fgat: results -> {folder}")

    @staticmethod
    def _optics_files(pl_module, folder: Path) -> None:
        """Estimated PSF stack and parameters; pupil-phase maps, coefficient bars and per-view PSF
        MIPs (ideal, estimated and, on phantoms, true)."""
        scene, jpgm = pl_module.scene, pl_module.jpgm
        write_tiff(folder / "psf.ome.tif", pl_module.psf.cpu().numpy(), axes="CZYX", voxel_size_um=scene.voxel_size_um)
        with atomic_path(folder / "optics.yaml") as temporary:
            temporary.write_text(yaml.safe_dump(optics_metrics(jpgm), sort_keys=False))
        phases = {"estimated": jpgm.pupil_phase_map().numpy()}
        coefficients = {"estimated": jpgm.zernike_coefficients.detach().cpu().tolist()}
        optics = dict(scene.optics)
        with torch.no_grad():
            stacks = {"ideal": JPGM(optics["system"], optics["depths_um"], centers_px=optics["centers_px"])()}
        stacks["estimated"] = pl_module.psf.cpu()
        if pl_module.true_psf is not None:  # a phantom: its true optics, computed once at fit start
            indices, truth = pl_module.true_parameters()[:2]
            phases["truth"] = wavefront_map(indices, truth).numpy()
            coefficients["truth"] = truth.tolist()
            stacks["truth"] = pl_module.true_psf.cpu()
        plot_pupil_phases(phases, folder / "pupil_phase.png", title="Zernike pupil phase")
        plot_coefficients(jpgm.zernike_indices, coefficients, folder / "zernike.png", title="Zernike coefficients")
        for label, stack in stacks.items():
            plot_psf_stack(stack.numpy(), folder / f"psf_{label}.png", title=f"{label} PSF",
                           depths_um=optics["depths_um"], pixel_um=scene.voxel_size_um[2])
