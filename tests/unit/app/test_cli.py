import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import fgat.app.lightning_cli  # noqa: F401  (Lightning's log handler on the real stderr)
from fgat.app.cli import main
from fgat.io.images import read_tiff, read_voxel_size

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def run(*args):
    return subprocess.run([sys.executable, "-m", "fgat", *args], capture_output=True, text=True)


@pytest.mark.slow
def test_help_lists_subcommands():
    out = run("--help")
    assert out.returncode == 0
    for command in ("design", "psf"):
        assert command in out.stdout


def test_exit_waits_for_threads_runs_atexit_and_flushes(tmp_path):
    """``python -m fgat`` ends as Python's exit does, less the modules' finalisation: a
    non-daemon thread still writing is waited for, an idle thread pool (as MLflow's artifact
    downloads leave one) is shut down rather than waited on for ever, ``atexit`` handlers run,
    buffered output and the exit status come through."""
    script = f"""
import atexit, pathlib, sys, threading, time
from concurrent.futures import ThreadPoolExecutor
from fgat.app.cli import exit_without_finalising
folder = pathlib.Path({str(tmp_path)!r})
def late():
    time.sleep(0.5)
    (folder / "thread").write_text("done")
threading.Thread(target=late).start()
pool = ThreadPoolExecutor(2)  # kept, as MLflow keeps its artifact repository's
pool.submit(time.sleep, 0).result()  # its worker stays, idle
atexit.register(lambda: (folder / "atexit").write_text("ran"))
sys.stdout.write("buffered, no newline")
exit_without_finalising(3)
print("never")
"""
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 3, done.stderr
    assert done.stdout == "buffered, no newline"
    assert (tmp_path / "thread").read_text() == "done"
    assert (tmp_path / "atexit").read_text() == "ran"


def test_design_table_default_has_three_objectives(capsys):
    assert main(["design"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[2:]] == ["20x/0.45", "40x/0.90", "60x/1.25"]


def test_psf_command_writes_the_stack(tmp_path, capsys):
    out = tmp_path / "psf.ome.tif"
    plot = tmp_path / "psf.png"
    assert (
        main(
            [
                "psf",
                "--system",
                "small",
                "--depths-um=-20:20:5",
                "--out",
                str(out),
                "--zernike",
                "5=0.1,23=0.05",
                "--intercepts",
                "1=0.5:-0.5",
                "--plot",
                str(plot),
            ]
        )
        == 0
    )
    stack = read_tiff(out)
    assert stack.shape == (7, 5, 65, 65) and stack.dtype == np.float32
    assert read_voxel_size(out) == pytest.approx({"Z": 10.0, "Y": 0.975, "X": 0.975})
    assert plot.stat().st_size > 10_000
    assert "PSF stack (7, 5, 65, 65)" in capsys.readouterr().out


@pytest.mark.slow
def test_psf_warns_when_crops_lose_light(tmp_path):
    out = run(
        "psf",
        "--system",
        "small",
        "--depths-um=-50,0",
        "--crop-radius",
        "8",
        "--out",
        str(tmp_path / "p.tif"),
    )
    assert out.returncode == 0
    assert "warning: the crops hold only" in out.stderr and "-50 um" in out.stderr


def test_psf_parallax_of_the_20x_objective(tmp_path):
    out = tmp_path / "psf.ome.tif"
    assert (
        main(
            [
                "psf",
                "--objective",
                "20x/0.45",
                "--depths-um=-30,-15,0,15,30",
                "--out",
                str(out),
                "--crop-radius",
                "40",
            ]
        )
        == 0
    )
    stack = read_tiff(out).astype(np.float64)
    cols = np.arange(stack.shape[-1]) - stack.shape[-1] // 2
    centroid = (stack[1].sum(axis=1) * cols).sum(axis=1) / stack[1].sum(axis=(1, 2))
    assert abs(np.polyfit([-30, -15, 0, 15, 30], centroid, 1)[0]) == pytest.approx(0.28, abs=0.01)


@pytest.mark.parametrize(
    "args,message",
    [
        (["psf", "--system", "small", "--depths-um=a,b", "--out", "x.tif"], "depths 'a,b'"),
        (
            ["psf", "--system", "small", "--depths-um=0", "--out", "x.tif", "--zernike", "5:1"],
            "NOLL=WAVES",
        ),
        (["design", "--objective", "20/0.45"], "MAGx/NA"),
        (["psf", "--system", "tiny", "--depths-um=0", "--out", "x.tif"], "unknown system 'tiny'"),
        (
            ["psf", "--system", "small", "--depths-um=0", "--out", "x.tif", "--slopes", "9=1:1"],
            "view 9 does not exist",
        ),
        (
            ["psf", "--system", "small", "--depths-um=0", "--out", "no/x.tif"],
            "--out no/x.tif: folder",
        ),
        (
            [
                "fit",
                "--config",
                str(CONFIGS / "base" / "common.yaml"),
                "--config",
                str(CONFIGS / "dynamic_quick.yaml"),
                "--times",
                "0:1:3",
            ],
            "fgat fit: error: --times, --out and --overwrite belong to 'predict'",
        ),
        (
            [
                "fit",
                "--config",
                str(CONFIGS / "base" / "common.yaml"),
                "--config",
                str(CONFIGS / "dynamic_quick.yaml"),
                "--config",
                str(CONFIGS / "dynamic_quick_dynamic.yaml"),
                "--model.init_args.static=none.ckpt",
            ],
            "fgat fit: error: model.static: none.ckpt does not exist",
        ),
    ],
)
def test_bad_arguments_give_one_clear_line(args, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    try:
        code = main(args)
    except SystemExit as stop:  # an option parser's refusal
        code = stop.code
    assert code == 2
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error


@pytest.mark.parametrize(
    ("setting", "group"),
    [("densification", "Densification"), ("optics", "OpticsEstimation")],
)
def test_a_group_of_settings_given_as_null_is_one_line(setting, group, tmp_path, capsys):
    """``--model.init_args.<group>=null`` names the group's fields instead of a jsonargparse
    TypeError from deep in the instantiation."""
    words = ["fit", "--config", str(CONFIGS / "base" / "common.yaml")]
    words += ["--config", str(CONFIGS / "quickstart.yaml")]
    words += [f"--trainer.default_root_dir={tmp_path}", f"--model.init_args.{setting}=null"]
    assert main(words) == 2
    error = capsys.readouterr().err
    assert (
        f"fgat fit: error: model.init_args.{setting}: null; expected a mapping of {group}'s"
        in error
    )
    assert ("enabled" if setting == "densification" else "estimate") in error
    assert "Traceback" not in error and not list(tmp_path.iterdir())
