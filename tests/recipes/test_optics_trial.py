"""``benchmarks/optics_trial.py``: one optics figure's 4DGAT trial with its schedule overridden."""

import argparse
import math
from pathlib import Path

import pytest

from fgat.app.recipes import optics_trial

ROOT = Path(__file__).resolve().parents[2]


def trial_args(**overrides) -> argparse.Namespace:
    fields = dict.fromkeys(
        ("amplitude", "depth_chunk", "tolerance", "parameter_tolerance", "blur_px", "blur_events")
    )
    fields.update(figure="figS7", quick=True, seed=0, event_psnr=True, device="cpu")
    fields.update(start=None, every=None, steps=None, max_steps=None)
    return argparse.Namespace(**{**fields, **overrides})


@pytest.mark.slow
def test_trial_runs_the_schedule_it_is_given_and_scores_every_event(monkeypatch):
    """Fig. S7's CPU recipe with ``--start 10 --every 10 --steps 2 --max-steps 40``: events
    after steps 20, 30 and 40 (the first one ``every`` steps after ``start``) of two inner steps
    each; each event's PSF error below the ideal optics' (1.10 on this scene:
    tests/test_jpgm_basin.py); its PSNR that of the final scores after the last event (the
    same volume, scored on another path), and its registered PSNR reported with a shift inside
    the window searched."""
    monkeypatch.chdir(ROOT)
    args = trial_args(start=10, every=10, steps=2, max_steps=40)
    result = optics_trial.run_trial(args, optics_trial.resolve_device("cpu"))
    events = result["events"]
    assert [event["step"] for event in events] == [20, 30, 40]
    assert all(event["inner_steps"] == 2 for event in events)
    assert result["steps"] == 40 and result["optics"]["start"] == 10
    assert all(0 < event["psf_error"] < 1.0 for event in events)
    assert result["psf_error"] == pytest.approx(events[-1]["psf_error"])
    times = [event["elapsed_s"] for event in events]
    assert result["scoring_s"] > 0 and times == sorted(times) and times[-1] <= result["total_s"]
    assert events[-1]["psnr"] == pytest.approx(result["psnr"], abs=1e-3)  # the same volume
    for event in events:
        assert math.isfinite(event["psnr"]) and math.isfinite(event["psnr_aligned"])
        assert max(abs(s) for s in event["shift_zyx"]) < 6


@pytest.mark.parametrize("text", ["0", "-3"])
def test_schedule_overrides_must_be_positive(text):
    with pytest.raises(argparse.ArgumentTypeError, match="positive number of steps"):
        optics_trial.positive(text)
