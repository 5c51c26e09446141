"""Files a reconstruction leaves behind: volumes, Gaussians and figures (also in MLflow), and
the volume series a ``predict`` run renders."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import torch
import yaml
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import rank_zero_info

from fgat.app.callbacks.mlflow import mlflow_loggers, results_folder
from fgat.app.modules.shell import log_event
from fgat.app.report import RESIDUAL_FILE, report_lines, residual_report, write_report
from fgat.io.files import atomic_path, check_output_file, write_csv
from fgat.io.images import volume_entries, write_tiff
from fgat.io.zarr_series import ZarrSeriesWriter, is_zarr
from fgat.optics.acquisition import crop_guard
from fgat.optics.zernike import wavefront_map
from fgat.recon import names
from fgat.recon.metrics import compare_volumes, relative_residual, residual_ratios, residual_sums
from fgat.recon.optics_report import optics_metrics
from fgat.recon.outcome import VolumeRecord, check_fit
from fgat.viz.figures import plot_curves
from fgat.viz.optics import (
    plot_coefficients,
    plot_psf_stack,
    plot_pupil_phases,
    plot_standard_errors,
)
from fgat.viz.volumes import mip_series_columns, plot_mip_series, plot_mips


def write_scene_volume(
    path: Path, volume: np.ndarray, axes: str, scene, time_interval_s: float | None = None
) -> None:
    """Write a volume ``(Z, Y, X)`` or series ``(T, Z, Y, X)`` of ``scene`` as OME-TIFF with its
    voxel sizes, depth axis, plane depths and view order (:meth:`Scene.volume_entries`), and the
    seconds between time points when known."""
    write_tiff(
        path,
        volume,
        axes=axes,
        voxel_size_um=scene.voxel_size_um,
        metadata=scene.volume_entries(),
        time_interval_s=time_interval_s,
    )


def seconds_per_unit_time(scene) -> float | None:
    """The duration of ``scene``'s sequence in seconds (first to last frame): seconds per unit
    of normalised time; ``None`` without ``frame_interval_s`` or a sequence."""
    if scene.frame_interval_s is None or scene.n_frames < 2:
        return None
    return scene.frame_interval_s * (scene.n_frames - 1)


def times_interval_s(times, scene) -> float | None:
    """Seconds between evenly spaced normalised ``times`` of ``scene`` (the time axis of a
    series rendered at them); ``None`` when uneven, fewer than two or of unknown duration."""
    duration, steps = seconds_per_unit_time(scene), np.diff(np.asarray(times, dtype=np.float64))
    if duration is None or len(steps) == 0 or not np.allclose(steps, steps[0], rtol=1e-6):
        return None
    return float(steps[0]) * duration if steps[0] > 0 else None


class ReconstructionArtifacts(pl.Callback):
    """At the end of a fit write, under ``<default_root_dir>/results/<run>``, for the static stage:

    * ``volume.ome.tif``: the reconstruction ``(Z, Y, X)`` in measurement counts, with voxel sizes,
      depth axis, depths and view order (:func:`fgat.io.images.volume_metadata`);
    * ``gaussians.pt``: the Gaussian set (see :meth:`fgat.gaussians.cloud.GaussianCloud.save`);
    * ``shb.ome.tif``: the SHB baseline the validation compares against, in counts;
    * on phantoms, ``truth.ome.tif``: the ground truth in counts too (:func:`truth_in_counts`),
      on the same grid and with the same metadata as ``volume.ome.tif``;
    * with JPGM self-estimation, ``psf.ome.tif`` (the estimated PSF stack), ``optics.yaml``
      (its Zernike coefficients in waves and lenslet shifts in pixels), ``pupil_phase.png``,
      ``zernike.png`` and ``psf_<ideal|estimated|truth>.png``; and, unless
      ``optics.identifiability`` is off, the standard errors of the estimated parameters
      (:func:`identifiability_files`: ``identifiability.csv``, ``identifiability.png`` and the
      ``zernike/stderr_c{j}``, ``shift/stderr_...`` metrics);
    * with ``estimate_gains``, ``gains.yaml`` (``gains: [...]``, the effective per-view gains of
      the forward model, which the dynamic stage uses);
    * ``mips.png``: x-y and x-z MIPs of the reconstruction (labelled 3DGAT with the optics held
      fixed, 4DGAT with them estimated), the SHB baseline and the truth;

    for the dynamic stage:

    * ``volumes.ome.tif``: the volumes ``(T, Z, Y, X)`` at the frames' times, in counts;
    * ``mips_time.png``: x-y MIPs over time of the reconstruction, of ``G_0`` at every frame (no
      deformation) and of the truth;
    * on phantoms, ``frames.csv`` and ``psnr_frames.png``: per-frame volume PSNR and SSIM of both
      (also logged as ``frame/...`` metrics with the frame index as step).

    Every file is also logged to the run of each MLflow logger.
    """

    def on_fit_end(self, trainer, pl_module) -> None:
        # on_fit_end, not on_train_end: a stage skipped before its first step still has a result
        if not trainer.is_global_zero:
            return
        loggers = mlflow_loggers(trainer)
        folder = results_folder(trainer)
        folder.mkdir(parents=True, exist_ok=True)
        written = VolumeRecord()
        if pl_module.per_frame:
            residual = self._sequence_files(trainer, pl_module, folder, written)
        else:
            residual = self._static_files(trainer, pl_module, folder, written)
        report = fit_report(trainer, pl_module, residual)
        log_report(trainer, report)
        write_report(folder / RESIDUAL_FILE, report)
        for logger in loggers:
            for path in sorted(folder.iterdir()):
                logger.experiment.log_artifact(logger.run_id, str(path))
        trend = pl_module.loss_trend
        check_fit(written, trend.first, trend.last, folder)  # a failure marks the run FAILED
        # rank_zero_info, not pl_module.print: the progress bars are closed by now and would
        # swallow it
        rank_zero_info(fit_summary(trainer, folder, report))

    @classmethod
    def _static_files(
        cls, trainer, pl_module, folder: Path, written: VolumeRecord
    ) -> dict[str, object]:
        """Write the static stage's files (recorded in ``written`` for the end check); the
        relative data residual of its final state (:func:`~fgat.recon.metrics.relative_residual`
        with the fit's forward model, gains and mask)."""
        engine = pl_module.engine
        scene = engine.scene
        volume = engine.volume().cpu().numpy() * scene.scale
        written.add(volume)
        write_scene_volume(folder / "volume.ome.tif", volume, "ZYX", scene)
        engine.cloud.save(folder / "gaussians.pt")
        if engine.jpgm is not None:  # the self-estimated optics
            cls._optics_files(engine, folder)
            identifiability_files(trainer, engine, folder)
            settling = engine.optics_settling()
            if settling is not None:
                warnings.warn(settling, RuntimeWarning, stacklevel=2)
        if engine.log_gains is not None:  # the estimated gains
            with atomic_path(folder / "gains.yaml") as temporary, torch.no_grad():
                temporary.write_text(yaml.safe_dump({"gains": engine.gains().tolist()}))
        label = static_label(engine)
        panels, units = {label: volume}, {label: "counts"}
        if engine.baseline is not None:
            baseline = engine.baseline.numpy() * scene.scale
            write_scene_volume(folder / "shb.ome.tif", baseline, "ZYX", scene)
            label = f"SHB {engine.settings.baseline_iterations} it."
            panels[label], units[label] = baseline, "counts"
        if scene.truth is not None:
            panels["ground truth"] = scene.truth
            truth = truth_in_counts(engine)
            write_scene_volume(folder / "truth.ome.tif", truth, "ZYX", scene)
        plot_mips(
            panels,
            folder / "mips.png",
            title=f"{scene.name}: maximum intensity projections",
            voxel_size_um=scene.voxel_size_um,
            units=units,
        )
        return relative_residual(
            engine.operator, engine.grid_volume(), engine.measurement, engine.mask
        )

    @staticmethod
    def _sequence_files(
        trainer, pl_module, folder: Path, written: VolumeRecord
    ) -> dict[str, object]:
        """The series, its per-frame scores and MIPs, one frame at a time: memory holds one
        volume (and the few x-y MIPs the figure shows), however long the sequence. Returns the
        relative data residual over all frames (:func:`~fgat.recon.metrics.residual_sums` added over
        them)."""
        engine = pl_module.engine
        scene = engine.scene
        times = engine.times
        still = engine.still_volume().cpu().numpy() * scene.scale
        truth = scene.truth_frames
        scores = None if truth is None else FrameScores()
        rows = {"4DGAT": [], "no deformation": []} | ({} if truth is None else {"ground truth": []})
        maxima = dict.fromkeys(rows, 0.0)
        shown = set(mip_series_columns(len(times)).tolist())
        path = folder / series_name((len(times), *still.shape))
        sums = None  # the residual's, added over the frames
        interval = scene.frame_interval_s
        with (
            SceneSeries(path, scene, still.shape, time_interval_s=interval) as series,
            torch.no_grad(),
        ):
            for index, t in enumerate(times):
                grid = engine.grid_volume_at(float(t))
                views = np.ascontiguousarray(engine.frames[index])
                frame = residual_sums(engine.operator, grid, views, engine.mask)
                sums = frame if sums is None else [a + b for a, b in zip(sums, frame)]
                volume = crop_guard(grid, scene.guard_px).cpu().numpy() * scene.scale
                series.append(volume)
                written.add(volume)
                frame = {"4DGAT": volume, "no deformation": still}
                if truth is not None:
                    frame["ground truth"] = truth[index]
                    scores.add(trainer, index, float(t), volume, still, truth[index])
                for label, values in frame.items():
                    maxima[label] = max(maxima[label], float(values.max()))
                    if index in shown:
                        rows[label].append(values.max(axis=0)[None])
        if scores is not None:
            scores.write(folder)
        plot_mip_series(
            {label: np.stack(mips) for label, mips in rows.items()},
            times[sorted(shown)],
            folder / "mips_time.png",
            title=f"{scene.name}: x-y MIPs over time",
            voxel_size_um=scene.voxel_size_um,
            units={"4DGAT": "counts", "no deformation": "counts"},
            maxima=maxima,
        )
        return residual_ratios(*sums)

    @staticmethod
    def _optics_files(engine, folder: Path) -> None:
        """Estimated PSF stack (``psf.ome.tif``, its planes in the scene's depth-axis order,
        which it records with their depths) and parameters; pupil-phase maps, coefficient bars
        and per-view PSF MIPs (ideal, estimated and, on phantoms, true)."""
        scene, jpgm = engine.scene, engine.jpgm
        write_tiff(
            folder / "psf.ome.tif",
            engine.psf.cpu().numpy(),
            axes="CZYX",
            voxel_size_um=scene.voxel_size_um,
            metadata=volume_entries(scene.depth_axis, scene.depths_um, content="psf"),
        )
        with atomic_path(folder / "optics.yaml") as temporary:
            temporary.write_text(yaml.safe_dump(optics_metrics(jpgm), sort_keys=False))
        phases = {"estimated": jpgm.pupil_phase_map().numpy()}
        coefficients = {"estimated": jpgm.zernike_coefficients.detach().cpu().tolist()}
        stacks = {
            "ideal": torch.from_numpy(scene.optics.ideal().psf()),
            "estimated": engine.psf.cpu(),
        }
        if engine.true_psf is not None:  # a phantom: its true optics
            truth = engine.true_parameters()[0]
            phases["truth"] = wavefront_map(jpgm.zernike_indices, truth).numpy()
            coefficients["truth"] = truth.tolist()
            stacks["truth"] = engine.true_psf.cpu()
        plot_pupil_phases(phases, folder / "pupil_phase.png", title="Zernike pupil phase")
        plot_coefficients(
            jpgm.zernike_indices, coefficients, folder / "zernike.png", title="Zernike coefficients"
        )
        for label, stack in stacks.items():
            plot_psf_stack(
                stack.numpy(),
                folder / f"psf_{label}.png",
                title=f"{label} PSF",
                depths_um=list(scene.optics.depths_um),
                pixel_um=scene.voxel_size_um[2],
            )


def truth_in_counts(engine) -> np.ndarray:
    """A phantom's ground truth ``(Z, Y, X)`` in measurement counts, comparable voxel by voxel
    with ``volume.ome.tif``: ``k s x_true``, where ``s`` is the scene's counts per normalised
    unit (:attr:`Scene.scale <fgat.recon.scene.Scene>`, by which the reconstruction is written)
    and ``k = <A x_true, y> / ||A x_true||^2`` (over the unmasked pixels) the least-squares
    brightness of the truth's forward projection ``A x_true`` against the normalised
    measurement ``y``, with the phantom's true PSF when the fit knows it (optics estimated),
    else the scene's. The truth's own units are the phantom's (peak 1), which the measurement's
    photon scale, background and noise do not preserve."""
    scene = engine.scene
    psf = engine.true_psf if engine.true_psf is not None else torch.as_tensor(scene.psf)
    operator = scene.operator(psf.detach().float().cpu())
    truth = torch.as_tensor(np.asarray(scene.truth, dtype=np.float32))
    measurement = torch.as_tensor(scene.measurement, dtype=torch.float32)
    weights = 1.0 if scene.mask is None else torch.as_tensor(scene.mask)
    with torch.no_grad():
        prediction = operator.forward(operator.pad(truth)) * weights
        norm = float(prediction.square().sum())
        brightness = float((prediction * measurement * weights).sum()) / max(norm, 1e-30)
    return truth.numpy() * (brightness * scene.scale)


def static_label(engine) -> str:
    """What a static fit ran, as its figures name it: 3DGAT with the optics held fixed, 4DGAT's
    static stage with them estimated (JPGM self-estimation)."""
    if engine.jpgm is None:
        return "3DGAT (Gaussians, optics fixed)"
    return "4DGAT static (Gaussians, optics estimated)"


STDERR_PANELS = {
    "zernike/c": "Zernike (waves)",
    "shift/b": "intercept (px)",
    "shift/s": "slope (px)",
}
"""Prefix of a parameter's logged name -> its panel in ``identifiability.png``."""


def identifiability_files(trainer, engine, folder: Path) -> None:
    """The standard errors of the estimated optics at the end of a static fit
    (:meth:`~fgat.recon.StaticReconstruction.identifiability`): logged as metrics at
    the last step, ``identifiability.csv`` (per parameter: estimate, standard error, relative
    standard error, flagged, and on phantoms truth, error and whether it is within 2 s.e.) and
    ``identifiability.png``; or one line saying why they were skipped (switched off, more
    memory than the device has, a parameter with no effect on the image)."""
    try:
        result = engine.identifiability()
    except ValueError as error:
        rank_zero_info(f"fgat: identifiability skipped: {error}")
        return
    if result is None:
        rank_zero_info("fgat: identifiability skipped (model.optics.identifiability = false)")
        return
    log_event(trainer.loggers, result.metrics(), trainer.global_step)
    write_csv(folder / "identifiability.csv", result.columns(), result.rows())
    plot_standard_errors(
        [name.split("/")[1] for name in result.names],
        result.estimates,
        result.stderrs,
        result.flagged,
        folder / "identifiability.png",
        groups=[
            next(panel for prefix, panel in STDERR_PANELS.items() if name.startswith(prefix))
            for name in result.names
        ],
        truth=result.truth,
        title=f"estimated optics +/- 2 s.e. (flagged: s.e. > {result.tolerance:g} |estimate|)",
    )
    rank_zero_info(identifiability_summary(result, engine.estimation.estimate))


def identifiability_summary(result, estimate: str) -> str:
    """The line a fit prints about its standard errors: noise level, flagged terms, coverage on
    phantoms, and for a ``joint`` estimate how far the standard errors were found to hold."""
    summary = (
        f"fgat: identifiability: noise sigma {result.noise_sigma:.3g} (normalised units), "
        f"{int(result.flagged.sum())} of {len(result.names)} estimated terms flagged "
        f"(s.e. > {result.tolerance:g} |estimate|)"
    )
    if result.truth is not None:
        summary += f"; true error within 2 s.e. for {result.within_2se.mean():.0%} of them"
    if estimate == "joint":
        summary += (
            "; joint estimation: Zernike terms and shifts trade off (Notes S4-S5), and these "
            "local errors held only about a third of the true errors on Fig. S7 phantoms: read "
            "the coefficients and shifts as one optical model, not as separate measurements"
        )
    return summary


SUMMARY_SCORES = (
    (names.PSNR, "{:.2f} dB"),
    (names.PSNR_REGISTERED, "{:.2f} dB"),
    (names.SSIM, "{:.3f}"),
    (names.SSIM_XY, "{:.3f}"),
)
"""Logged scores a finished fit prints, with their format."""
BASELINES = ((names.SHB, "SHB"), (names.STILL, "G0 still"))


RESIDUAL, RESIDUAL_VIEW, CONVERGED, STOPPED = (
    "residual/relative",
    "residual/relative_view{}",
    "fit/converged",
    "fgat.stopped",
)
"""The fit report's metrics (at the last step) and the MLflow tag that says how it stopped."""


def fit_ending(trainer, pl_module) -> tuple[bool, str]:
    """Whether a fit converged, and the sentence that says how it stopped: by a stopping rule
    (a callback's or the module's ``reason`` / ``stop_reason``: plateau, held-out pixels,
    converged frames) before its step budget, or by its budget ``trainer.max_steps``."""
    step, budget = trainer.global_step, trainer.max_steps
    reasons = [c.reason for c in trainer.callbacks if getattr(c, "reason", None)]
    if getattr(pl_module, "stop_reason", None):
        reasons.append(pl_module.stop_reason)
    if reasons:
        return (
            True,
            f"converged: stopped at step {step} by its stopping rule ({'; '.join(reasons)})",
        )
    if budget == -1 or step < budget:
        return False, (
            f"stopped at step {step}, before its step budget ({budget}) and without a stopping "
            "rule's verdict"
        )
    rules = [type(c).__name__ for c in trainer.callbacks if hasattr(c, "rule")]
    return False, (
        f"stopped by its step budget (trainer.max_steps = {budget}) rather than converged"
        + (
            f" ({', '.join(rules)} not met)"
            if rules
            else " (no stopping rule: fgat.callbacks.PlateauStopping in trainer.callbacks adds one)"
        )
    )


def fit_report(trainer, pl_module, residual: dict[str, object]) -> dict[str, object]:
    """The fit's :func:`~fgat.app.report.residual_report`: the residual, how it stopped
    (:func:`fit_ending`), its stage, steps, step budget and last training loss."""
    converged, stopped = fit_ending(trainer, pl_module)
    return residual_report(
        residual,
        converged=converged,
        stopped=stopped,
        stage="dynamic" if pl_module.per_frame else "static",
        steps=trainer.global_step,
        max_steps=trainer.max_steps,
        loss=float(getattr(pl_module, "last_loss", math.nan)),
    )


def log_report(trainer, report: dict[str, object]) -> None:
    """Log the report to the trainer's loggers at the last step (``residual/relative``,
    ``residual/relative_view{v}``, ``fit/converged`` 1 or 0) and tag its MLflow runs with how the
    fit stopped (``fgat.stopped``)."""
    metrics = {RESIDUAL: report["relative_residual"], CONVERGED: float(report["converged"])}
    for view, value in enumerate(report["relative_residual_views"]):
        metrics[RESIDUAL_VIEW.format(view)] = value
    log_event(trainer.loggers, metrics, trainer.global_step)
    for logger in mlflow_loggers(trainer):
        logger.experiment.set_tag(logger.run_id, STOPPED, report["stopped"])


def fit_summary(trainer, folder: Path, report: dict[str, object] | None = None) -> str:
    """What a finished fit prints: the last validation's scores (beside the baseline's: SHB for
    the static stage, ``G_0`` left still for the dynamic one; the data misfit on measured
    sequences), the data residual, last loss and how the fit stopped (``report``,
    :func:`fit_report`), the results folder, and each MLflow run with the command that shows
    it."""
    metrics = {key: float(value) for key, value in trainer.callback_metrics.items()}
    scores = []
    for key, style in SUMMARY_SCORES:
        if key not in metrics:
            continue
        text = f"{key} {style.format(metrics[key])}"
        for suffix, label in BASELINES:
            if f"{key}{suffix}" in metrics:
                text += f" ({label} {style.format(metrics[f'{key}{suffix}'])})"
        scores.append(text)
    if not scores and names.LOSS_PIX in metrics:
        scores.append(f"{names.LOSS_PIX} {metrics[names.LOSS_PIX]:.4g}")
    lines = [
        f"fgat: fit finished at step {trainer.global_step}"
        + (f"; last validation: {', '.join(scores)}" if scores else "")
    ]
    if report is not None:
        lines.append(f"  data: {report_lines(report)}; last loss {report['loss']:.4g}")
    lines.append(f"  results: {folder}")
    for logger in mlflow_loggers(trainer):
        client = logger.experiment
        run = client.get_run(logger.run_id)
        experiment = client.get_experiment(run.info.experiment_id).name
        uri = client.tracking_uri
        browse = (
            f"open {uri}"
            if uri.startswith(("http://", "https://"))
            else f"mlflow ui --backend-store-uri {uri}"
        )
        lines.append(
            f"  MLflow: run {run.info.run_name} ({logger.run_id}) in experiment {experiment!r}; "
            f"to browse runs: {browse}"
        )
    return "\n".join(lines)


class FrameScores:
    """Per-frame volume PSNR/SSIM of the reconstruction and of ``G_0`` against the truth, added
    frame by frame (each logged as ``frame/...`` metrics at step = frame index), then written as
    ``frames.csv`` and ``psnr_frames.png``."""

    def __init__(self) -> None:
        self.rows: list[list[float]] = []
        self.columns: list[str] = []
        self.curves = {"volume": {"4DGAT": {}, "no deformation": {}}}

    def add(self, trainer, index: int, time: float, volume, still, truth) -> None:
        scores = {"": compare_volumes(volume, truth), names.STILL: compare_volumes(still, truth)}
        metrics = {
            key: value
            for suffix, s in scores.items()
            for key, value in names.volume_scores(s, suffix, prefix="frame/").items()
        }
        log_event(trainer.loggers, metrics, index)
        self.columns = list(metrics)
        self.rows.append([index, time, *metrics.values()])
        for suffix, label in (("", "4DGAT"), (names.STILL, "no deformation")):
            for key in ("psnr", "ssim"):
                self.curves["volume"][label].setdefault(key, []).append(scores[suffix][key])

    def write(self, folder: Path) -> None:
        write_csv(folder / "frames.csv", ["frame", "time", *self.columns], self.rows)
        plot_curves(
            self.curves,
            folder / "psnr_frames.png",
            xlabel="frame number (1 = first)",
            ylabels={"psnr": "volume PSNR (dB)", "ssim": "volume SSIM"},
            title="per-frame accuracy",
        )


SERIES_TIFF_BYTES = 1 << 30
"""A series up to this size (float32) is written as one OME-TIFF; a larger one as OME-Zarr."""


def series_name(shape, stem: str = "volumes") -> str:
    """``<stem>.ome.tif`` for a ``(T, Z, Y, X)`` float32 series of at most
    :data:`SERIES_TIFF_BYTES`, else ``<stem>.ome.zarr`` (written frame by frame)."""
    small = 4 * int(np.prod(shape)) <= SERIES_TIFF_BYTES
    return f"{stem}.ome.tif" if small else f"{stem}.ome.zarr"


class SceneSeries:
    """A scene's volume series written as it comes, frame by frame: an OME-Zarr image
    ``(T, 1, Z, Y, X)`` (``*.zarr`` paths; memory holds no frame), or an OME-TIFF ``(T, Z, Y,
    X)`` written when the block ends (small series; memory holds them). Both carry the scene's
    voxel sizes and volume entries, and appear at ``path`` only once whole.

    Parameters
    ----------
    path : Path
        Target file or store.
    scene : Scene
        Its voxel size and volume entries.
    frame_shape : (Z, Y, X)
        Shape of every volume.
    overwrite : bool
        Replace an existing Zarr store (a TIFF is replaced atomically either way).
    time_interval_s : float, optional
        Seconds between time points (the time axis counts frames without it).
    """

    def __init__(
        self,
        path: Path,
        scene,
        frame_shape,
        overwrite: bool = False,
        time_interval_s: float | None = None,
    ) -> None:
        self.path, self.scene, self.frame_shape = Path(path), scene, tuple(frame_shape)
        self.time_interval_s = time_interval_s
        self._frames: list[np.ndarray] = []
        self._store = None
        if is_zarr(self.path):
            self._store = ZarrSeriesWriter(
                self.path,
                (1, *self.frame_shape),
                voxel_size_um=scene.voxel_size_um,
                time_interval_s=time_interval_s,
                overwrite=overwrite,
                metadata=scene.volume_entries(),
            )

    def __enter__(self) -> SceneSeries:
        if self._store is not None:
            self._store.__enter__()
        return self

    def append(self, volume: np.ndarray) -> None:
        if self._store is not None:
            self._store.append(volume[None])
        else:
            self._frames.append(np.asarray(volume, np.float32))

    def __exit__(self, kind, error, trace) -> None:
        if self._store is not None:
            self._store.__exit__(kind, error, trace)
        elif kind is None and self._frames:
            volumes = np.stack(self._frames)
            write_scene_volume(self.path, volumes, "TZYX", self.scene, self.time_interval_s)
        self._frames = []


class VolumeSeriesWriter(BasePredictionWriter):
    """Write what a ``predict`` run renders (``{"index", "time", "volume"}`` per time point) as one
    OME-TIFF ``(T, Z, Y, X)`` at ``path``, or, for a ``*.zarr`` path, as an OME-Zarr image
    ``(T, 1, Z, Y, X)`` written volume by volume as they are rendered (each volume is dropped from
    the prediction once written, so memory holds one however many times are asked for); and the
    normalised times as ``<name>_times.csv`` (with the volume PSNR and x-y MIP SSIM against the
    truth on dynamic phantoms).

    Parameters
    ----------
    path : str or Path, optional
        Target file or store; default ``<default_root_dir>/predictions/volumes.ome.tif``.
    overwrite : bool
        Replace an existing target; otherwise an existing one is refused before rendering.
    """

    def __init__(self, path: str | Path | None = None, overwrite: bool = False) -> None:
        super().__init__(write_interval="batch_and_epoch")
        self.path, self.overwrite = path, overwrite
        self._series: SceneSeries | None = None
        self._rows: list[list[float]] = []

    def target(self, trainer) -> Path:
        return Path(self.path or Path(trainer.default_root_dir) / "predictions" / "volumes.ome.tif")

    def setup(self, trainer, pl_module, stage: str) -> None:
        """Before anything is rendered: the target must be writable, and new unless ``overwrite``
        (:func:`fgat.io.files.check_output_file`)."""
        if stage != "predict" or not trainer.is_global_zero:
            return
        path = self.target(trainer)
        if self.path is None:
            path.parent.mkdir(parents=True, exist_ok=True)
        check_output_file(path, overwrite=self.overwrite, option="--out")
        self._series, self._rows = None, []

    def write_on_batch_end(
        self, trainer, pl_module, prediction, batch_indices, batch, batch_idx, dataloader_idx=0
    ) -> None:
        if not (trainer.is_global_zero and isinstance(prediction, dict)):
            return
        scene = pl_module.scene
        if self._series is None:
            shape = prediction["volume"].shape
            planned = getattr(getattr(trainer, "datamodule", None), "predict_times", None)
            interval = times_interval_s(scene.sequence()[1] if planned is None else planned, scene)
            self._series = SceneSeries(
                self.target(trainer), scene, shape, self.overwrite, time_interval_s=interval
            )
            self._series.__enter__()
        self._series.append(prediction["volume"])
        self._rows += time_rows([prediction], scene)
        prediction["volume"] = None  # written: the predict loop keeps only its index and time

    def on_exception(self, trainer, pl_module, exception) -> None:
        if self._series is not None:  # a failed render leaves no half-written series
            series, self._series = self._series, None
            series.__exit__(type(exception), exception, None)

    def write_on_epoch_end(self, trainer, pl_module, predictions, batch_indices) -> None:
        if not trainer.is_global_zero or self._series is None:
            return
        series, self._series = self._series, None
        series.__exit__(None, None, None)
        path, scene, rows = series.path, pl_module.scene, self._rows
        times = path.with_name(path.name.split(".")[0] + "_times.csv")
        columns, note = ["index", "time"], ""
        if seconds_per_unit_time(scene) is not None:
            columns.append("time_s")
        if scene.truth_at is not None:  # a dynamic phantom: its truth at the rendered times
            columns += [names.VOLUME_SCORES["psnr"], names.VOLUME_SCORES["ssim_xy"]]
            note = (
                f"; mean volume PSNR {np.mean([row[-2] for row in rows]):.2f} dB "
                "against the phantom's truth"
            )
        write_csv(times, columns, rows)
        pl_module.print(
            f"fgat: {len(rows)} volumes {series.frame_shape} (Z, Y, X) -> {path} "
            f"(times: {times}){note}"
        )


def time_rows(items: list[dict], scene) -> list[list[float]]:
    """``[index, time]`` of rendered volumes (normalised time, and in seconds from the first
    frame when the scene's frame interval is known), with their volume PSNR and x-y MIP SSIM
    against a dynamic phantom's truth at that time."""
    duration = seconds_per_unit_time(scene)
    rows = [[item["index"], item["time"]] for item in items]
    if duration is not None:
        rows = [[*row, float(row[1]) * duration] for row in rows]
    if scene.truth_at is None:
        return rows
    truth = scene.truth_at(np.array([item["time"] for item in items]))
    scores = [compare_volumes(item["volume"], ref) for item, ref in zip(items, truth)]
    return [row + [score["psnr"], score["ssim_xy"]] for row, score in zip(rows, scores)]
