"""The napari plugin is an extra: the command line never loads napari or Qt, even where they are
installed, and the manifest names commands that exist (the core install's requirements:
tests/unit/app/test_extras.py)."""

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GUI = ("napari", "magicgui", "qtpy", "PyQt5", "PyQt6", "PySide2", "PySide6", "vispy")


def test_the_command_line_and_the_physics_load_without_gui_modules():
    code = (
        "import sys, fgat.app.cli, fgat.app.monitor, fgat.io.images, fgat.instrument.calibration;"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({GUI!r})))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_the_manifest_is_valid_and_its_commands_exist():
    npe2 = pytest.importorskip("npe2")
    pytest.importorskip("napari")
    manifest = npe2.PluginManifest.from_file(ROOT / "fgat" / "napari" / "napari.yaml")
    assert manifest.name == "fgat"
    for command in manifest.contributions.commands:
        module, name = command.python_name.split(":")
        assert callable(getattr(importlib.import_module(module), name)), command.python_name
    kinds = {
        "readers": len(manifest.contributions.readers),
        "writers": len(manifest.contributions.writers),
        "widgets": len(manifest.contributions.widgets),
    }
    assert kinds == {"readers": 1, "writers": 1, "widgets": 3}
