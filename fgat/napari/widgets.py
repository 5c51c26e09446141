"""The dock widgets: Calibrate, Deconvolve and Fit.

Each widget turns its fields into the words of the fgat command it stands for
(``python -m fgat calibrate|deconvolve|fit ...``) and runs that command in a thread worker
(:func:`fgat.app.cli.run_command`), so the viewer never waits and the files it writes are those
the command line writes from the same inputs. An image layer opened from a TIFF file is passed
as that file; other layers are written as TIFF files named after the layers in a temporary
folder, removed when the run ends. Progress shows in
napari's activity dock; **Cancel** stops a deconvolution after the iteration under way and a fit
after the step under way (:mod:`fgat.app.monitor`); an error shows as one notification with the
command line's one-line message. The results open through the plugin's reader
(:mod:`fgat.napari.reader`) with their scales and metadata.
"""

from __future__ import annotations

import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import napari
import numpy as np
import torch
import yaml
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    Label,
    LineEdit,
    PushButton,
    SpinBox,
    create_widget,
)
from napari.layers import Image, Layer
from napari.qt.threading import create_worker
from napari.utils import progress
from napari.utils.notifications import show_error, show_info
from qtpy.QtCore import QObject, Signal

from fgat.app.cli import run_command
from fgat.app.monitor import Cancelled, Monitor, monitored
from fgat.app.process import USER_ERRORS
from fgat.io.images import read_tiff, tiff_shape, write_tiff
from fgat.napari.reader import get_reader
from fgat.optics.systems import PRESETS
from fgat.recon.estimation import ESTIMATES


def keep_triton_out() -> None:
    """On a machine without CUDA, make ``import triton`` fail in this process (as it fails
    where Triton is not installed), unless it is loaded already.

    Lightning loads Triton through ``torch._dynamo`` when a fit starts; loaded after napari has
    drawn with Mesa's software OpenGL (llvmpipe: virtual machines, remote desktops, CI), Triton's
    LLVM clashes with Mesa's and the process crashes. Without CUDA, Triton serves fgat nothing
    (its kernels run on GPUs; :func:`fgat._core.devices.use_triton`)."""
    if "triton" not in sys.modules and not torch.cuda.is_available():
        sys.modules["triton"] = None


keep_triton_out()

SYSTEM_FILE = "YAML file below"
"""The choice of the system menu that takes the system from the file field."""


def run_monitored(words: list[str], monitor: Monitor) -> tuple[str, str | None]:
    """Run the fgat command ``words`` under ``monitor`` (in a worker thread); never raises.

    Returns
    -------
    (outcome, line)
        ``("done", None)``, ``("cancelled", line)`` or ``("error", line)``, the line as the
        command line prints it (``fgat <command>: error: <message>``).
    """
    command = words[0]
    try:
        with monitored(monitor):
            run_command(words)
    except Cancelled as stop:
        return "cancelled", f"fgat {command}: {stop}"
    except USER_ERRORS as error:
        return "error", f"fgat {command}: error: {error}"
    except SystemExit as stop:  # an option parser's refusal, printed on stderr
        return "error", f"fgat {command}: error: options refused (exit code {stop.code})"
    except Exception as error:  # an unexpected failure: one line too, not a traceback
        return "error", f"fgat {command}: {type(error).__name__}: {error}"
    if monitor.cancelled:  # a fit stops between steps and ends as a complete run
        return "cancelled", f"fgat {command}: cancelled at step {monitor.outputs.get('step')}"
    return "done", None


def layer_file(layer: Image, folder: Path) -> Path:
    """The TIFF a command reads for ``layer``: the file it was opened from when that is a TIFF
    whose content is still the layer's (so the command sees the file's folder too, e.g. the
    ``params.yaml`` of a simulation beside it), else its data written as
    ``<folder>/<layer name>.tif`` with its own values and type: a layer edited since it was
    opened is passed as edited."""
    source = layer.source.path
    data = layer.data
    if source and Path(source).suffix.lower() in (".tif", ".tiff") and Path(source).is_file():
        if tiff_shape(source) == (tuple(data.shape), np.dtype(data.dtype)):
            if holds_file(np.asarray(data), source):
                return Path(source)
    name = "".join(c if c.isalnum() or c in "-_." else "_" for c in layer.name) or "layer"
    return write_tiff(folder / f"{name}.tif", np.asarray(data))


def holds_file(data: np.ndarray, path: str) -> bool:
    """Whether ``data`` is the TIFF's image as a layer opened from it holds it: as stored
    (napari's own reader), or as fgat's reader gives it when it opens the file (a volume
    recorded ``down`` reversed, for one)."""
    if np.array_equal(data, read_tiff(path)):
        return True
    reader = get_reader(path)
    images = [] if reader is None else [d for d, _, kind in reader(path) if kind == "image"]
    return len(images) == 1 and np.array_equal(data, np.asarray(images[0]))


