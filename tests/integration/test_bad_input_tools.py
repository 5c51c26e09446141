"""Bad input to ``fgat psf``, ``simulate``, ``deconvolve`` and ``design``: one clear line, exit
code 2, before any computation; nothing the user made is lost."""

import errno
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import namedtuple

import numpy as np
import pytest
import scipy.io
import tifffile
import torch
import yaml

from fgat._core import resources
from fgat.app.cli import main
from fgat.instrument.centres import read_centers
from fgat.io.images import read_tiff, write_tiff
from fgat.optics.operator import FLFMOperator, operator_memory
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system
from fgat.recon import costs
from fgat.sim.simulation import OUTPUT_FILES

CENTERS = load_system("small").lenslet_centers_px()  # 7 views on a 256 x 256 sensor
SIMULATION = {
    "system": "small",
    "depths_um": "-6:6:3",
    "view_size": 32,
    "phantom": {"kind": "beads", "n_beads": 4, "sigma": 1.0},
    "photons": 1000,
    "background": 100,
    "seed": 0,
}


def centers_csv(rows, header="row,col"):
    return header + "\n" + "".join(f"{a},{b}\n" for a, b in rows)


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    """Tiny inputs: a sensor image, a PSF stack (7, 3, 9, 9), centres, a truth, configs."""
    folder = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(0)
    write_tiff(folder / "sensor.tif", rng.uniform(90, 200, (256, 256)).astype(np.float32))
    write_tiff(folder / "psf.tif", rng.uniform(0, 1, (7, 3, 9, 9)).astype(np.float32), axes="CZYX")
    write_tiff(folder / "truth.tif", np.ones((3, 32, 32), np.float32))
    write_tiff(folder / "truth_z4.tif", np.ones((4, 32, 32), np.float32))
    write_tiff(folder / "sensor3d.tif", np.ones((2, 256, 256), np.float32))
    write_tiff(folder / "psf3d.tif", np.ones((7, 9, 9), np.float32))
    (folder / "centers.csv").write_text(centers_csv(CENTERS))
    duplicate = CENTERS.copy()
    duplicate[3] = duplicate[2]
    (folder / "duplicate.csv").write_text(centers_csv(duplicate))
    scipy.io.savemat(folder / "duplicate.mat", {"centers": duplicate + 1})
    (folder / "uv.csv").write_text(centers_csv(CENTERS, "u,v"))
    (folder / "header_only.csv").write_text("row,col\n")
    off = CENTERS.copy()
    off[1, 0] += 500
    (folder / "off.csv").write_text(centers_csv(off))
    (folder / "empty.tif").write_bytes(b"")
    (folder / "image.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    (folder / "existing.tif").write_bytes(b"user data")
    (folder / "existing.png").write_bytes(b"user data")
    (folder / "a_folder").mkdir()
    (folder / "not_empty").mkdir()
    (folder / "not_empty" / "notes.txt").write_text("mine")
    configs = {
        "syntax": "system: small\nphantom: {kind: beads, n_beads: 5\nseed: 0\n",
        "zernike_nan": {"zernike": {5: float("nan")}},
        "background_nan": {"background": float("nan")},
        "photons_inf": {"photons": float("inf")},
        "read_noise_inf": {"read_noise": float("inf")},
        "intercepts_nan": {"intercepts": {1: [float("nan"), 0.0]}},
        "zernike_text": {"zernike": {5: "abc"}},
        "negative_beads": {"phantom": {"kind": "beads", "n_beads": -5}},
        "negative_sigma": {"phantom": {"kind": "beads", "n_beads": 5, "sigma": -1.0}},
        "typo": {"phantom": {"kind": "beads", "n_bead": 5}},
        "reticular": {"phantom": {"kind": "reticular"}},
        "line_width": {"phantom": {"kind": "line_sphere", "line_width": 0}},
        "many_beads": {"phantom": {"kind": "beads", "n_beads": 1e8}},
        "packed_beads": {"phantom": {"kind": "beads", "n_beads": 200, "min_spacing": 20.0}},
        "huge_view": {"view_size": 100000},
        "many_depths": {"depths_um": "-20:20:10000"},
        "bool_view": {"view_size": True},
        "fraction_view": {"view_size": 2.5},
        "seed": {"seed": -1},
        "terms": {"aberrations": {"terms": 40}},
        "depths": {"depths_um": "5:5:0"},
        "shift_view": {"intercepts": {9: [1, 1]}},
    }
    for name, change in configs.items():
        text = change if isinstance(change, str) else yaml.safe_dump({**SIMULATION, **change})
        (folder / f"{name}.yaml").write_text(text)
    (folder / "good.yaml").write_text(yaml.safe_dump(SIMULATION))
    return folder


def run(argv):
    """``fgat.app.cli.main(argv)``'s exit code, also when argparse exits."""
    try:
        return main([str(word) for word in argv])
    except SystemExit as exit:
        return exit.code


@pytest.fixture
def no_compute(monkeypatch):
    """Fail the test if a command starts its real work (a PSF stack or an FLFM operator)."""

    def refuse(*args, **kwargs):
        raise AssertionError("computation started before the bad input was refused")

    monkeypatch.setattr(JPGM, "forward", refuse)
    monkeypatch.setattr(FLFMOperator, "__init__", refuse)


def deconvolve(**changes):
    options = {
        "--measurement": "sensor.tif",
        "--psf": "psf.tif",
        "--centers": "centers.csv",
        "--out": "new.tif",
        "--iterations": "3",
        **changes,
    }
    words = ["deconvolve"]
    for option, value in options.items():
        words += [option] if value is None else [option, value]
    return words


def psf(*extra, out="new.tif"):
    return ["psf", "--system", "small", "--depths-um=-6:6:3", "--out", out, *extra]


def simulate(config, out="out"):
    return ["simulate", "--config", f"{config}.yaml", "--out", out]


CUDA = torch.cuda.is_available()
CASES = [
    # nothing the user made is lost
    (
        deconvolve(**{"--out": "existing.tif"}),
        "--out existing.tif: the file exists; choose another name or pass --overwrite",
    ),
    (psf(out="existing.tif"), "the file exists; choose another name or pass --overwrite"),
    (psf("--plot", "existing.png"), "--plot existing.png: the file exists"),
    (deconvolve(**{"--out": "a_folder"}), "--out a_folder: is a folder; expected a file name"),
    (psf(out="a_folder"), "--out a_folder: is a folder"),
    (psf("--plot", "a_folder"), "--plot a_folder: is a folder"),
    (psf(out="missing/x.tif"), "--out missing/x.tif: folder {d}/missing does not exist"),
    (simulate("good", out="existing.tif"), "existing.tif exists and is not a folder"),
    (
        simulate("good", out="not_empty"),
        "not_empty is not empty; choose another folder or pass --overwrite",
    ),
    # NaN / Inf
    (
        deconvolve(**{"--background": "nan"}),
        "argument --background: must be a finite number, got 'nan'",
    ),
    (psf("--zernike", "5=nan"), "zernike[5] must be a finite number (waves), got nan"),
    (psf("--intercepts", "1=nan:0"), "intercepts[1] must be a finite number (pixels), got nan"),
    (psf("--slopes", "1=inf:0"), "slopes[1] must be a finite number (pixels), got inf"),
    (
        simulate("zernike_nan"),
        "zernike_nan.yaml: zernike[5] must be a finite number (waves), got nan",
    ),
    (
        simulate("background_nan"),
        "background_nan.yaml: background must be a finite number, got nan",
    ),
    (simulate("photons_inf"), "photons_inf.yaml: photons must be a finite number, got inf"),
    (
        simulate("read_noise_inf"),
        "read_noise_inf.yaml: read_noise must be a finite number, got inf",
    ),
    (
        simulate("intercepts_nan"),
        "intercepts_nan.yaml: intercepts[1] must be a finite number (pixels), got nan",
    ),
    (simulate("zernike_text"), "zernike[5] must be a finite number (waves), got 'abc'"),
    # sizes and shapes
    (deconvolve(**{"--view-size": "0"}), "argument --view-size: must be an integer >= 1, got '0'"),
    (
        deconvolve(**{"--view-size": "1000"}),
        "a 1000 x 1000 patch centred at [128.0, 128.0] does not fit on the 256 x 256",
    ),
    (
        deconvolve(**{"--truth": "truth.tif", "--view-size": "30"}),
        "truth.tif: shape (3, 32, 32) does not match the reconstruction (3, 30, 30)",
    ),
    (
        deconvolve(**{"--truth": "truth_z4.tif"}),
        "truth_z4.tif: shape (4, 32, 32) does not match the reconstruction (3, 32, 32)",
    ),
    (deconvolve(**{"--truth": "sensor.tif"}), "sensor.tif: expected 3D (Z, Y, X), got 2D"),
    # centres
    (deconvolve(**{"--centers": "duplicate.csv"}), "duplicate.csv: centres 2 and 3"),
    (deconvolve(**{"--centers": "duplicate.mat"}), "duplicate.mat: centres 2 and 3"),
    (
        deconvolve(**{"--centers": "uv.csv"}),
        "uv.csv: header 'u,v'; expected 'row,col'",
    ),
    (
        deconvolve(**{"--centers": "header_only.csv"}),
        "header_only.csv: no lenslet centres after the 'row,col' header",
    ),
    (
        deconvolve(**{"--centers": "off.csv"}),
        "lenslet centre 1 (628, 204.923) lies outside the 256 x 256 sensor",
    ),
    (deconvolve(**{"--centers": "missing.csv"}), "missing.csv: no such file"),
    # phantoms
    (simulate("negative_beads"), "phantom beads: n_beads must be an integer >= 1, got -5"),
    (simulate("negative_sigma"), "phantom beads: sigma must be a finite number >= 0, got -1.0"),
    (
        simulate("typo"),
        "typo.yaml: phantom: unknown option(s) ['n_bead'] for kind 'beads'; valid options: "
        "['intensity_range', 'margin', 'min_spacing', 'n_beads', 'seed', 'sigma']",
    ),
    (simulate("reticular"), "phantom: kind 'reticular' needs option(s) ['path']"),
    (simulate("line_width"), "phantom line_sphere: line_width must be a finite number > 0, got 0"),
    (simulate("many_beads"), "n_beads = 100000000 is more than the 3072 voxels where beads can go"),
    (
        simulate("packed_beads"),
        "n_beads = 200 beads 20 voxels apart cannot fit in shape (3, 32, 32)",
    ),
    # devices
    pytest.param(
        deconvolve(**{"--device": "cuda"}),
        "--device cuda: CUDA is not available on this machine (torch ",
        marks=pytest.mark.skipif(CUDA, reason="CUDA is available"),
    ),
    pytest.param(
        deconvolve(**{"--device": "cuda:99"}),
        "--device cuda:99: this machine has",
        marks=pytest.mark.skipif(not CUDA, reason="no CUDA"),
    ),
    (
        deconvolve(**{"--device": "tpu9"}),
        "--device 'tpu9': unknown device; expected auto, cpu, cuda, cuda:N or mps",
    ),
    # files
    (
        simulate("syntax"),
        "syntax.yaml: invalid YAML at line 3, column 5: expected ',' or '}', but got ':' "
        "(while parsing a flow mapping started at line 2, column 10)",
    ),
    (simulate("missing"), "simulation config missing.yaml does not exist"),
    (deconvolve(**{"--measurement": "empty.tif"}), "empty.tif: not a readable TIFF file"),
    (deconvolve(**{"--measurement": "image.png"}), "image.png: not a readable TIFF file"),
    (
        deconvolve(**{"--measurement": "sensor3d.tif"}),
        "sensor3d.tif: expected 2D (H, W) sensor image, got 3D",
    ),
    (deconvolve(**{"--psf": "psf3d.tif"}), "psf3d.tif: expected 4D (V, Z, h, w) PSF stack, got 3D"),
    # other options and fields
    (
        deconvolve(**{"--iterations": "-1"}),
        "argument --iterations: must be an integer >= 1, got '-1'",
    ),
    (
        deconvolve(**{"--guard-px": "wide"}),
        "argument --guard-px: expected 'auto' or a number of pixels >= 0, got 'wide'",
    ),
    (deconvolve(**{"--tol": "nan"}), "argument --tol: must be a finite number > 0, got 'nan'"),
    (psf("--depths-um=0,0"), "depths '0,0': depth 0 is given more than once"),
    (psf("--depths-um=nan"), "depths 'nan': every depth must be a finite number"),
    (psf("--depths-um=5:5:0"), "depth count must be positive in '5:5:0'"),
    (psf("--zernike", "0=0.1"), "zernike: keys must be Noll indices (integers >= 1), got 0"),
    (psf("--zernike", "5=0.1,5=0.2"), "'5=0.1,5=0.2': 5 is given more than once"),
    (psf("--slopes", "9=1:1"), "slopes: view 9 does not exist (views 0..6)"),
    (psf("--crop-radius", "0"), "argument --crop-radius: must be an integer >= 1, got '0'"),
    (psf("--crop-radius", "5000"), "10001-pixel crops, wider than the 256 x 256 sensor"),
    (
        ["psf", "--objective", "15x/0.3", "--depths-um=0", "--out", "new.tif"],
        "unknown system '15x/0.3'",
    ),
    (
        simulate("huge_view"),
        "a 100000 x 100000 patch centred at [128.0, 128.0] does not fit on the 256 x 256 sensor",
    ),
    (simulate("bool_view"), "bool_view.yaml: view_size must be an integer, got True"),
    (simulate("fraction_view"), "fraction_view.yaml: view_size must be an integer, got 2.5"),
    (simulate("seed"), "seed.yaml: seed must be non-negative, got -1"),
    (simulate("terms"), "terms.yaml: aberrations.terms must be 1..17, got 40"),
    (simulate("depths"), "depths.yaml: depth count must be positive in '5:5:0'"),
    (simulate("shift_view"), "intercepts: view 9 does not exist (views 0..6)"),
    (["design", "--objective", "20/0.45"], "MAGx/NA"),
    (
        ["design", "--wavelength-um", "-1"],
        "wavelength_um must be a positive finite number, got -1.0",
    ),
    (["design", "--pixel-um", "nan"], "pixel_um must be a positive finite number, got nan"),
    (
        ["design", "--objective", "0x/0.45"],
        "magnification must be a positive finite number, got 0.0",
    ),
]


@pytest.mark.parametrize("argv,message", CASES)
def test_bad_input_fails_fast_with_one_line(argv, message, d, capsys, monkeypatch, no_compute):
    monkeypatch.chdir(d)
    assert run(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert "Traceback" not in err
    assert lines[-1].startswith(f"fgat {argv[0]}: error: ")
    assert message.replace("{d}", str(d)) in lines[-1]
    assert all(not (d / name).exists() for name in ("new.tif", "out"))


MEMORY_CASES = [
    (
        ["psf", "--system", "small", "--depths-um=-20:20:10000", "--out", "new.tif"],
        "the 10000 planes of the PSF stack need about",
    ),
    (simulate("many_depths"), "the phantom, PSF stack and forward model need about"),
    (deconvolve(), "the FLFM operator and the deconvolution need about"),
]


@pytest.mark.parametrize("argv,message", MEMORY_CASES)
def test_requests_larger_than_memory_are_refused(argv, message, d, capsys, monkeypatch, no_compute):
    monkeypatch.setattr(resources, "_host_available", lambda: 2_000_000)  # room for the inputs only
    monkeypatch.chdir(d)
    assert run(argv) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in line and "; this machine has 2.0 MB available (" in line


def test_reading_a_file_larger_than_memory_is_refused_from_its_header(d, capsys, monkeypatch):
    monkeypatch.setattr(resources, "_host_available", lambda: 100_000)
    monkeypatch.chdir(d)
    assert run(deconvolve()) == 2
    line = capsys.readouterr().err.strip()
    assert line == (
        "fgat deconvolve: error: the (256, 256) float32 values of sensor.tif need about 262.1 kB; "
        "this machine has 100.0 kB available"
    )


def test_memory_estimate_matches_a_hand_computation():
    # PSF (2, 3, 5, 5) on a (3, 8, 8) volume: FFT grid 10 x 10 (8 + 5 // 2), 10 x 6 complex bins.
    real, spectrum = 10 * 10 * 4, 10 * 6 * 8  # float32 grid, complex64 bins
    otf = 2 * 3 * (real + 2 * spectrum)  # padded PSFs, OTFs and their conjugate
    projections = 2 * (3 + 2) * (real + spectrum)
    assert operator_memory((2, 3, 5, 5), (3, 8, 8)) == otf + projections == 16960
    assert costs.deconvolution_memory((2, 3, 5, 5), (3, 8, 8)) == 16960 + (6 * 3 + 5 * 2) * 64 * 4
    operator = FLFMOperator(torch.rand(7, 5, 65, 65), (5, 76, 76))
    held = (operator.otf.numel() + operator.conjugate_otf.numel()) * 8
    assert held <= operator_memory((7, 5, 65, 65), (5, 76, 76)) <= 3 * held


def test_psf_memory_grows_by_the_windows_and_crops_of_each_depth():
    small = load_system("small")  # crop radius 32: windows and crops of 66 x 66 per view and depth
    grow = (  # a fixed depth chunk: the automatic one evens out over the depths
        JPGM(small, torch.linspace(-20, 20, 200), depth_chunk=10).memory_bytes()
        - JPGM(small, torch.linspace(-20, 20, 100), depth_chunk=10).memory_bytes()
    )
    assert grow == 100 * 7 * (2 * 66**2 + 4 * 66**2) * 4


def test_check_memory_message():
    resources.check_memory("a small buffer", 1000)
    with pytest.raises(
        ValueError,
        match=r"^the buffers need about 1000.0 PB; this machine has .* available \(less\)$",
    ):
        resources.check_memory("the buffers", 10**18, hint="less")
    assert (
        resources.format_bytes(1.9e12) == "1.9 TB" and resources.format_bytes(21.3e9) == "21.3 GB"
    )


def test_existing_outputs_are_kept_unless_overwrite(d, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(d)
    out = tmp_path / "volume.tif"
    out.write_bytes(b"user data")
    argv = deconvolve(**{"--out": out})
    assert run(argv) == 2 and out.read_bytes() == b"user data"
    assert run(argv + ["--overwrite"]) == 0
    assert read_tiff(out).shape == (3, 76, 76)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["volume.residual.json", "volume.tif"]
    assert "fgat deconvolve: error: --out" in capsys.readouterr().err


def test_background_clipping_is_reported(d, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(d)
    argv = deconvolve(**{"--out": tmp_path / "v.tif"})
    views = FLFMOperator.views_from_sensor(
        torch.from_numpy(read_tiff(d / "sensor.tif")), CENTERS, 76
    )
    expected = int((views < 150).sum())
    assert run(argv + ["--background", "150"]) == 0
    out = capsys.readouterr().out
    assert (
        f"--background 150: {expected} of {views.numel()} view pixels "
        f"({expected / views.numel():.1%}) "
        "are below it and are clipped to 0" in out
    )
    assert 0 < expected < views.numel()


def test_read_only_folder_is_refused_before_compute(tmp_path, capsys, no_compute):
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        probe = folder / "probe"
        try:
            probe.write_bytes(b"")
            probe.unlink()
            pytest.skip(
                "files can be created in a 555 folder here (root): permissions are not enforced"
            )
        except PermissionError:
            pass
        assert run(psf(out=str(folder / "psf.tif"))) == 2
        assert run(["simulate", "--config", "unused.yaml", "--out", str(folder / "sim")]) == 2
    finally:
        folder.chmod(0o755)
    err = capsys.readouterr().err
    assert f"--out {folder}/psf.tif: cannot write in folder {folder} (Permission denied)" in err


@pytest.mark.skipif(
    not os.path.isdir("/proc/self"), reason="needs Linux /proc, read-only even for root"
)
def test_read_only_file_system_is_refused_before_compute(d, capsys, monkeypatch, no_compute):
    monkeypatch.chdir(d)
    assert run(deconvolve(**{"--out": "/proc/volume.tif"})) == 2
    assert run(psf("--plot", "/proc/psf.png")) == 2
    assert run(simulate("good", out="/proc/simulation")) == 2
    assert capsys.readouterr().err.splitlines() == [
        "fgat deconvolve: error: --out /proc/volume.tif: cannot write in folder /proc "
        "(No such file or directory)",
        "fgat psf: error: --plot /proc/psf.png: cannot write in folder /proc "
        "(No such file or directory)",
        "fgat simulate: error: /proc/simulation: cannot write in folder /proc "
        "(No such file or directory)",
    ]


def test_simulate_overwrite_keeps_files_it_did_not_write(d, tmp_path, capsys):
    out = tmp_path / "sim"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert run(["simulate", "--config", d / "good.yaml", "--out", out]) == 2
    assert run(["simulate", "--config", d / "good.yaml", "--out", out, "--overwrite"]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in out.iterdir()) == sorted([*OUTPUT_FILES, "notes.txt"])
    (out / "truth.ome.tif").unlink()
    (out / "truth.ome.tif").mkdir()  # a folder under one of fgat's names is not replaced
    assert run(["simulate", "--config", d / "good.yaml", "--out", out, "--overwrite"]) == 2
    assert "truth.ome.tif: is a folder" in capsys.readouterr().err


def dead_pid():
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    target = tmp_path / "volume.ome.tif"
    dead = tmp_path / f".volume.ome.tif.{dead_pid()}.k2j4_x9a.part"
    live = tmp_path / f".volume.ome.tif.{os.getppid()}.q8w3e1rt.part"
    other = [
        tmp_path / ".volume.ome.tif.backup.part",
        tmp_path / f".other.tif.{dead_pid()}.abcdefgh.part",
    ]
    for path in (dead, live, *other):
        path.write_bytes(b"half")
    write_tiff(target, np.ones((2, 3, 3), np.float32))
    assert not dead.exists() and live.exists() and all(path.exists() for path in other)
    np.testing.assert_array_equal(read_tiff(target), np.ones((2, 3, 3)))


def test_a_killed_writer_leaves_a_temporary_that_the_next_write_removes(tmp_path):
    target = tmp_path / "volume.ome.tif"
    code = (
        "import os, signal, sys\nfrom fgat.io.files import atomic_path\n"
        "with atomic_path(sys.argv[1]) as temporary:\n"
        "    temporary.write_bytes(b'half')\n    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    killed = subprocess.run([sys.executable, "-c", code, str(target)])
    assert killed.returncode == -signal.SIGKILL
    (left,) = tmp_path.iterdir()
    assert left.name.startswith(".volume.ome.tif.") and left.name.endswith(".part")
    assert int(left.name.split(".")[4]) > 0  # the writer's PID
    write_tiff(target, np.zeros((4, 4), np.float32))
    assert [p.name for p in tmp_path.iterdir()] == ["volume.ome.tif"]


def test_col_row_header_is_read_as_named(tmp_path, d, capsys, monkeypatch):
    monkeypatch.chdir(d)
    rng = np.random.default_rng(1)
    rows = rng.uniform(0, 256, (7, 2))
    text = centers_csv(rows[:, ::-1], "Col , Row")
    (tmp_path / "swapped.csv").write_text(text)
    lines = text.splitlines()
    names = [name.strip().lower() for name in lines[0].split(",")]
    reference = np.array(
        [
            [float(dict(zip(names, line.split(",")))[axis]) for axis in ("row", "col")]
            for line in lines[1:]
        ]
    )
    np.testing.assert_array_equal(read_centers(tmp_path / "swapped.csv"), reference)
    np.testing.assert_allclose(reference, rows)
    (tmp_path / "swapped_real.csv").write_text(centers_csv(CENTERS[:, ::-1], "col,row"))
    volumes = []
    for name, centers in (
        ("straight", d / "centers.csv"),
        ("swapped", tmp_path / "swapped_real.csv"),
    ):
        assert run(deconvolve(**{"--centers": centers, "--out": tmp_path / f"{name}.tif"})) == 0
        volumes.append(read_tiff(tmp_path / f"{name}.tif"))
    np.testing.assert_array_equal(volumes[0], volumes[1])


def test_tiny_views_are_written_as_volumes(d, tmp_path, monkeypatch):
    monkeypatch.chdir(d)
    assert run(deconvolve(**{"--view-size": "3", "--out": tmp_path / "v.tif"})) == 0
    assert read_tiff(tmp_path / "v.tif").shape == (3, 3, 3)  # not read back as an RGB image


# ------------------------------------------------------------- sizes, faults and litter
def last_line(capsys):
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]


def test_psf_stack_is_sized_before_any_plane_is_made(d, capsys, monkeypatch, no_compute):
    built = []
    init = JPGM.__init__

    def record(self, system, depths_um, **options):
        built.append(len(depths_um))
        init(self, system, depths_um, **options)

    monkeypatch.setattr(JPGM, "__init__", record)
    monkeypatch.setattr(resources, "_host_available", lambda: 500_000_000)
    monkeypatch.chdir(d)
    assert run(psf(out="new.tif")[:3] + ["--depths-um=-20:20:4000", "--out", "new.tif"]) == 2
    line = last_line(capsys)
    assert line.startswith("fgat psf: error: the 4000 planes of the PSF stack need about ")
    assert "; this machine has 500.0 MB available (fewer --depths-um" in line
    assert built == [2]  # the two extreme depths only, never the 4000-plane model
    assert not (d / "new.tif").exists()


def test_psf_size_from_the_extreme_depths_equals_the_full_models():
    from fgat.optics.spec import OpticsSpec

    system = load_system("small")
    depths = (-7.0, -3.5, 0.0, 2.0, 6.0, 9.5)  # uneven: only the range matters
    full = OpticsSpec(system, depths, zernike={5: 0.2}).jpgm(crop_radius_px=12)
    probe = OpticsSpec(system, (-7.0, 9.5), zernike={5: 0.2}).jpgm(crop_radius_px=12)
    full.check_sampling()
    probe.check_sampling()
    assert probe.memory_bytes(planes=len(depths)) == full.memory_bytes()


@pytest.mark.parametrize(
    "fields,message",
    [
        ("n_lenslets: 1e8", "n_lenslets = 100000000 lenslets of pitch 76.9 px fit neither"),
        ("n_lenslets: 100000000", "on the 256 x 256 px sensor nor in the pupil of radius"),
        ("n_lenslets: 7.5", "n_lenslets must be an integer >= 1, got 7.5"),
        ("n_lenslets: '7'", None),
        ("crop_radius_px: 4000", "crop_radius_px = 4000 makes PSF crops of 8001 px, wider"),
        ("sensor_shape: [256, 512.0]", None),
        ("sensor_shape: [256, -3]", "sensor_shape must be two positive integers, got (256, -3)"),
        ("n_lenslets: 7\nn_lenslets: 19", "duplicate key 'n_lenslets' at line 3 (first given"),
    ],
)
def test_system_counts_are_checked_when_loaded(tmp_path, fields, message):
    path = tmp_path / "mine.yaml"
    path.write_text(f"base: small\n{fields}\n")
    start = time.perf_counter()
    if message is None:
        system = load_system(path)
        assert isinstance(system.n_lenslets, int) and all(
            isinstance(side, int) for side in system.sensor_shape
        )
        return
    with pytest.raises(ValueError) as caught:
        load_system(path)
    assert time.perf_counter() - start < 2.0
    assert str(caught.value).startswith(f"{path}: ")
    assert message in str(caught.value)


def test_system_with_too_many_lenslets_is_refused_by_psf_at_once(d, tmp_path, capsys):
    path = tmp_path / "huge.yaml"
    path.write_text("base: small\nn_lenslets: 1e8\n")
    start = time.perf_counter()
    assert run(["psf", "--system", path, "--depths-um", "0", "--out", tmp_path / "p.tif"]) == 2
    assert time.perf_counter() - start < 2.0
    assert f"fgat psf: error: {path}: system 'small': n_lenslets = 100000000" in last_line(capsys)


def test_deconvolution_beyond_a_day_needs_allow_long(d, capsys, monkeypatch):
    from fgat.recon import deconvolution

    monkeypatch.chdir(d)
    assert run(deconvolve(**{"--iterations": "1e9"})) == 2
    line = last_line(capsys)
    assert line.startswith("fgat deconvolve: error: the deconvolution would take about ")
    assert "(1000000000 iterations x " in line
    assert "more than 24.0 h: lower --iterations, or pass --allow-long to run it" in line
    hours = float(line.split("would take about ")[1].split(" h")[0])
    assert hours > 24
    assert not (d / "new.tif").exists()

    class Started(Exception):
        pass

    def started(*args, **kwargs):
        raise Started

    monkeypatch.setattr(deconvolution, "deconvolve", started)
    with pytest.raises(Started):
        run(deconvolve(**{"--iterations": "1e9"}) + ["--allow-long"])


def test_deconvolution_names_the_given_background(d, capsys, monkeypatch, no_compute):
    monkeypatch.chdir(d)  # the sensor is uniform in [90, 200)
    assert run(deconvolve(**{"--background": "1000"})) == 2
    assert last_line(capsys) == (
        "fgat deconvolve: error: --measurement sensor.tif: every view pixel is at or below the "
        "--background 1000; nothing is left to deconvolve (check --background, --dark or the "
        "calibration)"
    )


def test_a_sequence_reports_its_views_not_its_frames(d, tmp_path, capsys):
    config = tmp_path / "moving.yaml"
    config.write_text(
        yaml.safe_dump(
            {**SIMULATION, "phantom": {"kind": "moving_beads", "n_beads": 3}, "frames": 3}
        )
    )
    assert run(["simulate", "--config", config, "--out", tmp_path / "sim"]) == 0
    out = capsys.readouterr().out
    assert "(T, Z, Y, X), 7 views, sensor (3, 256, 256)" in out


@pytest.mark.parametrize(
    "text,message",
    [
        (
            "system: small\nview_size: 32\nphantom: {kind: beads, n_beads: 4}\nview_size: 48\n",
            "invalid YAML at line 4, column 1: duplicate key 'view_size' at line 4 (first given "
            "at line 2)",
        ),
        (b"\xff\xfe\x00\x01binary", "not a UTF-8 text file (byte 0xff at offset 0)"),
    ],
)
def test_yaml_configs_that_cannot_be_trusted_are_refused(tmp_path, capsys, text, message):
    for command, config in (("simulate", "sim.yaml"), ("fit", "fit.yaml"), ("psf", "sys.yaml")):
        path = tmp_path / config
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        argv = {
            "simulate": ["simulate", "--config", path, "--out", tmp_path / "out"],
            "fit": ["fit", "--config", path],
            "psf": ["psf", "--system", path, "--depths-um", "0", "--out", tmp_path / "p.tif"],
        }[command]
        start = time.perf_counter()
        assert run(argv) == 2
        assert time.perf_counter() - start < 2.0
        line = last_line(capsys)
        assert line.startswith(f"fgat {command}: error: ") and str(path) in line
        assert message in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.yaml", "sim.yaml", "sys.yaml"]


def test_a_truncated_tiff_is_named(d, tmp_path, capsys, monkeypatch, no_compute):
    monkeypatch.chdir(d)
    for name in ("sensor.tif", "psf.tif"):
        data = (d / name).read_bytes()
        (tmp_path / name).write_bytes(data[: len(data) // 2])
    assert run(deconvolve(**{"--measurement": tmp_path / "sensor.tif"})) == 2
    assert last_line(capsys).startswith(
        f"fgat deconvolve: error: {tmp_path / 'sensor.tif'}: the TIFF file is truncated or corrupt"
    )
    assert run(deconvolve(**{"--psf": tmp_path / "psf.tif"})) == 2
    assert last_line(capsys).startswith(
        f"fgat deconvolve: error: {tmp_path / 'psf.tif'}: the TIFF file is truncated or corrupt"
    )


def small_disk(monkeypatch, free):
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**12, 10**12 - free, free))


@pytest.mark.parametrize(
    "argv,needs",
    [
        (psf(out="new.tif"), 7 * 3 * 65 * 65 * 4),  # views x planes x crop^2 float32
        (deconvolve(), 3 * 76 * 76 * 4),  # the volume
        (simulate("good"), 4 * (3 * 32 * 32 + 256 * 256 + 7 * 32 * 32 + 7 * 3 * 65 * 65)),
    ],
)
def test_outputs_larger_than_the_free_disk_are_refused_before_compute(
    argv, needs, d, capsys, monkeypatch, no_compute
):
    small_disk(monkeypatch, 1000)
    monkeypatch.chdir(d)
    assert run(argv) == 2
    line = last_line(capsys)
    needs = resources.format_bytes(needs)
    assert f"needs about {needs} of disk space; only 1.0 kB free in {d}; free some" in line
    assert not (d / "new.tif").exists() and not (d / "out").exists()


@pytest.fixture
def full_disk(monkeypatch):
    """``tifffile.imwrite`` fails with ENOSPC from its ``n``-th call on (``full_disk(n)``); the
    list of the paths it was called with is returned."""
    calls = []
    imwrite = tifffile.imwrite

    def arm(first_failing: int) -> list:
        def write(*args, **kwargs):
            calls.append(args[0])
            if len(calls) >= first_failing:
                raise OSError(errno.ENOSPC, "No space left on device")
            return imwrite(*args, **kwargs)

        monkeypatch.setattr(tifffile, "imwrite", write)
        return calls

    return arm


def test_disk_full_during_simulate_removes_what_it_wrote(d, tmp_path, capsys, full_disk):
    calls = full_disk(2)  # truth.ome.tif is written, psf.ome.tif fails
    out = tmp_path / "a" / "sim"
    assert run(["simulate", "--config", d / "good.yaml", "--out", out]) == 2
    line = last_line(capsys)
    assert line.startswith(f"fgat simulate: error: cannot write {out / 'psf.ome.tif'}: the disk")
    assert "the disk is full (No space left on device); needs about 354.9 kB" in line
    assert len(calls) == 2 and list(tmp_path.iterdir()) == []  # the folders it made are gone


def test_disk_full_during_deconvolve_and_psf_leaves_nothing(
    d, tmp_path, capsys, monkeypatch, full_disk
):
    full_disk(1)
    monkeypatch.chdir(d)
    assert run(deconvolve(**{"--out": tmp_path / "v.tif"})) == 2
    line = last_line(capsys)
    assert line.startswith(f"fgat deconvolve: error: cannot write {tmp_path / 'v.tif'}: the disk")
    assert f"needs about {resources.format_bytes(3 * 76 * 76 * 4)}" in line
    assert run(psf(out=tmp_path / "p.tif")) == 2
    assert last_line(capsys).startswith(f"fgat psf: error: cannot write {tmp_path / 'p.tif'}")
    assert list(tmp_path.iterdir()) == []


def test_a_volume_whose_report_cannot_be_written_is_removed(d, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(d)
    monkeypatch.setattr(type(tmp_path), "write_text", no_space)
    assert run(deconvolve(**{"--out": tmp_path / "v.tif"})) == 2
    assert last_line(capsys).startswith(
        f"fgat deconvolve: error: cannot write {tmp_path / 'v.residual.json'}: the disk is full"
    )
    assert list(tmp_path.iterdir()) == []


def no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_no_lock_file_is_left_beside_a_users_file(tmp_path):
    from fgat.app.callbacks.mlflow import _store_lock, check_tracking_uri

    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"II*\x00 not a database")
    with pytest.raises(ValueError, match="garbage.tif exists and is not an SQLite database"):
        check_tracking_uri(f"sqlite:///{garbage}", "experiment")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["garbage.tif"]
    assert _store_lock(garbage).parent != tmp_path
    assert _store_lock(tmp_path / "x" / ".." / "garbage.tif") == _store_lock(garbage)
