"""The high-NA hollow-microsphere recipe (reproduce/highna_shell.sh and .py): its scores, its
wrong-convention system, and the whole recipe at a tiny size."""

import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from fgat.app.recipes import highna_shell as recipe
from fgat.optics.systems import load_system
from fgat.sim.phantoms import shell_beads

ROOT = Path(__file__).resolve().parents[2]
SYSTEM = ROOT / "reproduce" / "systems" / "highna37.yaml"


def test_wrong_pitch_system_is_the_corner_to_corner_width(tmp_path):
    nominal = load_system(SYSTEM)
    path = tmp_path / "wrong.yaml"
    path.write_text(yaml.safe_dump(recipe.wrong_pitch_system(SYSTEM)))
    wrong = load_system(path)
    # a regular hexagon's corner-to-corner width is 2 / sqrt(3) of its flat-to-flat width
    assert wrong.pitch_px == pytest.approx(nominal.pitch_px * 2 / math.sqrt(3))
    assert wrong.lenslet_aperture_mm == pytest.approx(wrong.mla_pitch_mm)
    assert (wrong.na, wrong.sample_index, wrong.lenslet_shape) == (1.3, 1.33, "hexagon")
    path.write_text(yaml.safe_dump(recipe.immersion_depths_system(SYSTEM)))
    immersion = load_system(path)
    assert immersion.sample_index is None and immersion.sample_medium_index == 1.406
    assert immersion.replace(name=nominal.name, sample_index=1.33) == nominal


def test_volume_row_scores_the_truth_and_flags_an_empty_volume():
    voxel = (0.5, 0.54, 0.54)
    truth = shell_beads((25, 32, 32), voxel_size_um=voxel, diameter_um=9.0, n_beads=4)
    row = recipe.volume_row(truth, truth, voxel)
    assert row["aspect"] == pytest.approx(1.0, abs=0.01) and not row["empty"]
    assert row["border_ratio"] == pytest.approx(1.0) and row["ssim"] == pytest.approx(1.0)
    empty = recipe.volume_row(np.zeros_like(truth), truth, voxel)
    assert empty["empty"] and math.isnan(empty["aspect"]) and math.isnan(empty["psnr_registered"])


@pytest.mark.slow
def test_recipe_runs_at_a_tiny_size(tmp_path):
    """reproduce/highna_shell.sh on a 9 x 24 x 24 simulation, 60 fit steps (JPGM events of 2
    inner steps for 4DGAT after steps 40 and 60): every step runs, the summary scores all five
    volumes, and the script's exit status says whether the wrong-convention calibration was
    refused."""
    config = yaml.safe_load((ROOT / "configs/simulate/highna_shell.yaml").read_text())
    config.update(depths_um="-4:4:9", view_size=24)
    config["phantom"].update(diameter_um=8.0, n_beads=6, clearance_um=1.0, margin=[1, 0, 0])
    config["imperfections"].update(field_margin_px=4, dark_frames=2)
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump(config))
    out = tmp_path / "run"
    environment = {
        **os.environ,
        # the scripts import this checkout's fgat (python puts reproduce/ first on the path)
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        "HIGHNA_OUT": str(out),
        "HIGHNA_CONFIG": str(tmp_path / "sim.yaml"),
        "HIGHNA_DEPTHS": "-4:4:9",
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
    }
    fit_options = [
        "--trainer.max_steps=60",
        "--trainer.val_check_interval=30",
        "--trainer.enable_progress_bar=false",
        "--model.init_args.n_gaussians=200",
        "--model.init_args.densification={enabled: false}",
        "--model.init_args.optics.start=20",
        "--model.init_args.optics.every=20",
        "--model.init_args.optics.steps=2",
    ]
    result = subprocess.run(
        ["bash", "reproduce/highna_shell.sh", *fit_options],
        cwd=ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=3600,
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["wrong_pitch"] in ("refused", "accepted")
    assert (result.returncode == 0) == (summary["wrong_pitch"] == "refused"), result.stderr[-2000:]
    volumes = summary["volumes"]
    assert list(volumes) == [
        "truth",
        "SHB",
        "SHB, sample index unset",
        "3DGAT (optics fixed)",
        "4DGAT (optics estimated)",
    ]
    assert volumes["truth"]["aspect"] == pytest.approx(1.0, abs=0.02)
    assert not volumes["truth"]["empty"] and not volumes["SHB"]["empty"]
    assert volumes["SHB"]["psnr"] > 10
    assert "aspect" in result.stdout and "3DGAT (optics fixed)" in result.stdout