def input_file(field, inputs: Path, what: str) -> Path:
    """The file a command reads for the layer chosen in the layer menu ``field``
    (:func:`layer_file`); refused, naming the field, when none is chosen."""
    if field.value is None:
        raise ValueError(f"{field.label}: open or choose {what}")
    return layer_file(field.value, inputs)


def read_layers(path: Path, kinds: tuple[str, ...] = ("image", "points", "shapes")) -> list:
    """The layers fgat's reader makes of ``path`` (only those of ``kinds``)."""
    reader = get_reader(str(path))
    if reader is None:
        raise ValueError(f"{path}: not a file or folder fgat's napari reader opens")
    return [Layer.create(*data) for data in reader(str(path)) if data[2] in kinds]


def system_words(choice: str, file: Path | None) -> list[str]:
    """``--system`` with the shipped system ``choice`` or the YAML ``file``."""
    if choice != SYSTEM_FILE:
        return ["--system", choice]
    if file is None or not str(file).strip() or not Path(file).is_file():
        raise ValueError(f"system: choose a YAML file (got {str(file or '')!r})")
    return ["--system", str(file)]


def given_path(value) -> Path | None:
    """A file field's path, ``None`` when it is empty."""
    text = str(value or "").strip()
    return None if text in ("", ".") else Path(text)


class ProgressRelay(QObject):
    """Progress bars for a command in a worker thread, drawn in the viewer's thread: the
    worker's bars (:meth:`bar`, the ``progress`` of its :class:`~fgat.app.monitor.Monitor`)
    emit signals that Qt delivers to this object's thread, where napari's ``progress`` bars
    (shown in the activity dock) are made, advanced and closed."""

    opened = Signal(object, str)
    advanced = Signal(int)
    closed = Signal()

    def __init__(self) -> None:
        super().__init__()
        self.current = None
        self.opened.connect(self._open)
        self.advanced.connect(self._advance)
        self.closed.connect(self.finish)

    def bar(self, *, total: int | None, desc: str, unit: str = "it") -> RelayedBar:
        return RelayedBar(self, total, desc)

    def _open(self, total, desc: str) -> None:
        self.finish()
        self.current = progress(total=total, desc=desc)

    def _advance(self, steps: int) -> None:
        if self.current is not None:
            self.current.update(steps)

    def finish(self) -> None:
        """Close the bar shown, if any."""
        if self.current is not None:
            self.current.close()
            self.current = None


class RelayedBar:
    """A worker thread's end of a :class:`ProgressRelay` bar, used as a ``tqdm`` bar is."""

    def __init__(self, relay: ProgressRelay, total: int | None, desc: str) -> None:
        self.relay = relay
        relay.opened.emit(total, desc)

    def update(self, steps: int = 1) -> None:
        self.relay.advanced.emit(int(steps))

    def close(self) -> None:
        self.relay.closed.emit()

    def __enter__(self) -> RelayedBar:
        return self

    def __exit__(self, *error) -> None:
        self.close()


