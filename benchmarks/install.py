"""Install size and time: fgat's core and dev installs in fresh virtual environments.

For each install a new ``python -m venv`` in a temporary folder gets ``pip install
--no-cache-dir -e <checkout>[extras] "torch==<--torch>"``, timed (downloads included: nothing
is cached); then its size on disk (MB, 1e6 bytes; files counted once), its package count (``pip
list``, pip and setuptools included) and its five largest distributions (their installed files).
The editable fgat's own files stay in the checkout: not counted.

- ``core``: no extras. The commands a user runs first must work there, without Ray, Triton,
  napari and Qt or the test tools (whether each imports is recorded): ``--help``,
  ``--version``, ``design``, ``sweep --help``, the quickstart fit shortened to ``--steps``
  steps and a two-point sweep with ``--parallel 2`` (without Ray it runs its trials one after
  another and says how to parallelise; that line is recorded). Then ``[cluster]``,
  ``[gpu-kernels]`` and ``[napari]`` are each installed into it in turn: what each adds (MB,
  packages, time) is the difference.
- ``dev``: ``[dev]`` (the extras above, the documentation tools and the test and lint tools).

Where the torch pin finds a CPU wheel (a wheelhouse, a mirror, PyTorch's CPU index), no CUDA
library is installed; from PyPI on Linux the pin brings the CUDA build and its libraries (and
Triton with it), gigabytes more.

    python benchmarks/install.py [--torch 2.13.0] [--steps 20] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from shared_machine import fit_command

from fgat.app.recipes.benchmark import provenance, write_json

ROOT = Path(__file__).resolve().parent.parent
MB = 1e6
INSTALLS = {"core": "", "dev": "[dev]"}
EXTRAS = ("cluster", "gpu-kernels", "napari")
OPTIONAL = (
    "ray",
    "triton",
    "napari",
    "qtpy",
    "pytest",
    "hypothesis",
    "ome_zarr",
    "mkdocs",
    "importlinter",
)
DISTRIBUTION_SIZES = """
import importlib.metadata, json
sizes = {}
for dist in importlib.metadata.distributions():
    total = 0
    for file in dist.files or ():
        path = dist.locate_file(file)
        if path.is_file():
            total += path.stat().st_size
    sizes[dist.metadata["Name"].lower()] = total
print(json.dumps(sizes))
"""
IMPORTABLE = """
import importlib.util, json, sys
print(json.dumps({name: importlib.util.find_spec(name) is not None for name in sys.argv[1:]}))
"""


def disk_mb(folder: Path) -> float:
    """Disk space (MB) of the files under ``folder``: allocated blocks, each hard-linked file once,
    symbolic links not followed."""
    seen, total = set(), 0
    for directory, _, files in os.walk(folder):
        for name in files:
            status = os.lstat(os.path.join(directory, name))
            if (status.st_dev, status.st_ino) not in seen:
                seen.add((status.st_dev, status.st_ino))
                total += status.st_blocks * 512
    return total / MB


def environment() -> dict[str, str]:
    """This process's environment without what would put another Python's packages in a
    virtual environment's way."""
    skip = ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")
    return {k: v for k, v in os.environ.items() if k not in skip}


def run(command: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=cwd, env=environment(), capture_output=True, text=True)


def checked(command: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    """:func:`run`, raising with the end of its output where it fails."""
    done = run(command, cwd)
    if done.returncode != 0:
        output = (done.stdout + done.stderr)[-3000:]
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}):\n{output}")
    return done


def pip_install(python: Path, extras: str, torch: str) -> tuple[list[str], float]:
    """``pip install`` of this checkout with ``extras`` (``""`` or ``"[dev]"``) and the torch pin
    into ``python``'s environment: the command as a user types it, and its wall time (s)."""
    arguments = ["install", "--no-cache-dir", "-e", f"{ROOT}{extras}", f"torch=={torch}"]
    start = time.perf_counter()
    checked([str(python), "-m", "pip", *arguments])
    shown = ["pip", *arguments[:-2], f'"<checkout>{extras}"', f'"torch=={torch}"']
    return shown, time.perf_counter() - start


def state(python: Path, venv: Path) -> dict:
    """Size (MB), package count and per-distribution sizes (MB) of ``python``'s environment."""
    listed = json.loads(checked([str(python), "-m", "pip", "list", "--format=json"]).stdout)
    sizes = json.loads(checked([str(python), "-c", DISTRIBUTION_SIZES]).stdout)
    return {
        "venv_mb": disk_mb(venv),
        "packages": len(listed),
        "names": sorted(p["name"].lower() for p in listed),
        "sizes_mb": {name: size / MB for name, size in sizes.items()},
    }


def largest(sizes_mb: dict[str, float], count: int = 5) -> list[dict]:
    ranked = sorted(sizes_mb.items(), key=lambda item: -item[1])[:count]
    return [{"name": name, "mb": round(mb, 1)} for name, mb in ranked]


