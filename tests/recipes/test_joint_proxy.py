"""``benchmarks/joint_proxy.py``: Fig. S7 on the CPU proxy of the paper's scale."""

import json
import math
from pathlib import Path

import pytest

from fgat.app.recipes import joint_proxy

ROOT = Path(__file__).resolve().parents[2]
TINY = """\
trainer.accelerator: cpu
trainer.max_steps: 60
data.init_args.simulation.view_size: 48
data.init_args.simulation.depths_um: "-75:75:13"
data.init_args.simulation.phantom:
  {kind: beads, n_beads: 4, sigma: 1.0, min_spacing: 8.0, margin: 1.0}
model.init_args.n_gaussians: 20
model.init_args.baseline_iterations: 5
model.init_args.init_iterations: 5
model.init_args.optics:
  {depth_chunk: 0, start: 20, every: 10, steps: 2, blur_px: [2, 0], blur_events: 2}
"""


@pytest.fixture
def tiny(monkeypatch, tmp_path):
    """The proxy shrunk to a 13 x 48 x 48 grid and 60 static steps with four JPGM events (two
    blurred, two sharp)."""
    monkeypatch.chdir(ROOT)
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY)
    monkeypatch.setattr(joint_proxy, "PROXY_CONFIG", str(config))
    return tmp_path


def test_seed_ranges_and_lists():
    assert joint_proxy.seeds("0-7") == list(range(8))
    assert joint_proxy.seeds("3,5") == [3, 5]


@pytest.mark.slow
def test_a_trial_is_keyed_on_its_config_and_run_once(tiny, monkeypatch):
    """The digest changes with the seed, the method and every override; a trial found under its
    digest is read, not run again."""
    digests = {
        joint_proxy.trial_digest(joint_proxy.proxy_config(seed, overrides), method)
        for seed, method, overrides in (
            (0, "4DGAT", []),
            (1, "4DGAT", []),
            (0, "3DGAT", []),
            (0, "4DGAT", ["optics.blurred_estimate="]),
            (0, "4DGAT", ["optics.lr_zernike=0.02"]),
        )
    }
    assert len(digests) == 5
    config = joint_proxy.proxy_config(0, [])
    assert joint_proxy.trial_digest(config, "4DGAT") == joint_proxy.trial_digest(
        joint_proxy.proxy_config(0, []), "4DGAT"
    )
    runs = []

    def run_trial(config, seed, method, label):
        runs.append(seed)
        return {"seed": seed, "label": label, "events": []}

    monkeypatch.setattr(joint_proxy, "run_trial", run_trial)
    for _ in range(2):
        row = joint_proxy.cached_trial(tiny / "trials", 0, "4DGAT", [], "plain")
    assert runs == [0] and row == {"seed": 0, "label": "plain", "events": []}
    (path,) = (tiny / "trials").iterdir()
    assert path.name.startswith("plain-seed0-") and json.loads(path.read_text()) == row


@pytest.mark.slow
def test_zernike_first_holds_the_shifts_through_the_blurred_events(tiny):
    """With ``optics.blurred_estimate=zernike`` the two blurred events move the Zernike terms
    only (the shift errors stay the ideal optics'), the sharp ones every group; the truth-held
    run reports one row per blur level; every score is finite."""
    config = joint_proxy.proxy_config(0, ["optics.blurred_estimate=zernike"])
    row = joint_proxy.run_trial(config, 0, "4DGAT", "zernike-first")
    events = row["events"]
    assert [event["step"] for event in events] == [30, 40, 50, 60]
    assert [event["blur_px"] for event in events] == [2, 2, 0, 0]
    first, second, sharp = events[0], events[1], events[3]
    assert first["intercept_error_px"] == second["intercept_error_px"]
    assert first["slope_error_px"] == second["slope_error_px"]
    assert first["sigma"] != second["sigma"]
    assert sharp["intercept_error_px"] != second["intercept_error_px"]
    assert row["psf_error"] == pytest.approx(sharp["psf_error"])
    assert all(math.isfinite(row[key]) for key in ("psnr", "shb_psnr", "ideal_psf_error"))
    held = joint_proxy.run_trial(joint_proxy.proxy_config(0, []), 0, "held", "held")
    assert [event["blur_px"] for event in held["events"]] == [2, 0]
    assert held["sigma"] == held["events"][-1]["sigma"] and math.isnan(held["psnr"])
    assert held["ideal_psf_error"] == pytest.approx(row["ideal_psf_error"])