class CommandWidget(Container):
    """A form that runs one fgat command in a thread worker, with Run and Cancel buttons and a
    status line. Subclasses give the command's words (:meth:`words`) and show its results
    (:meth:`show`).

    Attributes
    ----------
    outcome : tuple or None
        The last run's ``(outcome, line)`` (:func:`run_monitored`).
    cancel_latency_s : float or None
        Seconds from the last Cancel to the end of that run.
    """

    command = ""

    def __init__(self, viewer: napari.viewer.Viewer, fields: list) -> None:
        self.viewer = viewer
        self.run_button = PushButton(text="Run")
        self.cancel_button = PushButton(text="Cancel", enabled=False)
        self.status = Label(value="")
        super().__init__(widgets=[*fields, self.run_button, self.cancel_button, self.status])
        self.run_button.changed.connect(self.start)
        self.cancel_button.changed.connect(self.cancel)
        self.worker = None
        self.monitor: Monitor | None = None
        self.outcome: tuple[str, str | None] | None = None
        self.cancel_latency_s: float | None = None
        self._cancelled_at: float | None = None
        self._inputs: Path | None = None
        self.relay = ProgressRelay()

    def words(self, inputs: Path) -> list[str]:
        """The command line (without ``python -m fgat``); input layers go to ``inputs``."""
        raise NotImplementedError

    def show(self, monitor: Monitor) -> None:
        """Add the finished run's results to the viewer."""
        raise NotImplementedError

    def start(self) -> None:
        """Check the fields and start the command in a thread worker."""
        if self.worker is not None:
            return
        self._inputs = Path(tempfile.mkdtemp(prefix="fgat-napari-"))
        try:
            words = self.words(self._inputs)
        except (ValueError, FileNotFoundError) as error:
            self._end(("error", f"fgat {self.command}: error: {error}"))
            return
        self.monitor = Monitor(progress=self.relay.bar)
        self.outcome, self.cancel_latency_s, self._cancelled_at = None, None, None
        self.status.value = f"running: fgat {self.command} ..."
        self.worker = create_worker(
            run_monitored, words, self.monitor, _progress={"desc": f"fgat {self.command}"}
        )
        self.worker.returned.connect(self._end)
        self.run_button.enabled, self.cancel_button.enabled = False, True
        self.worker.start()

    def cancel(self) -> None:
        """Ask the run under way to stop at its next check."""
        if self.monitor is not None and self.worker is not None:
            self._cancelled_at = time.perf_counter()
            self.monitor.cancel()
            self.status.value = "cancelling ..."

    @property
    def running(self) -> bool:
        return self.worker is not None

    def _end(self, outcome: tuple[str, str | None]) -> None:
        self.outcome = outcome
        if self._cancelled_at is not None:
            self.cancel_latency_s = time.perf_counter() - self._cancelled_at
        kind, line = outcome
        try:
            if kind == "error":
                show_error(line)
                self.status.value = line
            elif self.monitor is not None:
                if kind == "cancelled":
                    show_info(f"{line} ({self.cancel_latency_s:.2f} s after Cancel)")
                    self.status.value = line
                if kind == "done" or self.monitor.outputs:
                    self.show(self.monitor)
        except (ValueError, FileNotFoundError) as error:
            self.outcome = ("error", f"fgat {self.command}: error: {error}")
            show_error(self.outcome[1])
        finally:
            self.relay.finish()
            if self._inputs is not None:
                shutil.rmtree(self._inputs, ignore_errors=True)
            self.worker, self._inputs = None, None
            self.run_button.enabled, self.cancel_button.enabled = True, False


def _image_choice(label: str, nullable: bool = False):
    return create_widget(annotation=Image, label=label, options={"nullable": nullable})


def _system_fields(default: str) -> tuple[ComboBox, FileEdit]:
    choice = ComboBox(label="system", choices=[*PRESETS, SYSTEM_FILE], value=default)
    file = FileEdit(label="system YAML", filter="*.yaml *.yml", value="")
    return choice, file


class CalibrateWidget(CommandWidget):
    """``python -m fgat calibrate``: the lenslet centres and the hexagonal lattice of an image of
    the MLA (or of the sample), optional dark and flat frames, written to a calibration folder;
    the centres (numbered in fgat's view order) and the lattice appear over the image, the fit
    quality in the status line."""

    command = "calibrate"

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self.image = _image_choice("image")
        self.system, self.system_file = _system_fields("small37")
        self.dark = _image_choice("dark (optional)", nullable=True)
        self.flat = _image_choice("MLA flat (optional)", nullable=True)
        self.out = FileEdit(label="calibration folder", mode="d", value="calib")
        self.overwrite = CheckBox(label="replace an existing calibration", value=False)
        fields = [self.image, self.system, self.system_file, self.dark, self.flat, self.out]
        super().__init__(viewer, [*fields, self.overwrite])

    def words(self, inputs: Path) -> list[str]:
        image = input_file(self.image, inputs, "the image of the lenslets")
        words = ["calibrate", "--image", str(image)]
        words += system_words(self.system.value, given_path(self.system_file.value))
        for flag, field in (("--dark", self.dark), ("--flat", self.flat)):
            if field.value is not None:
                words += [flag, str(layer_file(field.value, inputs))]
        out = given_path(self.out.value)
        if out is None:
            raise ValueError("calibration folder: choose where to write the calibration")
        return [*words, "--out", str(out), *(["--overwrite"] if self.overwrite.value else [])]

    def show(self, monitor: Monitor) -> None:
        folder = given_path(self.out.value)
        image = self.image.value
        for layer in read_layers(folder, ("points", "shapes")):
            layer.scale, layer.translate = image.scale[-2:], image.translate[-2:]
            self.viewer.add_layer(layer)
        quality = yaml.safe_load((folder / "lattice.yaml").read_text())["quality"]
        self.status.value = (
            f"{quality['views_found']} of {quality['n_views']} views found, residual RMS "
            f"{quality['residual_rms_px']:.2f} px, median view contrast "
            f"{quality['median_contrast']:.1f} noise std -> {folder}"
        )


