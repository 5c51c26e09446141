"""Hostile inputs over every command: each case ends in one clean refusal before any
computation, a warning, or a result that is right.

Each case writes the tiny inputs it needs (corrupt, empty, huge, NaN, wrong-unit or wrong-type)
into a folder of its own and runs ``python -m fgat ...`` there as a user does, with MLflow
logging into a SQLite file outside that folder and a per-case timeout (the process group is
killed and the case recorded as ``timeout``). Expectations:

* ``refuse``: a non-zero exit without a traceback; the last line of stderr is the only error
  line and names every one of the case's tokens (the option, file or field and what was
  expected); the command computed at most :data:`COMPUTE_BOUND_S` before refusing (its wall
  time less that of a trivial refusal by the same kind of command, which measures the start-up:
  imports); nothing left behind in the case's folder (no empty ``--out``, no 0-byte database,
  no lock file).
* ``warn``: exit 0 and a warning on stderr naming the tokens (a clean refusal naming them also
  passes: it is stricter).
* ``result``: exit 0 and a number printed by the command (a regular expression) equal to the
  right one within a relative tolerance.

The cases are those of the hardening issue (silently wrong results, sizes checked before
allocation, faults, messages that name the file and field) and variants of the class each one
stands for (NaN, infinite, negative and zero values of every numeric size option).
``tests/integration/test_hostile.py`` runs the same table in-process.

    python benchmarks/hostile.py [--only ID ...] [--timeout 60] \
        [--out benchmarks/results/hostile.json]
    python benchmarks/hostile.py --table benchmarks/results/hostile.json
    python benchmarks/hostile.py --compare benchmarks/results/hostile_before.json \\
        --table benchmarks/results/hostile.json
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import re
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

FGAT_ROOT = Path(__file__).resolve().parents[3]
"""The folder that holds this fgat package: first on the commands' ``PYTHONPATH``, so that they
run the fgat that runs the cases."""
COMPUTE_BOUND_S = 2.0
REFERENCE_REPEATS = 3  # runs of each start-up reference (their median)
TIMEOUT_S = 60.0
UNREACHABLE = "http://127.0.0.1:9"

SMALL_SIMULATION = {
    "system": "small",
    "depths_um": "-6:6:3",
    "view_size": 64,
    "phantom": {"kind": "beads", "n_beads": 6, "sigma": 1.0, "min_spacing": 6, "margin": [0, 8, 8]},
    "photons": 1000,
    "background": 100,
    "seed": 0,
}
TRAINER = {
    "max_steps": 2,
    "accelerator": "cpu",
    "val_check_interval": 2,
    "check_val_every_n_epoch": None,
    "num_sanity_val_steps": 0,
    "enable_progress_bar": False,
    "enable_model_summary": False,
}
PHANTOM_DATA = {
    "class_path": "fgat.datamodules.PhantomDataModule",
    "init_args": {
        "simulation": {
            "system": "small",
            "depths_um": "-9:9:7",
            "view_size": 32,
            "photons": None,
            "phantom": {
                "kind": "beads",
                "n_beads": 4,
                "sigma": 1.0,
                "min_spacing": 6,
                "margin": [1, 5, 5],
            },
        }
    },
}
TUBE_PIXEL_UM = 0.1
TUBE_SIGMA_PX = 2.0
TUBE_FWHM_UM = 2 * math.sqrt(2 * math.log(2)) * TUBE_SIGMA_PX * TUBE_PIXEL_UM
CELL_VOXEL_UM = (1.0, 0.5, 0.5)
TRACK_VOXEL_UM = (2.0, 0.5, 0.5)


# --------------------------------------------------------------------------------- the inputs


def static_config(n_gaussians: int = 300, root: str = "run", data: dict | None = None) -> dict:
    """A static fit of a few steps on a tiny phantom."""
    return {
        "seed_everything": 0,
        "trainer": {**TRAINER, "default_root_dir": root},
        "model": {
            "class_path": "fgat.modules.StaticModule",
            "init_args": {
                "n_gaussians": n_gaussians,
                "init_iterations": 5,
                "baseline_iterations": 5,
            },
        },
        "data": data or PHANTOM_DATA,
    }


def dynamic_config(static: str) -> dict:
    return {
        "seed_everything": 0,
        "trainer": {**TRAINER, "default_root_dir": "run"},
        "model": {
            "class_path": "fgat.modules.DynamicModule",
            "init_args": {"static": static, "width": 16},
        },
        "data": {
            "class_path": "fgat.datamodules.PhantomDataModule",
            "init_args": {
                "simulation": {
                    **PHANTOM_DATA["init_args"]["simulation"],
                    "frames": 5,
                    "phantom": {
                        "kind": "moving_beads",
                        "n_beads": 3,
                        "sigma": 1.0,
                        "velocity": [0.0, 6.0, 0.0],
                        "rotation_deg": 0.0,
                        "min_spacing": 5.0,
                        "margin": [2, 9, 5],
                    },
                }
            },
        },
    }


def write_yaml(path: Path, content) -> Path:
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def fgat_env(tracking: Path) -> dict[str, str]:
    """The environment of a command: this fgat first (:data:`FGAT_ROOT`), MLflow into
    ``tracking``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(FGAT_ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env["MLFLOW_TRACKING_URI"] = f"sqlite:///{tracking / 'mlflow.db'}"
    env.pop("FGAT_TRACEBACK", None)
    return env


class Workspace:
    """A case's folder (``folder``, the command's working directory), the inputs the cases
    share, made once in ``shared`` on first use, and the repository's ``configs`` folder (the
    shipped configs some cases start from)."""

    def __init__(self, folder: Path, shared: Path, configs: Path) -> None:
        self.folder, self.shared, self.configs = folder, shared, configs

    def _once(self, name: str, make: Callable[[Path], None]) -> Path:
        path = self.shared / name
        if not path.exists():
            partial = self.shared / f".{name}.partial"
            shutil.rmtree(partial, ignore_errors=True)
            partial.mkdir(parents=True)
            make(partial)
            partial.rename(path)
        return path

    def link(self, name: str, source: Path) -> str:
        """``source`` copied into the case's folder as ``name``; its name there."""
        target = self.folder / name
        if source.is_dir():
            shutil.copytree(source, target)
        else:
            shutil.copyfile(source, target)
        return name

    def write(self, name: str, data: bytes | str) -> str:
        path = self.folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(data, str):
            path.write_text(data)
        else:
            path.write_bytes(data)
        return name

    def yaml(self, name: str, content) -> str:
        write_yaml(self.folder / name, content)
        return name

    # -- shared inputs
    def deconvolution_inputs(self) -> Path:
        """``sensor.tif`` (256 x 256, 90..200 counts), ``psf.tif`` (7, 3, 9, 9), ``centers.csv``
        of the small system: a deconvolution whose default view is 76 x 76."""

        def make(folder: Path) -> None:
            from fgat.io.images import write_tiff  # imported when used: keeps start-up fast
            from fgat.optics.systems import load_system  # imported when used: keeps start-up fast

            rng = np.random.default_rng(0)
            write_tiff(folder / "sensor.tif", rng.uniform(90, 200, (256, 256)).astype(np.float32))
            psf = rng.uniform(0, 1, (7, 3, 9, 9)).astype(np.float32)
            write_tiff(folder / "psf.tif", psf, axes="CZYX")
            centers = load_system("small").lenslet_centers_px()
            (folder / "centers.csv").write_text(
                "row,col\n" + "".join(f"{r},{c}\n" for r, c in centers)
            )
            write_tiff(folder / "dim.tif", np.full((256, 256), 60.0, np.float32))

        return self._once("deconvolution", make)

    def simulation(self) -> Path:
        """``python -m fgat simulate`` of :data:`SMALL_SIMULATION` (small system, 64 x 64 views)."""

        def make(folder: Path) -> None:
            from fgat.sim.simulation import (  # imported when used: keeps start-up fast
                SimulationConfig,
                simulate,
                write_simulation,
            )

            write_simulation(simulate(SimulationConfig(**SMALL_SIMULATION)), folder / "sim")

        return self._once("simulation", make) / "sim"

    def lenslet_images(self) -> Path:
        """``mla7.tif``: a white-light image of the small system's 7 lenslets (disks);
        ``noise.tif``: pure camera noise; ``bright.tif``: a bright frame (the MLA image at
        ~2000 counts); all 256 x 256."""

        def make(folder: Path) -> None:
            from scipy import ndimage  # SciPy loaded when used: keeps start-up fast

            from fgat.io.images import write_tiff  # imported when used: keeps start-up fast
            from fgat.optics.systems import load_system  # imported when used: keeps start-up fast

            system = load_system("small")
            rows, cols = np.indices(system.sensor_shape)
            radius = 0.45 * system.pitch_px
            disks = sum(
                ((rows - r) ** 2 + (cols - c) ** 2 <= radius**2).astype(float)
                for r, c in system.lenslet_centers_px()
            )
            rng = np.random.default_rng(0)
            mla = 100 + 1000 * ndimage.gaussian_filter(disks, 1.0)
            write_tiff(folder / "mla7.tif", (mla + 3 * rng.standard_normal(mla.shape)).astype("f4"))
            write_tiff(folder / "noise.tif", rng.normal(100, 3, mla.shape).astype(np.float32))
            write_tiff(folder / "bright.tif", (2 * mla).astype(np.float32))

        return self._once("lenslets", make)

    def tube_images(self) -> Path:
        """A vertical Gaussian tube (s.d. 2 px = 0.2 um) as a volume (3, 64, 64) with its OME
        sizes in ``nm`` (``tube_nm.ome.tif``), as an image in ``mm`` (``tube_mm.ome.tif``), in an
        unknown unit (``tube_furlong.ome.tif``), in ``um`` (``tube_um.ome.tif``); a segment
        table across it, one with a non-numeric cell and one with a NaN half-length."""

        def make(folder: Path) -> None:
            import tifffile  # loaded when a file is read or written: keeps start-up fast

            x = np.arange(64)
            tube = np.exp(-0.5 * ((x - 31.3) / TUBE_SIGMA_PX) ** 2)
            image = np.tile(tube + 0.002 * x + 0.1, (64, 1)).astype(np.float32)
            volume = np.stack([image] * 3)
            for name, data, unit, scale in (
                ("tube_nm", volume, "nm", 1000.0),
                ("tube_mm", image, "mm", 1e-3),
                ("tube_furlong", volume, "furlong", 1.0),
                ("tube_um", volume, "µm", 1.0),
            ):
                metadata = {"axes": "ZYX"[-data.ndim :]}
                sizes = (1.0, TUBE_PIXEL_UM, TUBE_PIXEL_UM)[-data.ndim :]
                for axis, size in zip("ZYX"[-data.ndim :], sizes):
                    metadata[f"PhysicalSize{axis}"] = size * scale
                    metadata[f"PhysicalSize{axis}Unit"] = unit
                tifffile.imwrite(folder / f"{name}.ome.tif", data, ome=True, metadata=metadata)
            header = "center_y,center_x,axis_angle_rad,half_length_px\n"
            (folder / "segments.csv").write_text(header + f"40,31,{math.pi / 2},15\n")
            (folder / "segments_text.csv").write_text(header + f"40,a,{math.pi / 2},15\n")
            (folder / "segments_nan.csv").write_text(header + f"40,31,{math.pi / 2},nan\n")
            whole = (folder / "tube_um.ome.tif").read_bytes()
            (folder / "truncated.ome.tif").write_bytes(whole[: len(whole) // 2])

        return self._once("tubes", make)

    def cells(self) -> Path:
        """The cytometry phantom (24, 64, 64) at 1 x 0.5 x 0.5 um: ``nuclei.ome.tif``,
        ``CD11b.ome.tif``; 12 cells."""

        def make(folder: Path) -> None:
            from fgat.analysis.cytometry import (  # imported when used: keeps start-up fast
                cell_phantom,
            )
            from fgat.io.images import write_tiff  # imported when used: keeps start-up fast

            channels, _ = cell_phantom(
                (24, 64, 64),
                voxel_size_um=CELL_VOXEL_UM,
                n_cells=12,
                marker_names=("CD11b", "Ferritin"),
                nucleus_radius_um=2.0,
                cell_radius_um=3.5,
                seed=0,
                background=0.1,
                noise_std=0.05,
            )
            for name in ("nuclei", "CD11b"):
                write_tiff(
                    folder / f"{name}.ome.tif",
                    channels[name],
                    axes="ZYX",
                    voxel_size_um=CELL_VOXEL_UM,
                )

        return self._once("cells", make)

    def blob_series(self) -> Path:
        """``series.ome.tif``: 5 Gaussian cells (s.d. 2, 1, 1 um) moving over 3 frames of
        (12, 48, 48) voxels at 2 x 0.5 x 0.5 um."""

        def make(folder: Path) -> None:
            from fgat.io.images import write_tiff  # imported when used: keeps start-up fast

            starts = np.array(
                [[8, 5.2, 5.3], [12.3, 8.1, 17.7], [9.7, 18, 8.1], [14, 17, 18], [6, 12, 12.5]]
            )
            steps = np.array(
                [[0.6, 0.7, 0.35], [-0.8, 0.4, -0.6], [0.5, -0.55, 0.45]] + [[0] * 3] * 2
            )
            axes = [(np.arange(n) + 0.5) * v for n, v in zip((12, 48, 48), TRACK_VOXEL_UM)]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
            volumes = np.zeros((3, 12, 48, 48))
            for frame in range(3):
                for centre in starts + frame * steps:
                    volumes[frame] += np.exp(
                        -0.5 * np.sum(((grid - centre) / np.array([2.0, 1.0, 1.0])) ** 2, -1)
                    )
            volumes += 0.01 * np.random.default_rng(0).standard_normal(volumes.shape)
            write_tiff(
                folder / "series.ome.tif", volumes, axes="TZYX", voxel_size_um=TRACK_VOXEL_UM
            )

        return self._once("blobs", make)

    def checkpoints(self) -> Path:
        """``other.ckpt``: the last checkpoint of a real 2-step static fit with 300 Gaussians,
        copied out of its run folder (as a user keeps one); ``dynamic.ckpt``: a checkpoint file
        of a dynamic run (what the set-up checks read)."""

        def make(folder: Path) -> None:
            import torch  # torch loaded when used: keeps start-up fast

            config = write_yaml(folder / "static300.yaml", static_config(300, str(folder / "run")))
            tracking = folder / "tracking"
            tracking.mkdir()
            done = subprocess.run(
                [sys.executable, "-m", "fgat", "fit", "--config", str(config)],
                cwd=folder,
                env=fgat_env(tracking),
                capture_output=True,
                text=True,
                timeout=600,
            )
            if done.returncode != 0:
                raise RuntimeError(f"the 300-Gaussian fit failed:\n{done.stderr[-3000:]}")
            shutil.copyfile(folder / "run" / "checkpoints" / "last.ckpt", folder / "other.ckpt")
            shutil.rmtree(folder / "run")
            shutil.rmtree(tracking)
            torch.save(
                {
                    "state_dict": {},
                    "pytorch-lightning_version": "2.6.6",
                    "hyper_parameters": {"_class_path": "fgat.modules.DynamicModule"},
                    "reconstruction": {},
                },
                folder / "dynamic.ckpt",
            )

        return self._once("checkpoints", make)


# ----------------------------------------------------------------------------- the set-ups


def deconvolve_inputs(w: Workspace) -> None:
    source = w.deconvolution_inputs()
    for name in ("sensor.tif", "psf.tif", "centers.csv", "dim.tif"):
        w.link(name, source / name)


def deconvolve_truth(w: Workspace) -> None:
    """A simulated acquisition (its `params.yaml` names 64 px views) with a 32 px truth."""
    from fgat.io.images import write_tiff  # imported when used: keeps start-up fast

    deconvolve_inputs(w)
    w.write("params.yaml", "config:\n  view_size: 64\n")  # as `fgat simulate` writes it
    write_tiff(w.folder / "truth32.tif", np.ones((3, 32, 32), np.float32))


def deconvolve_truncated(w: Workspace) -> None:
    deconvolve_inputs(w)
    whole = (w.folder / "sensor.tif").read_bytes()
    w.write("truncated.tif", whole[: len(whole) // 2])


def fit_truth(w: Workspace) -> None:
    """An FLFM fit of the simulation's 64 x 64 views with a truth cropped to 32 x 32."""
    from fgat.io.images import read_tiff, write_tiff  # imported when used: keeps start-up fast

    sim = w.simulation()
    write_tiff(w.folder / "truth32.ome.tif", read_tiff(sim / "truth.ome.tif")[:, :32, :32])
    data = {
        "class_path": "fgat.datamodules.FLFMDataModule",
        "init_args": {
            "measurement": str(sim / "sensor.ome.tif"),
            "centers": str(sim / "centers.csv"),
            "psf": str(sim / "psf.ome.tif"),
            "truth": "truth32.ome.tif",
        },
    }
    w.yaml("flfm.yaml", static_config(100, data=data))


def other_checkpoint(w: Workspace) -> None:
    w.link("other.ckpt", w.checkpoints() / "other.ckpt")
    w.yaml("static500.yaml", static_config(500))


def foreign_checkpoint(w: Workspace) -> None:
    """A Lightning checkpoint of another program (no fgat reconstruction state in it)."""
    import torch  # torch loaded when used: keeps start-up fast

    content = {"state_dict": {}, "pytorch-lightning_version": "2.6.6", "hyper_parameters": {}}
    torch.save(content, w.folder / "foreign.ckpt")
    w.yaml("static.yaml", static_config(100))


def static_fit(w: Workspace) -> None:
    w.yaml("static.yaml", static_config(100))


def dynamic_predict(w: Workspace) -> None:
    w.link("dynamic.ckpt", w.checkpoints() / "dynamic.ckpt")
    w.yaml("dynamic.yaml", dynamic_config(str(w.folder / "no_static_run")))


def pipeline_configs(w: Workspace) -> None:
    w.yaml("dynamic.yaml", dynamic_config("later"))
    w.yaml("static.yaml", {"model": static_config(100)["model"]})


def lenslets(w: Workspace) -> None:
    source = w.lenslet_images()
    for name in ("mla7.tif", "noise.tif", "bright.tif"):
        w.link(name, source / name)


def tubes(w: Workspace) -> None:
    source = w.tube_images()
    for path in source.iterdir():
        w.link(path.name, path)


def cells(w: Workspace) -> None:
    source = w.cells()
    for path in source.iterdir():
        w.link(path.name, path)
    whole = (w.folder / "nuclei.ome.tif").read_bytes()
    w.write("truncated.ome.tif", whole[: len(whole) // 2])


def blobs(w: Workspace) -> None:
    w.link("series.ome.tif", w.blob_series() / "series.ome.tif")


def simulation_config(**changes) -> Callable[[Workspace], None]:
    def setup(w: Workspace) -> None:
        w.yaml("sim.yaml", {**SMALL_SIMULATION, **changes})

    return setup


def text_file(name: str, data: bytes | str) -> Callable[[Workspace], None]:
    def setup(w: Workspace) -> None:
        w.write(name, data)

    return setup


DUPLICATE_SIMULATION = yaml.safe_dump(SMALL_SIMULATION, sort_keys=False) + "photons: 10\n"
BINARY_YAML = b"\xff\xfe\x00system: small\n\x89PNG\r\n\x1a\n"


def crossinfo_config(**scene) -> Callable[[Workspace], None]:
    def setup(w: Workspace) -> None:
        config = yaml.safe_load((w.configs / "crossinfo.yaml").read_text())
        config["scene"] = {**config["scene"], "system": "small", **scene}
        w.yaml("crossinfo.yaml", config)

    return setup


def system_file(**fields) -> Callable[[Workspace], None]:
    def setup(w: Workspace) -> None:
        text = "base: small\nname: hostile\n" + "".join(f"{k}: {v}\n" for k, v in fields.items())
        w.write("system.yaml", text)

    return setup


def port_in_use(w: Workspace) -> dict:
    """A socket listening on a free port while the command runs: ``{port}``."""
    holder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    return {"port": str(holder.getsockname()[1]), "_keep": holder}


def free_port(w: Workspace) -> dict:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    return {"port": str(port)}


def artifacts_file(w: Workspace) -> dict:
    w.write("artifacts", "a file, not a folder\n")
    return free_port(w)


def database_folder(w: Workspace) -> dict:
    (w.folder / "db_folder").mkdir()
    return free_port(w)


# -------------------------------------------------------------------------------- the table


@dataclasses.dataclass(frozen=True)
class Case:
    """One hostile input: ``argv`` (after ``python -m fgat``; ``{name}`` fields are filled from
    what ``setup`` returns, ``{dir}`` is the case's folder), the expectation (``refuse``,
    ``warn`` or ``result``), the ``tokens`` its line must name, and where it comes from."""

    id: str
    argv: tuple[str, ...]
    expect: str
    tokens: tuple[str, ...] = ()
    setup: Callable[[Workspace], dict | None] | None = None
    section: str = ""
    result: tuple[str, float, float] | None = None  # regex (one number), value, rel. tolerance
    forbid: tuple[str, ...] = ()  # words the line must not hold (a wrong diagnosis)
    env: tuple[tuple[str, str], ...] = ()
    isolate: bool = False  # in-process tests run it as a subprocess (servers, hangs, huge sizes)
    note: str = ""

    @property
    def kind(self) -> str:
        """``lightning`` (fit, validate, test, predict, and sweep and pipeline, which resolve
        their configs through LightningCLI) or ``tools``: which start-up it has."""
        lightning = ("fit", "validate", "test", "predict", "sweep", "pipeline")
        return "lightning" if self.argv[0] in lightning else "tools"


SILENT = "silently wrong"
SIZES = "sizes before allocation"
FAULTS = "faults"
MESSAGES = "messages"
CLASS = "class variant"
REFERENCE = "start-up reference"

DECONVOLVE = ("deconvolve", "--measurement", "sensor.tif", "--psf", "psf.tif")
DECONVOLVE += ("--centers", "centers.csv", "--out", "v.ome.tif", "--iterations", "3")
PSF = ("psf", "--system", "small", "--depths-um=-6:6:3", "--out", "p.ome.tif")
FWHM = ("analyze", "fwhm", "--segments", "segments.csv", "--out", "widths")
CYTOMETRY = ("analyze", "cytometry", "--nuclei", "nuclei.ome.tif", "--marker")
CYTOMETRY += ("CD11b=CD11b.ome.tif", "--out", "cyto", "--match-radius-um", "3")
TRACK = ("analyze", "track", "--series", "series.ome.tif", "--frame-interval-s", "0.5")
TRACK += ("--search-range-um", "3", "--minmass", "1", "--out", "tracks")
CALIBRATE = ("calibrate", "--out", "cal")
SWEEP = ("sweep", "--config", "static.yaml", "--parallel", "1")
PIPELINE = ("pipeline", "--config", "dynamic.yaml", "--static", "static.yaml")
SERVER = ("tracking-server", "--host", "127.0.0.1")


def numeric(prefix: str, argv: tuple[str, ...], option: str, values, setup=None, **kw):
    """Refusals of ``option`` set to each of ``values`` (``(name, text)``) after ``argv``; the
    line must name ``token`` (default the option)."""
    return [
        Case(
            f"{prefix}_{option.strip('-').replace('-', '_').replace('.', '_')}_{name}",
            (*argv, f"{option}={value}"),
            "refuse",
            (kw.get("token", option),),
            setup,
            kw.get("section", CLASS),
            isolate=kw.get("isolate", False),
        )
        for name, value in values
    ]


NAN_INF_NEG = (("nan", "nan"), ("inf", "inf"), ("negative", "-1"))
NAN_INF_NEG_ZERO = (*NAN_INF_NEG, ("zero", "0"))

CASES: list[Case] = [
    # start-up references: a trivial refusal by each kind of command (imports, no work)
    Case(
        "reference_tools",
        (*DECONVOLVE[:2], "missing.tif", *DECONVOLVE[3:]),
        "refuse",
        ("missing.tif",),
        deconvolve_inputs,
        REFERENCE,
    ),
    Case(
        "reference_lightning",
        ("fit", "--config", "static.yaml", "--model.init_args.n_gaussiansx=3"),
        "refuse",
        ("n_gaussiansx",),
        static_fit,
        REFERENCE,
    ),
    # ---------------------------------------------------------------- silently wrong
    Case(
        "calibrate_noise_system",
        (*CALIBRATE, "--image", "noise.tif", "--system", "small"),
        "refuse",
        ("noise.tif",),
        lenslets,
        SILENT,
        note="lattice fitted to pure noise, exit 0",
    ),
    Case(
        "calibrate_noise_n_lenslets",
        (*CALIBRATE, "--image", "noise.tif", "--n-lenslets", "7"),
        "refuse",
        ("noise.tif",),
        lenslets,
        SILENT,
        note="7 lenslets: pitch 82.64 px on noise, exit 0",
    ),
    Case(
        "calibrate_small37_on_7_lenses",
        (*CALIBRATE, "--image", "mla7.tif", "--system", "small37"),
        "refuse",
        ("mla7.tif",),
        lenslets,
        SILENT,
        note="views not found, gains 0.000, exit 0",
    ),
    Case(
        "calibrate_dark_is_bright",
        (*CALIBRATE, "--image", "mla7.tif", "--n-lenslets", "7", "--dark", "bright.tif"),
        "warn",
        ("--dark",),
        lenslets,
        SILENT,
        note="thousands of hot pixels without a warning",
    ),
    Case(
        "fwhm_volume_in_nm",
        ("analyze", "fwhm", "--image", "tube_nm.ome.tif", *FWHM[2:]),
        "result",
        setup=tubes,
        section=SILENT,
        result=(r"width median ([-+0-9.eE]+) um", TUBE_FWHM_UM, 0.05),
        note="PhysicalSizeUnit nm ignored: 1000x off",
    ),
    Case(
        "fwhm_image_in_mm",
        ("analyze", "fwhm", "--image", "tube_mm.ome.tif", *FWHM[2:]),
        "result",
        setup=tubes,
        section=CLASS,
        result=(r"width median ([-+0-9.eE]+) um", TUBE_FWHM_UM, 0.05),
    ),
    Case(
        "fwhm_unknown_unit",
        ("analyze", "fwhm", "--image", "tube_furlong.ome.tif", *FWHM[2:]),
        "refuse",
        ("tube_furlong.ome.tif", "furlong"),
        tubes,
        CLASS,
    ),
    Case(
        "fwhm_plane_negative",
        ("analyze", "fwhm", "--image", "tube_um.ome.tif", *FWHM[2:], "--plane=-1"),
        "refuse",
        ("--plane",),
        tubes,
        SILENT,
        note="silently the last plane",
    ),
    Case(
        "track_diameter_tiny",
        (*TRACK, "--diameter-um", "0.001"),
        "refuse",
        ("--diameter-um",),
        blobs,
        SILENT,
        note="14 cells where 5 exist",
    ),
    Case(
        "track_diameter_huge",
        (*TRACK, "--diameter-um", "1e6"),
        "refuse",
        ("--diameter-um",),
        blobs,
        SILENT,
        isolate=True,
        note="40 s, then no objects",
    ),
    Case(
        "cytometry_sigma_1500",
        (*CYTOMETRY, "--sigma-um", "1500"),
        "refuse",
        ("--sigma-um",),
        cells,
        SILENT,
        isolate=True,
        note="1 cell",
    ),
    Case(
        "cytometry_sigma_1e6",
        (*CYTOMETRY, "--sigma-um", "1e6"),
        "refuse",
        ("--sigma-um",),
        cells,
        SILENT,
        isolate=True,
        note="past 120 s",
    ),
    Case(
        "deconvolve_truth_other_size",
        (*DECONVOLVE, "--truth", "truth32.tif"),
        "refuse",
        ("truth32.tif",),
        deconvolve_truth,
        SILENT,
        note="reconstruction shrunk to the truth's 32 px and scored",
    ),
    Case(
        "fit_truth_other_size",
        ("fit", "--config", "flfm.yaml"),
        "refuse",
        ("data.truth",),
        fit_truth,
        SILENT,
        note="the fit takes the truth's 32 px instead of the data's 64",
    ),
    Case(
        "fit_ckpt_other_configuration",
        ("fit", "--config", "static500.yaml", "--ckpt_path", "other.ckpt"),
        "refuse",
        ("--ckpt_path",),
        other_checkpoint,
        SILENT,
        note="300-Gaussian checkpoint restored into a 500-Gaussian run",
    ),
    Case(
        "validate_ckpt_of_another_program",
        ("validate", "--config", "static.yaml", "--ckpt_path", "foreign.ckpt"),
        "refuse",
        ("--ckpt_path", "foreign.ckpt"),
        foreign_checkpoint,
        SILENT,
        note="KeyError traceback while the checkpoint is restored",
    ),
    Case(
        "test_ckpt_of_another_program",
        ("test", "--config", "static.yaml", "--ckpt_path", "foreign.ckpt"),
        "refuse",
        ("--ckpt_path", "foreign.ckpt"),
        foreign_checkpoint,
        SILENT,
    ),
    Case(
        "fit_tracking_store_is_a_user_file",
        ("fit", "--config", "static.yaml"),
        "refuse",
        ("garbage.tif",),
        lambda w: (static_fit(w), w.write("garbage.tif", b"user data")) and None,
        MESSAGES,
        env=(("MLFLOW_TRACKING_URI", "sqlite:///{dir}/garbage.tif"),),
        note="garbage.tif.lock left beside the user's file",
    ),
    Case(
        "fit_refused_leaves_no_database",
        ("fit", "--config", "flfm.yaml"),
        "refuse",
        ("data.truth",),
        fit_truth,
        MESSAGES,
        env=(("MLFLOW_TRACKING_URI", "sqlite:///{dir}/mlflow.db"),),
        note="a 0-byte mlflow.db left by a refused run",
    ),
    Case(
        "simulate_duplicate_yaml_key",
        ("simulate", "--config", "sim.yaml", "--out", "sim"),
        "refuse",
        ("sim.yaml", "photons"),
        text_file("sim.yaml", DUPLICATE_SIMULATION),
        SILENT,
        note="the last value wins silently",
    ),
    Case(
        "fit_duplicate_yaml_key",
        ("fit", "--config", "dup.yaml"),
        "refuse",
        ("dup.yaml", "seed_everything"),
        text_file("dup.yaml", yaml.safe_dump(static_config(100)) + "seed_everything: 3\n"),
        CLASS,
    ),
    Case(
        "psf_system_duplicate_yaml_key",
        ("psf", "--system", "system.yaml", "--depths-um=0", "--out", "p.ome.tif"),
        "refuse",
        ("system.yaml", "n_lenslets"),
        system_file(n_lenslets="7\nn_lenslets: 19"),
        CLASS,
    ),
    Case(
        "design_na_above_immersion",
        ("design", "--objective", "999x/9"),
        "refuse",
        ("999x/9",),
        section=SILENT,
        note="a design with NA 9",
    ),
    Case(
        "pipeline_address_ignored",
        (*PIPELINE, "--address", "ray://127.0.0.1:9"),
        "refuse",
        ("Ray cluster",),  # honoured: a cluster's trials need an HTTP tracking server
        pipeline_configs,
        SILENT,
        isolate=True,
        note="--address ignored",
    ),
    Case(
        "sweep_cpus_per_trial_nan",
        (*SWEEP, "--grid", "seed=0,1", "--cpus-per-trial", "nan"),
        "refuse",
        ("--cpus-per-trial",),
        static_fit,
        SILENT,
        note="accepted",
    ),
    # ------------------------------------------------------- sizes checked before allocation
    Case(
        "psf_40000_depths",
        ("psf", "--objective", "20x/0.45", "--depths-um=-100:100:40000", "--out", "p.ome.tif"),
        "refuse",
        ("--depths-um",),
        section=SIZES,
        isolate=True,
        note="the issue's 4000 planes need 18.7 GB: refused only where that is not available",
    ),
    Case(
        "psf_system_n_lenslets_1e8",
        ("psf", "--system", "system.yaml", "--depths-um=0", "--out", "p.ome.tif"),
        "refuse",
        ("n_lenslets",),
        system_file(n_lenslets="1e8"),
        SIZES,
        isolate=True,
        note="32 s",
    ),
    Case(
        "psf_system_n_lenslets_100000000",
        ("psf", "--system", "system.yaml", "--depths-um=0", "--out", "p.ome.tif"),
        "refuse",
        ("n_lenslets",),
        system_file(n_lenslets="100000000"),
        CLASS,
        isolate=True,
    ),
    Case(
        "calibrate_n_lenslets_1e6",
        (*CALIBRATE, "--image", "mla7.tif", "--n-lenslets", "1e6"),
        "refuse",
        ("--n-lenslets",),
        lenslets,
        SIZES,
        isolate=True,
        note="51 GiB ArrayMemoryError",
    ),
    Case(
        "crossinfo_view_size_20000",
        ("analyze", "crossinfo", "--config", "crossinfo.yaml", "--out", "ci"),
        "refuse",
        ("view_size",),
        crossinfo_config(view_size=20000),
        SIZES,
        isolate=True,
        note="46 GiB",
    ),
    Case(
        "crossinfo_empty_config",
        ("analyze", "crossinfo", "--config", "empty.yaml", "--out", "ci"),
        "refuse",
        ("empty.yaml",),
        text_file("empty.yaml", ""),
        SIZES,
        isolate=True,
        note="runs the whole default analysis",
    ),
    Case(
        "predict_times_1e8",
        (
            "predict",
            "--config",
            "dynamic.yaml",
            "--ckpt_path",
            "dynamic.ckpt",
            "--times",
            "0:1:100000000",
        ),
        "refuse",
        ("--times",),
        dynamic_predict,
        SIZES,
        isolate=True,
        note="std::bad_alloc, then the process never exited",
    ),
    Case(
        "sweep_grid_1e8_points",
        (*SWEEP, "--grid", "seed=0:100000000"),
        "refuse",
        ("--grid",),
        static_fit,
        SIZES,
        isolate=True,
        note="MemoryError after 45 s",
    ),
    Case(
        "deconvolve_iterations_1e9",
        (*DECONVOLVE[:-2], "--iterations", "1e9"),
        "refuse",
        ("--iterations",),
        deconvolve_inputs,
        SIZES,
        isolate=True,
        note="no cap, ETA 55,000 h",
    ),
    # ---------------------------------------------------------------------------- faults
    Case(
        "tracking_server_port_in_use",
        (*SERVER, "--port", "{port}", "--backend-store-uri", "sqlite:///{dir}/db.sqlite"),
        "refuse",
        ("{port}",),
        port_in_use,
        FAULTS,
        isolate=True,
        note="exit 0 when it cannot bind",
    ),
    Case(
        "tracking_server_host_not_local",
        ("tracking-server", "--host", "192.0.2.1", "--port", "{port}"),
        "refuse",
        ("192.0.2.1",),
        free_port,
        FAULTS,
        isolate=True,
        note="exit 0 when it cannot bind its host",
    ),
    Case(
        "tracking_server_artifacts_is_a_file",
        (*SERVER, "--port", "{port}", "--artifacts-destination", "artifacts"),
        "refuse",
        ("--artifacts-destination",),
        artifacts_file,
        FAULTS,
        isolate=True,
        note="starts anyway",
    ),
    Case(
        "tracking_server_database_is_a_folder",
        (*SERVER, "--port", "{port}", "--backend-store-uri", "sqlite:///{dir}/db_folder"),
        "refuse",
        ("--backend-store-uri",),
        database_folder,
        FAULTS,
        isolate=True,
        note="retried every 25.5 s forever",
    ),
    Case(
        "sweep_unreachable_tracking",
        (*SWEEP, "--grid", "seed=0,1"),
        "refuse",
        ("127.0.0.1:9",),
        static_fit,
        FAULTS,
        env=(("MLFLOW_TRACKING_URI", UNREACHABLE),),
        isolate=True,
        note="254 s and 113 lines",
    ),
    Case(
        "pipeline_unreachable_tracking",
        PIPELINE,
        "refuse",
        ("127.0.0.1:9",),
        pipeline_configs,
        CLASS,
        env=(("MLFLOW_TRACKING_URI", UNREACHABLE),),
    ),
    Case(
        "fit_unreachable_tracking",
        ("fit", "--config", "static.yaml"),
        "refuse",
        ("127.0.0.1:9",),
        static_fit,
        CLASS,
        env=(("MLFLOW_TRACKING_URI", UNREACHABLE),),
    ),
    # ----------------------------------------------------------------------- messages
    Case(
        "simulate_non_utf8_yaml",
        ("simulate", "--config", "binary.yaml", "--out", "sim"),
        "refuse",
        ("binary.yaml",),
        text_file("binary.yaml", BINARY_YAML),
        MESSAGES,
        note="'utf-8' codec can't decode byte 0xff",
    ),
    Case(
        "fit_non_utf8_yaml",
        ("fit", "--config", "binary.yaml"),
        "refuse",
        ("binary.yaml",),
        text_file("binary.yaml", BINARY_YAML),
        CLASS,
    ),
    Case(
        "pipeline_non_utf8_yaml",
        ("pipeline", "--config", "binary.yaml", "--static", "static.yaml"),
        "refuse",
        ("binary.yaml",),
        lambda w: (pipeline_configs(w), w.write("binary.yaml", BINARY_YAML)) and None,
        CLASS,
    ),
    Case(
        "crossinfo_non_utf8_yaml",
        ("analyze", "crossinfo", "--config", "binary.yaml", "--out", "ci"),
        "refuse",
        ("binary.yaml",),
        text_file("binary.yaml", BINARY_YAML),
        CLASS,
    ),
    Case(
        "psf_system_non_utf8_yaml",
        ("psf", "--system", "binary.yaml", "--depths-um=0", "--out", "p.ome.tif"),
        "refuse",
        ("binary.yaml",),
        text_file("binary.yaml", BINARY_YAML),
        CLASS,
    ),
    Case(
        "simulate_margin_of_two_axes",
        ("simulate", "--config", "sim.yaml", "--out", "sim"),
        "refuse",
        ("sim.yaml", "margin"),
        simulation_config(phantom={**SMALL_SIMULATION["phantom"], "margin": [1, 2]}),
        MESSAGES,
        note="all input arrays must have the same shape",
    ),
    Case(
        "fwhm_non_numeric_segment",
        ("analyze", "fwhm", "--image", "tube_um.ome.tif", *FWHM[2:3], "segments_text.csv")
        + FWHM[4:],
        "refuse",
        ("segments_text.csv", "center_x"),
        tubes,
        MESSAGES,
        note="could not convert string to float: 'a'",
    ),
    Case(
        "fwhm_nan_segment",
        ("analyze", "fwhm", "--image", "tube_um.ome.tif", *FWHM[2:3], "segments_nan.csv")
        + FWHM[4:],
        "refuse",
        ("segments_nan.csv", "half_length_px"),
        tubes,
        CLASS,
    ),
    Case(
        "pipeline_channels_not_integers",
        (*PIPELINE, "--channels", "a,b"),
        "refuse",
        ("--channels",),
        pipeline_configs,
        MESSAGES,
        note="invalid literal for int()",
    ),
    Case(
        "pipeline_parallel_not_a_number",
        (*PIPELINE, "--parallel", "many"),
        "refuse",
        ("--parallel",),
        pipeline_configs,
        CLASS,
    ),
    Case(
        "deconvolve_truncated_tiff",
        (*DECONVOLVE[:2], "truncated.tif", *DECONVOLVE[3:]),
        "refuse",
        ("truncated.tif",),
        deconvolve_truncated,
        MESSAGES,
        forbid=("got 2D", "got 3D", "voxel size"),
    ),
    Case(
        "fwhm_truncated_tiff",
        ("analyze", "fwhm", "--image", "truncated.ome.tif", *FWHM[2:]),
        "refuse",
        ("truncated.ome.tif",),
        tubes,
        MESSAGES,
        forbid=("voxel size", "2-D", "2D"),
        note="reported as no voxel size / 2D data",
    ),
    Case(
        "cytometry_truncated_tiff",
        (
            "analyze",
            "cytometry",
            "--nuclei",
            "truncated.ome.tif",
            *CYTOMETRY[4:],
            "--sigma-um",
            "1.5",
        ),
        "refuse",
        ("truncated.ome.tif",),
        cells,
        CLASS,
        forbid=("voxel size", "2-D", "2D"),
    ),
    Case(
        "deconvolve_background_named",
        (*DECONVOLVE[:2], "dim.tif", *DECONVOLVE[3:], "--background", "100"),
        "refuse",
        ("--background", "100"),
        deconvolve_inputs,
        MESSAGES,
        forbid=("(0.0)",),
        note="says background (0.0) when 100 was given",
    ),
    Case(
        "simulate_sequence_counts_views",
        ("simulate", "--config", "sim.yaml", "--out", "sim"),
        "result",
        setup=simulation_config(
            view_size=32,
            frames=3,
            phantom={"kind": "moving_beads", "n_beads": 3, "sigma": 1.0, "margin": [1, 8, 8]},
        ),
        section=MESSAGES,
        result=(r"(\d+) views", 7, 0.0),
        note="prints 6 views (frames) for a 7-view system",
    ),
    # --------------------------------------------------- the classes: numeric size options
    *numeric("deconvolve", DECONVOLVE, "--view-size", NAN_INF_NEG, deconvolve_inputs),
    *numeric(
        "deconvolve",
        DECONVOLVE,
        "--iterations",
        (("nan", "nan"), ("inf", "inf")),
        deconvolve_inputs,
    ),
    *numeric("deconvolve", DECONVOLVE, "--background", (("inf", "inf"),), deconvolve_inputs),
    *numeric("psf", PSF, "--crop-radius", NAN_INF_NEG),
    *numeric(
        "calibrate", (*CALIBRATE, "--image", "mla7.tif"), "--n-lenslets", NAN_INF_NEG_ZERO, lenslets
    ),
    *numeric(
        "calibrate",
        (*CALIBRATE, "--image", "mla7.tif", "--n-lenslets", "7"),
        "--pitch-px",
        NAN_INF_NEG,
        lenslets,
    ),
    *numeric(
        "calibrate_depth",
        ("calibrate-depth", "--stack", "s.tif", "--system", "small", "--calibration", "cal"),
        "--positions-um",
        (("nan", "nan"), ("inf", "0,inf")),
    ),
    *numeric(
        "fwhm",
        ("analyze", "fwhm", "--image", "tube_um.ome.tif", *FWHM[2:]),
        "--plane",
        (("nan", "nan"), ("beyond", "3")),
        tubes,
    ),
    *numeric(
        "fwhm",
        ("analyze", "fwhm", "--image", "tube_um.ome.tif", *FWHM[2:]),
        "--width-px",
        NAN_INF_NEG_ZERO,
        tubes,
    ),
    *numeric("cytometry", CYTOMETRY, "--sigma-um", (*NAN_INF_NEG_ZERO, ("tiny", "0.001")), cells),
    *numeric(
        "cytometry", (*CYTOMETRY[:-2], "--sigma-um", "1.5"), "--match-radius-um", NAN_INF_NEG, cells
    ),
    *numeric(
        "track",
        (*TRACK[:-2], "--diameter-um", "7", "--out", "tracks"),
        "--window",
        (("zero", "0"), ("negative", "-2")),
        blobs,
    ),
    *numeric("track", TRACK, "--diameter-um", NAN_INF_NEG_ZERO, blobs),
    *numeric(
        "track",
        (*TRACK[:4], "--diameter-um", "7", "--out", "tracks"),
        "--frame-interval-s",
        NAN_INF_NEG_ZERO,
        blobs,
    ),
    *numeric(
        "sweep",
        (*SWEEP, "--grid", "seed=0,1"),
        "--cpus-per-trial",
        (("inf", "inf"), ("negative", "-1"), ("zero", "0")),
        static_fit,
    ),
    *numeric(
        "sweep",
        (*SWEEP, "--grid", "seed=0,1"),
        "--gpus-per-trial",
        NAN_INF_NEG,
        static_fit,
    ),
    *numeric("pipeline", PIPELINE, "--cpus-per-trial", NAN_INF_NEG, pipeline_configs),
    *numeric(
        "server",
        SERVER,
        "--port",
        (("negative", "-1"), ("huge", "70000"), ("nan", "nan")),
        free_port,
        isolate=True,
    ),
    *numeric(
        "server",
        (*SERVER, "--port", "{port}"),
        "--workers",
        (("zero", "0"), ("nan", "nan")),
        free_port,
        isolate=True,
    ),
    *numeric(
        "predict",
        ("predict", "--config", "dynamic.yaml", "--ckpt_path", "dynamic.ckpt"),
        "--times",
        (("nan", "nan"), ("inf", "0,inf")),
        dynamic_predict,
    ),
    *numeric(
        "fit",
        ("fit", "--config", "static.yaml"),
        "--model.init_args.n_gaussians",
        (("negative", "-1"), ("zero", "0")),
        static_fit,
        token="n_gaussians",
    ),
    *numeric(
        "fit",
        ("fit", "--config", "static.yaml"),
        "--model.init_args.n_gaussians",
        (("huge", "1000000000000"),),
        static_fit,
        token="n_gaussians",
        isolate=True,
    ),
    *[
        Case(
            f"simulate_{field}_{name}",
            ("simulate", "--config", "sim.yaml", "--out", "sim"),
            "refuse",
            ("sim.yaml", field),
            simulation_config(**{field: value}),
            CLASS,
        )
        for field, name, value in (
            ("view_size", "nan", float("nan")),
            ("view_size", "negative", -64),
            ("photons", "negative", -5.0),
            ("frames", "zero", 0),
        )
    ],
]
CASE_IDS = [case.id for case in CASES]
assert len(set(CASE_IDS)) == len(CASE_IDS), "case ids must be unique"


# ------------------------------------------------------------------------------ the judge


@dataclasses.dataclass
class Outcome:
    """What one run of a case gave: ``exit`` (``None`` after a timeout), wall time (s), the
    output, and the files it left in the case's folder that its set-up did not put there."""

    exit: int | None
    wall_s: float
    stdout: str
    stderr: str
    litter: list[str]

    @property
    def line(self) -> str:
        """The last non-empty line of stderr (stdout when stderr has none)."""
        for text in (self.stderr, self.stdout):
            lines = [line.strip() for line in text.splitlines() if line.strip()]
            if lines:
                return lines[-1]
        return ""


ERROR_LINE = re.compile(r"(: error: |^\w*(Error|Exception)\b|^ERROR\b|^E\d+ |^error: )")


def error_lines(stderr: str) -> list[str]:
    """The lines of ``stderr`` that report an error (fgat's and argparse's ``prog: error:``
    lines, exception lines)."""
    return [line for line in stderr.splitlines() if ERROR_LINE.search(line.strip())]


def fill(text: str, values: dict) -> str:
    return text.format(**values) if "{" in text else text


def judge(
    case: Case, outcome: Outcome, values: dict, compute_s: float | None, bound_s: float
) -> list[str]:
    """Why ``outcome`` misses the case's expectation (empty when it holds). ``compute_s``: the
    time spent beyond the command's start-up (``None``: unknown, use the wall time against
    ``bound_s``)."""
    tokens = [fill(token, values) for token in case.tokens]
    failures = []
    if outcome.exit is None:
        return [f"timeout after {outcome.wall_s:.0f} s"]
    if "Traceback" in outcome.stderr or "Traceback" in outcome.stdout:
        failures.append("traceback")
    refused = outcome.exit != 0
    if case.expect == "warn" and outcome.exit == 0:
        warnings = [
            line
            for line in outcome.stderr.splitlines()
            if "warning" in line.lower() and all(token in line for token in tokens)
        ]
        if not warnings:
            failures.append(f"exit 0 without a warning naming {tokens}")
        return failures
    if case.expect == "result":
        if refused:
            return failures + [f"exit {outcome.exit}: {outcome.line}"]
        pattern, value, tolerance = case.result
        found = re.search(pattern, outcome.stdout + outcome.stderr)
        if found is None:
            return failures + [f"no {pattern!r} in the output"]
        got = float(found.group(1))
        if not abs(got - value) <= tolerance * abs(value):
            failures.append(f"printed {got:g}, expected {value:g} (within {tolerance:.0%})")
        return failures
    if not refused:
        return failures + ["exit 0: not refused"]
    if outcome.exit < 0 or outcome.exit > 128:
        failures.append(f"killed (exit {outcome.exit})")
    errors = error_lines(outcome.stderr)
    if len(errors) != 1:
        failures.append(f"{len(errors)} error lines")
    line = outcome.line
    missing = [token for token in tokens if token not in line]
    if missing:
        failures.append(f"the line does not name {missing}")
    wrong = [word for word in case.forbid if word in line]
    if wrong:
        failures.append(f"the line says {wrong}")
    spent = outcome.wall_s if compute_s is None else compute_s
    limit = bound_s if compute_s is None else COMPUTE_BOUND_S
    if spent > limit:
        failures.append(f"{spent:.1f} s before refusing (bound {limit:g} s)")
    if outcome.litter:
        failures.append(f"left {outcome.litter[:3]}")
    return failures


# ------------------------------------------------------------------------------ the runner


def listing(folder: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``folder`` with its size and modification time (0, 0 for a folder)."""
    return {
        str(path.relative_to(folder)): (0, 0)
        if path.is_dir()
        else (path.stat().st_size, path.stat().st_mtime_ns)
        for path in folder.rglob("*")
    }


def empty_store(path: Path) -> bool:
    """Whether ``path`` is an MLflow SQLite store that holds no active run: the tracking database
    a command was given, initialised by its up-front check (a 0-byte file is litter)."""
    if not path.is_file() or path.read_bytes()[:16] != b"SQLite format 3\x00":
        return False
    with contextlib.closing(sqlite3.connect(path)) as connection:
        try:
            query = "SELECT COUNT(*) FROM runs WHERE lifecycle_stage = 'active'"
            return not connection.execute(query).fetchone()[0]
        except sqlite3.Error:
            return False


def left_behind(folder: Path, made: dict[str, tuple[int, int]]) -> list[str]:
    """What a command left in ``folder`` beyond what its set-up ``made``: new paths, and
    ``changed <name>`` for a set-up file it modified."""
    now = listing(folder)
    new = sorted(name for name in set(now) - set(made) if not empty_store(folder / name))
    changed = sorted(f"changed {name}" for name in set(now) & set(made) if now[name] != made[name])
    return new + changed


def prepare(case: Case, folder: Path, shared: Path, configs: Path) -> tuple[dict, dict]:
    """Run the case's set-up in ``folder`` (:class:`Workspace` of ``folder``, ``shared`` and
    ``configs``): the values for its argv (``{dir}`` and what the set-up returned, ``_keep``
    held while the command runs) and the files it made."""
    folder.mkdir(parents=True, exist_ok=True)
    values = {"dir": str(folder)}
    if case.setup is not None:
        values.update(case.setup(Workspace(folder, shared, configs)) or {})
    return values, listing(folder)


def argv_of(case: Case, values: dict) -> list[str]:
    return [fill(word, values) for word in case.argv]


def run_subprocess(
    case: Case, folder: Path, shared: Path, configs: Path, tracking: Path, timeout: float
) -> tuple[Outcome, dict]:
    """``python -m fgat`` on the case in ``folder`` (set up by :func:`prepare`); the process
    group is killed at ``timeout``."""
    values, made = prepare(case, folder, shared, configs)
    env = {**fgat_env(tracking), **{name: fill(value, values) for name, value in case.env}}
    start = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, "-m", "fgat", *argv_of(case, values)],
        cwd=folder,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        errors="replace",
        start_new_session=True,
    )
    try:
        stdout, stderr = process.communicate(timeout=timeout)
        code = process.returncode
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        stdout, stderr = process.communicate()
        code = None
    wall = time.perf_counter() - start
    keep = values.pop("_keep", None)
    if keep is not None:
        keep.close()
    return Outcome(code, wall, stdout, stderr, left_behind(folder, made)), values


def record(case: Case, outcome: Outcome, failures: list[str], compute_s: float | None) -> dict:
    return {
        "id": case.id,
        "section": case.section,
        "command": "fgat " + " ".join(case.argv),
        "expect": case.expect,
        "tokens": list(case.tokens),
        "exit": "timeout" if outcome.exit is None else outcome.exit,
        "wall_s": round(outcome.wall_s, 2),
        "compute_s": None if compute_s is None else round(compute_s, 2),
        "line": outcome.line[:300],
        "traceback": "Traceback" in outcome.stderr,
        "litter": outcome.litter[:10],
        "ok": not failures,
        "failures": failures,
        "note": case.note,
    }


def run_cases(
    cases: list[Case], timeout: float, configs: Path, keep: Path | None = None
) -> list[dict]:
    """Run ``cases`` (the start-up references first) with the repository's ``configs`` folder
    and judge each."""
    references = [c for c in CASES if c.section == REFERENCE and c not in cases]
    rows, startup = [], {}
    with tempfile.TemporaryDirectory(prefix="fgat-hostile-") as scratch:
        scratch = Path(scratch) if keep is None else keep
        shared, tracking = scratch / "shared", scratch / "tracking"
        shared.mkdir(parents=True, exist_ok=True)
        tracking.mkdir(parents=True, exist_ok=True)
        for case in [*references, *cases]:
            folder = scratch / "cases" / case.id
            times = []
            for _ in range(REFERENCE_REPEATS if case.section == REFERENCE else 1):
                shutil.rmtree(folder, ignore_errors=True)
                try:
                    outcome, values = run_subprocess(
                        case, folder, shared, configs, tracking, timeout
                    )
                except Exception as error:  # a set-up that failed: recorded, the run goes on
                    outcome, values = Outcome(-1, 0.0, "", f"set-up failed: {error!r}", []), {}
                times.append(outcome.wall_s)
            if case.section == REFERENCE:
                startup[case.kind] = outcome.wall_s = float(np.median(times))
            compute = outcome.wall_s - startup.get(case.kind, 0.0)
            failures = judge(case, outcome, values, compute, timeout)
            row = record(case, outcome, failures, compute)
            if case in cases:
                rows.append(row)
            print(
                f"{case.id:45s} {'ok  ' if row['ok'] else 'FAIL'} exit {row['exit']!s:>7} "
                f"{row['wall_s']:6.1f} s  {row['line'][:90]}",
                flush=True,
            )
    return rows


# -------------------------------------------------------------------------------- tables


def _cell(row: dict | None) -> str:
    if row is None:
        return "-"
    line = row["line"].replace("|", "\\|").replace("`", "'")
    if len(line) > 110:
        line = line[:107] + "..."
    return (
        f"{row['exit']}, {row['wall_s']:.1f} s, `{line}`"
        if line
        else f"{row['exit']}, {row['wall_s']:.1f} s"
    )


def table(rows: list[dict]) -> str:
    lines = ["| case | exit, time, line | ok |", "| --- | --- | --- |"]
    for row in rows:
        ok = "yes" if row["ok"] else "no: " + "; ".join(row["failures"])
        lines.append(f"| {row['id']} | {_cell(row)} | {ok} |")
    return "\n".join(lines)


def comparison(before: list[dict], after: list[dict]) -> str:
    """case | before (exit, time, line) | after (exit, time, line) | ok (after)."""
    previous = {row["id"]: row for row in before}
    lines = [
        "| case | before: exit, time, line | after: exit, time, line | ok |",
        "| --- | --- | --- | --- |",
    ]
    for row in after:
        ok = "yes" if row["ok"] else "no: " + "; ".join(row["failures"])
        lines.append(f"| {row['id']} | {_cell(previous.get(row['id']))} | {_cell(row)} | {ok} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> dict:
    """Counts over the cases (the start-up references left out)."""
    rows = [row for row in rows if row["section"] != REFERENCE]
    failed = [row for row in rows if not row["ok"]]
    return {
        "cases": len(rows),
        "ok": len(rows) - len(failed),
        "failed": len(failed),
        "timeouts": sum(row["exit"] == "timeout" for row in rows),
        "tracebacks": sum(row["traceback"] for row in rows),
        "exit_0_not_refused": sum("exit 0: not refused" in row["failures"] for row in rows),
    }


def main(configs: Path, argv: list[str] | None = None) -> None:
    """The command line (module docstring).

    Parameters
    ----------
    configs : Path
        The repository's ``configs`` folder (the shipped configs some cases start from).
    argv : list of str, optional
        The arguments (default: the command line's).
    """
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--only", nargs="+", metavar="ID", help="run only these cases")
    parser.add_argument("--out", default="benchmarks/results/hostile.json")
    parser.add_argument("--timeout", type=float, default=TIMEOUT_S, help="per case, seconds")
    parser.add_argument(
        "--compare", metavar="BEFORE.json", help="print before | after for each case"
    )
    parser.add_argument(
        "--table", metavar="RESULTS.json", help="print the table of a results file; run nothing"
    )
    parser.add_argument("--keep", metavar="FOLDER", help="run the cases in FOLDER and keep it")
    words = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(words)
    if args.table is not None:
        rows = json.loads(Path(args.table).read_text())["cases"]
    else:
        unknown = sorted(set(args.only or ()) - set(CASE_IDS))
        if unknown:
            parser.error(f"--only: unknown case(s) {unknown}")
        cases = [c for c in CASES if args.only is None or c.id in args.only]
        keep = None if args.keep is None else Path(args.keep).absolute()
        rows = run_cases(cases, args.timeout, configs, keep)
        if "--keep" in words:  # where the cases ran changes nothing in their results
            at = words.index("--keep")
            words = words[:at] + words[at + 2 :]
        command = " ".join(["python benchmarks/hostile.py", *words])
        from fgat.app.recipes.benchmark import (  # imported when used: keeps start-up fast
            provenance,
            write_json,
        )

        write_json(
            args.out,
            {
                **provenance(command, load_average=list(os.getloadavg())),
                "timeout_s": args.timeout,
                "compute_bound_s": COMPUTE_BOUND_S,
                "summary": summary(rows),
                "cases": rows,
            },
        )
    if args.compare is not None:
        print(comparison(json.loads(Path(args.compare).read_text())["cases"], rows))
    else:
        print(table(rows))
    print(json.dumps(summary(rows)))