def new_venv(folder: Path, name: str) -> tuple[Path, Path]:
    venv = folder / name
    checked([sys.executable, "-m", "venv", str(venv)])
    return venv, venv / "bin" / "python"


def install(folder: Path, name: str, torch: str) -> tuple[dict, Path, Path]:
    """A fresh environment with install ``name`` (a key of :data:`INSTALLS`): its row, the
    environment and its Python."""
    venv, python = new_venv(folder, name)
    command, seconds = pip_install(python, INSTALLS[name], torch)
    after = state(python, venv)
    row = {
        "command": " ".join(command),
        "venv_mb": round(after["venv_mb"], 1),
        "install_s": round(seconds, 1),
        "packages": after["packages"],
        "largest_packages": largest(after["sizes_mb"]),
        "importable": importable(python),
    }
    print(f"{name}: {row['venv_mb']:.0f} MB, {row['packages']} packages, {seconds:.0f} s")
    return row, venv, python


def importable(python: Path) -> dict[str, bool]:
    """Whether each optional module imports in ``python``'s environment."""
    return json.loads(checked([str(python), "-c", IMPORTABLE, *OPTIONAL]).stdout)


def add_extra(python: Path, venv: Path, extra: str, torch: str) -> dict:
    """Install ``[extra]`` into an environment: what it adds."""
    before = state(python, venv)
    command, seconds = pip_install(python, f"[{extra}]", torch)
    after = state(python, venv)
    added = {n: mb for n, mb in after["sizes_mb"].items() if n not in before["sizes_mb"]}
    row = {
        "command": " ".join(command),
        "added_mb": round(after["venv_mb"] - before["venv_mb"], 1),
        "install_s": round(seconds, 1),
        "added_packages": sorted(set(after["names"]) - set(before["names"])),
        "largest_packages": largest(added),
    }
    print(f"[{extra}]: +{row['added_mb']:.0f} MB, +{len(row['added_packages'])} packages")
    return row


def core_commands(python: Path, folder: Path, steps: int) -> list[dict]:
    """The first commands of a user, run with ``python`` in an empty folder: each one's exit
    code, wall time and the lines of its output that say something is not installed."""
    fit = [str(python), *fit_command(folder, steps)[1:]]  # fit_command runs this Python
    sweep = [str(python), "-m", "fgat", "sweep", *fit[4:], "--grid", "seed=0:2", "--parallel", "2"]
    sweep = [  # its own output folder and MLflow store
        word.replace(str(folder / "run"), str(folder / "sweep")).replace("mlflow.db", "sweep.db")
        for word in sweep
    ]
    commands = [
        [str(python), "-m", "fgat", "--help"],
        [str(python), "-m", "fgat", "--version"],
        [str(python), "-m", "fgat", "design", "--objective", "20x/0.45", "--json"],
        [str(python), "-m", "fgat", "sweep", "--help"],
        fit,
        sweep,
    ]
    rows = []
    for command in commands:
        start = time.perf_counter()
        done = run(command, cwd=folder)
        output = done.stdout + done.stderr
        shown = " ".join(command[1:]).replace(str(folder), "<tmp>").replace(str(ROOT), "<checkout>")
        rows.append(
            {
                "command": f"python {shown}",
                "returncode": done.returncode,
                "seconds": round(time.perf_counter() - start, 1),
                "notices": [line for line in output.splitlines() if "not installed" in line],
            }
        )
        print(f"  {rows[-1]['returncode']}  {rows[-1]['seconds']:6.1f} s  {shown[:90]}")
        if done.returncode != 0:
            print(output[-3000:])
    return rows


def main() -> None:
    options = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    options.add_argument("--torch", default="2.13.0", help="the torch release pinned")
    options.add_argument("--steps", type=int, default=20, help="steps of the quickstart fit")
    options.add_argument("--out", default="benchmarks/results/install.json")
    args = options.parse_args()
    with tempfile.TemporaryDirectory(prefix="fgat-install-") as scratch:
        folder = Path(scratch)
        core, venv, python = install(folder, "core", args.torch)
        pip = checked([str(python), "-m", "pip", "--version"]).stdout.split()[1]
        work = folder / "work"
        work.mkdir()
        core["commands"] = core_commands(python, work, args.steps)
        extras = {extra: add_extra(python, venv, extra, args.torch) for extra in EXTRAS}
        shutil.rmtree(venv)
        dev, _, _ = install(folder, "dev", args.torch)
    command = f"python benchmarks/install.py --torch {args.torch} --steps {args.steps}"
    write_json(
        args.out,
        {
            **provenance(command, pip=pip),
            "torch": args.torch,
            "installs": {"core": core, "dev": dev},
            "extras_added_to_core": extras,
        },
    )


if __name__ == "__main__":
    main()