class DeconvolveWidget(CommandWidget):
    """``python -m fgat deconvolve``: SHB or RL deconvolution of a sensor image with a
    calibration folder (the PSF computed from the system at the given depths) or a PSF file;
    iterations in the activity dock, the volume as a layer with its voxel size and depths,
    written to the chosen file (or to a temporary one, to save with File > Save Selected
    Layers)."""

    command = "deconvolve"

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self.measurement = _image_choice("measurement")
        self.calibration = FileEdit(label="calibration folder", mode="d", value="")
        self.psf = FileEdit(label="PSF file (optional)", filter="*.tif *.tiff", value="")
        self.system, self.system_file = _system_fields("small37")
        self.depths = LineEdit(label="depths (um)", value="-4:4:25")
        self.method = ComboBox(label="method", choices=["shb", "rl"], value="shb")
        self.iterations = SpinBox(label="iterations", min=1, max=100000, value=30)
        self.out = FileEdit(label="volume file (optional)", mode="w", filter="*.ome.tif", value="")
        self.overwrite = CheckBox(label="replace an existing file", value=False)
        fields = [self.measurement, self.calibration, self.psf, self.system, self.system_file]
        fields += [self.depths, self.method, self.iterations, self.out, self.overwrite]
        super().__init__(viewer, fields)
        self.written: Path | None = None

    def words(self, inputs: Path) -> list[str]:
        measurement = input_file(self.measurement, inputs, "the sensor image")
        words = ["deconvolve", "--measurement", str(measurement)]
        calibration, psf = given_path(self.calibration.value), given_path(self.psf.value)
        if calibration is None:
            raise ValueError("calibration folder: choose one (python -m fgat calibrate)")
        words += ["--calibration", str(calibration)]
        if psf is not None:
            words += ["--psf", str(psf)]
        else:
            words += system_words(self.system.value, given_path(self.system_file.value))
            words += [f"--depths-um={self.depths.value.strip()}"]
        out = given_path(self.out.value)
        if out is None:
            name = f"{measurement.stem}-{self.method.value}.ome.tif"
            out = Path(tempfile.mkdtemp(prefix="fgat-volume-")) / name
        self.written = out
        words += ["--method", self.method.value, "--iterations", str(self.iterations.value)]
        return [*words, "--out", str(out), *(["--overwrite"] if self.overwrite.value else [])]

    def show(self, monitor: Monitor) -> None:
        for layer in read_layers(self.written, ("image",)):
            layer.name = f"{self.method.value.upper()} {self.measurement.value.name}"
            self.viewer.add_layer(layer)
        self.status.value = f"{self.method.value.upper()} volume -> {self.written}"


class FitWidget(CommandWidget):
    """``python -m fgat fit``: the static stage (Gaussians, optics fixed or estimated) on a
    sensor image with config files, a calibration and overrides; progress per step, the MLflow
    run it logged to, and the fitted volume (with the SHB one) as layers when done."""

    command = "fit"

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self.measurement = _image_choice("measurement")
        self.configs = FileEdit(label="config files", mode="rm", filter="*.yaml *.yml")
        self.calibration = FileEdit(label="calibration folder (optional)", mode="d", value="")
        self.system, self.system_file = _system_fields("small37")
        self.depths = LineEdit(label="depths (um)", value="-4:4:25")
        self.optics = ComboBox(label="optics estimated", choices=list(ESTIMATES), value="none")
        self.overrides = LineEdit(label="overrides", value="")
        fields = [self.measurement, self.configs, self.calibration, self.system]
        fields += [self.system_file, self.depths, self.optics, self.overrides]
        super().__init__(viewer, fields)

    def words(self, inputs: Path) -> list[str]:
        measurement = input_file(self.measurement, inputs, "the sensor image")
        configs = [Path(path) for path in (self.configs.value or ()) if given_path(path)]
        if not configs:
            raise ValueError("config files: choose at least one (e.g. configs/measured.yaml)")
        words = ["fit", *(word for path in configs for word in ("--config", str(path)))]
        words.append(f"--data.init_args.measurement={measurement}")
        calibration = given_path(self.calibration.value)
        if calibration is not None:
            words.append(f"--data.init_args.calibration={calibration}")
        system = system_words(self.system.value, given_path(self.system_file.value))[1]
        words += [f"--data.init_args.system={system}"]
        words += [f"--data.init_args.depths_um={self.depths.value.strip()}"]
        words.append(f"--model.init_args.optics.estimate={self.optics.value}")
        try:
            return words + shlex.split(self.overrides.value)
        except ValueError as error:
            raise ValueError(f"overrides: {error}") from None

    def show(self, monitor: Monitor) -> None:
        folder = Path(monitor.outputs["results"])
        for layer in read_layers(folder, ("image",)):
            self.viewer.add_layer(layer)
        runs = "; ".join(
            f"MLflow run {name} ({run_id}) in experiment '{experiment}' at {uri}"
            for name, run_id, experiment, uri in monitor.outputs.get("mlflow", [])
        )
        line = f"fit ended at step {monitor.outputs['step']}: results {folder}"
        self.status.value = f"{line}; {runs}" if runs else line
        show_info(self.status.value)
