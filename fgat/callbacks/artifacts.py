"""Files a reconstruction leaves behind: volume, Gaussians and MIP figures (also in MLflow)."""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl

import yaml

from fgat.callbacks.mlflow import mlflow_loggers
from fgat.io import atomic_path, write_tiff
from fgat.modules.static import optics_metrics
from fgat.plots import plot_mips


class ReconstructionArtifacts(pl.Callback):
    """At the end of training write, under ``<default_root_dir>/results/<run>``:

    * ``volume.ome.tif``: the reconstruction ``(Z, Y, X)`` in measurement counts, with voxel sizes;
    * ``gaussians.pt``: the Gaussian set (see :meth:`fgat.gaussians.cloud.GaussianCloud.save`);
    * with JPGM self-estimation, ``psf.ome.tif`` (the estimated PSF stack) and ``optics.yaml``
      (its Zernike coefficients in waves and lenslet shifts in pixels);
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
            write_tiff(folder / "psf.ome.tif", pl_module.psf.cpu().numpy(), axes="CZYX",
                       voxel_size_um=scene.voxel_size_um)
            with atomic_path(folder / "optics.yaml") as temporary:
                temporary.write_text(yaml.safe_dump(optics_metrics(pl_module.jpgm), sort_keys=False))
        panels = {"4DGAT static (Gaussians)": volume}
        if pl_module.hparams.baseline_iterations:
            panels[f"SHB {pl_module.hparams.baseline_iterations} it."] = pl_module.baseline.cpu().numpy()
        if scene.truth is not None:
            panels["ground truth"] = scene.truth
        plot_mips(panels, folder / "mips.png", title=scene.name, voxel_size_um=scene.voxel_size_um)
        for logger in loggers:
            for path in sorted(folder.iterdir()):
                logger.experiment.log_artifact(logger.run_id, str(path))
        pl_module.print(f"fgat: results -> {folder}")
