"""fgat's core install (``pip install -e .``) without its optional packages: Ray
(``[cluster]``), Triton (``[gpu-kernels]``), napari and Qt (``[napari]``) and the development
tools. Each is made unimportable here the way a missing package is (``sys.modules[name] =
None`` makes ``import name`` raise ImportError)."""

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from packaging.requirements import Requirement

import fgat
from fgat._core import devices
from fgat.app import trials

OPTIONAL = (
    "ray",
    "triton",
    "napari",
    "magicgui",
    "qtpy",
    "pytest",
    "hypothesis",
    "ome_zarr",
    "mkdocs",
    "importlinter",
)
CHECKOUT = Path(fgat.__file__).resolve().parents[1]
BLOCK = f"import sys\nfor name in {OPTIONAL!r}:\n    sys.modules[name] = None\n"


def without_optional(code: str) -> subprocess.CompletedProcess:
    """``code`` in a fresh Python where none of :data:`OPTIONAL` can be imported."""
    return subprocess.run(
        [sys.executable, "-c", BLOCK + code], capture_output=True, text=True, cwd=CHECKOUT
    )


def fgat_command(*words: str) -> subprocess.CompletedProcess:
    """``python -m fgat *words`` without the optional packages."""
    return without_optional(
        f"import runpy\nsys.argv = ['fgat', *{list(words)!r}]\n"
        "runpy.run_module('fgat', run_name='__main__', alter_sys=True)"
    )


@pytest.fixture
def no_triton(monkeypatch):
    monkeypatch.setitem(sys.modules, "triton", None)
    devices.triton_installed.cache_clear()
    yield
    devices.triton_installed.cache_clear()


def test_triton_missing_names_the_extra_and_auto_takes_pytorch(no_triton):
    means = torch.zeros(4, 3)
    assert not devices.triton_installed()
    assert devices.use_triton("auto", means, "means") is False
    with pytest.raises(ValueError, match=r"needs Triton.*pip install 'fgat\[gpu-kernels\]'"):
        devices.use_triton("triton", means, "means")


def test_ray_missing_is_seen_and_the_hint_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    assert trials.ray_available() is False
    assert "[cluster]" in trials.CLUSTER_HINT


def test_version_has_one_source():
    done = fgat_command("--version")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"fgat {fgat.__version__}"
    from setuptools.config.pyprojecttoml import read_configuration

    project = read_configuration(CHECKOUT / "pyproject.toml")["project"]
    assert project["version"] == fgat.__version__


def test_core_extras_leave_out_ray_triton_and_napari():
    from setuptools.config.pyprojecttoml import read_configuration

    project = read_configuration(CHECKOUT / "pyproject.toml")["project"]
    core = {Requirement(line).name.lower() for line in project["dependencies"]}
    assert not core & {"ray", "triton", "napari", "magicgui", "qtpy", "pyqt5", "pyqt6"}
    extras = project["optional-dependencies"]
    assert extras["cluster"] == ["ray>=2.9"]
    assert extras["gpu-kernels"][0].startswith("triton")
    assert {Requirement(line).name for line in extras["napari"]} == {"napari", "magicgui"}
    assert "fgat[cluster,gpu-kernels,docs,napari]" in extras["dev"]


@pytest.mark.parametrize(
    "words",
    [("--help",), ("design", "--objective", "20x/0.45", "--json"), ("sweep", "--help")],
)
def test_commands_run_without_optional_packages(words):
    done = fgat_command(*words)
    assert done.returncode == 0, done.stderr
    if "--json" in words:
        assert json.loads(done.stdout)


@pytest.mark.slow
def test_every_module_imports_without_optional_packages():
    """Only the Triton kernel modules (``*_triton``) and the napari widgets may need an optional
    package to import; every other module (but ``fgat.__main__``, which runs the command line),
    the plugin's reader and writer included, imports the optional ones inside the functions
    that use them."""
    names = [
        module.name
        for module in pkgutil.walk_packages(fgat.__path__, "fgat.")
        if not module.name.endswith(("_triton", ".__main__"))  # __main__ runs the CLI
        and module.name != "fgat.napari.widgets"  # napari's own widgets
    ]
    done = without_optional(
        "import importlib\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "print(len([n for n in sys.modules if n.startswith('fgat')]))"
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout) >= len(names)
