"""``benchmarks/time_vs_error.py``: its summary against hand-computed curves, its recipes at the
paper's scale, and the paper's Table S7 times on its plot."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fgat.app.recipes import time_vs_error
from fgat.recon.metrics import compare_volumes, registered_psnr

ROOT = Path(__file__).resolve().parents[2]


def curve(times, psnrs, sigma=math.nan, psf_error=math.nan, registered=None):
    count = len(psnrs)
    return time_vs_error.Curve(
        time_s=list(times),
        psnr=list(psnrs),
        ssim=[0.0] * count,
        sigma=[sigma] * count,
        psf_error=[psf_error] * count,
        psnr_registered=list(registered) if registered else [math.nan] * count,
    )


def test_summary_times_ratios_and_crossover():
    curves = {
        "RL": curve([1, 2, 4], [20, 25, 27]),
        "SHB": curve([0.5, 1, 2], [22, 26, 24]),  # peaks at 26 dB after 1 s
        "3DGAT": curve([3, 6], [26.5, 28]),  # the best of the three: 28 dB
        "4DGAT": curve([3, 6, 9, 12], [20, 27, 29, 35], sigma=0.1, psf_error=0.3),
    }
    summary = time_vs_error.summarize(curves)
    rows = {row["method"]: row for row in summary["rows"]}
    assert summary["shb_peak_psnr"] == 26
    assert rows["RL"]["time_to_shb_peak_s"] == 4 and rows["RL"]["ratio_to_shb"] == 4
    assert rows["3DGAT"]["ratio_to_shb"] == 3 and rows["4DGAT"]["ratio_to_shb"] == 6
    assert summary["crossover_psnr"] == 28 and summary["crossover_s"] == 9
    assert rows["4DGAT"]["final_sigma"] == 0.1 and rows["4DGAT"]["best_psnr"] == 35
    assert rows["4DGAT"]["final_psf_error"] == 0.3 and math.isnan(rows["RL"]["final_psf_error"])
    curves["4DGAT"] = curve([3, 6], [20, 27])
    assert math.isnan(time_vs_error.summarize(curves)["crossover_s"])


def test_registered_summary_is_the_same_arithmetic_on_the_registered_scores():
    """Times to SHB's best, ratios and crossover on ``psnr_registered``: here the registered
    scores reorder the methods (3DGAT's frame is off, so registration lifts it most), and NaN
    samples (a volume that did not register) never count as reached."""
    curves = {
        "RL": curve([1, 2, 4], [20, 25, 27], registered=[21, 26, 28]),
        "SHB": curve([0.5, 1, 2], [22, 26, 24], registered=[23, math.nan, 27]),  # best 27 at 2 s
        "3DGAT": curve([3, 6], [26.5, 28], registered=[29, 31]),
        "4DGAT": curve([3, 6, 9, 12], [20, 27, 29, 35], registered=[math.nan, 30, 31.5, 36]),
    }
    summary = time_vs_error.summarize(curves)
    rows = {row["method"]: row for row in summary["rows"]}
    assert summary["shb_peak_psnr"] == 26 and summary["shb_peak_psnr_registered"] == 27
    assert rows["RL"]["time_to_shb_peak_registered_s"] == 4
    assert rows["RL"]["ratio_to_shb_registered"] == 2
    assert rows["3DGAT"]["time_to_shb_peak_registered_s"] == 3
    assert rows["4DGAT"]["ratio_to_shb_registered"] == 3
    assert rows["3DGAT"]["best_psnr_registered"] == 31 and rows["4DGAT"]["best_psnr"] == 35
    assert summary["crossover_psnr"] == 28 and summary["crossover_s"] == 9
    assert summary["crossover_psnr_registered"] == 31
    assert summary["crossover_registered_s"] == 9  # 31.5 > 31 at 9 s
    unregistered = {m: curve(c.time_s, c.psnr) for m, c in curves.items()}
    plain = time_vs_error.summarize(unregistered)
    assert math.isnan(plain["crossover_registered_s"]) and plain["crossover_s"] == 9


def test_samples_are_registered_to_the_truth_up_to_a_size(monkeypatch):
    """A displaced sample scores its raw PSNR and, registered, what
    ``fgat.recon.metrics.registered_psnr`` gives it (close to the undisplaced volume's); above the
    size limit only raw."""
    g = np.random.default_rng(3)
    truth = np.zeros((16, 24, 24))
    truth[3:9, 8:16, 6:14] = g.random((6, 8, 8))
    estimate = truth + 0.01 * g.random(truth.shape)
    displaced = np.roll(estimate, (1, -2, 1), axis=(0, 1, 2))
    scores = time_vs_error.Curve()
    scores.sample(1.0, displaced, torch.as_tensor(truth))
    undisplaced = compare_volumes(torch.as_tensor(estimate), torch.as_tensor(truth))["psnr"]
    assert scores.psnr[0] < undisplaced - 10
    assert scores.psnr_registered[0] == registered_psnr(displaced, truth)[0]
    assert scores.psnr_registered[0] == pytest.approx(undisplaced, abs=1.5)
    monkeypatch.setattr(time_vs_error, "REGISTERED_SAMPLE_VOXELS", truth.size - 1)
    scores.sample(2.0, displaced, torch.as_tensor(truth))
    assert math.isnan(scores.psnr_registered[1]) and scores.psnr[1] == scores.psnr[0]


def test_samples_a_run_about_32_times():
    assert [time_vs_error.sample_every(n) for n in (200, 800, 1600, 2000)] == [25, 25, 50, 62]


@pytest.mark.parametrize("figure", ["figS6", "figS7"])
def test_paper_scale_is_the_papers_system_grid_and_schedule(monkeypatch, figure):
    """``--paper``: Table S6's 20x/0.45 at 300 x 300 x 101 with Table S7's 2,000 steps and
    JPGM events every 50 steps from step 200, of 100 inner steps, coarse to fine (4, 2, 1, 0 px, six
    events each); the CPU scale is smaller, its events plain."""
    monkeypatch.chdir(ROOT)
    paper = time_vs_error.recipe_config(figure, paper=True)
    quick = time_vs_error.recipe_config(figure)
    simulation = paper["data"]["init_args"]["simulation"]
    assert simulation["system"] == "20x/0.45" and simulation["view_size"] == 300
    assert simulation["depths_um"] == "-75:75:101"
    optics = paper["model"]["init_args"]["optics"]
    assert (optics["start"], optics["every"], optics["steps"]) == (200, 50, 100)
    assert optics["estimate"] == {"figS6": "zernike", "figS7": "joint"}[figure]
    assert paper["trainer"]["max_steps"] == 2000
    assert (optics["blur_px"], optics["blur_events"]) == ([4, 2, 1, 0], 6)
    assert quick["data"]["init_args"]["simulation"]["view_size"] < 300
    assert quick["model"]["init_args"]["optics"]["blur_px"] == []


def test_plot_marks_the_papers_times(tmp_path, monkeypatch):
    """At the paper's scale each method with a Table S7 time gets a dashed line there, in its
    curve's colour; without marks there are none."""
    figures = []
    monkeypatch.setattr(time_vs_error, "save_figure", lambda figure, path: figures.append(figure))
    curves = {m: curve([1, 10], [20, 30]) for m in ("RL", "SHB", "3DGAT", "4DGAT")}
    case = {
        "phantom": "beads",
        "settings": "aberrated",
        "curves": {m: vars(c) for m, c in curves.items()},
        "summary": time_vs_error.summarize(curves),
    }
    time_vs_error.plot([case], tmp_path / "a.png", time_vs_error.TABLE_S7_S)
    time_vs_error.plot([case], tmp_path / "b.png")
    marked, plain = (figure.axes[0] for figure in figures)
    lines = {line.get_label(): line for line in marked.get_lines()}
    for method, seconds in {"3DGAT": 140.0, "4DGAT": 2400.0}.items():
        mark = lines[f"{method}, paper (Table S7)"]
        assert list(mark.get_xdata()) == [seconds, seconds]
        assert mark.get_color() == lines[method].get_color()
    assert not any("paper" in line.get_label() for line in plain.get_lines())


def result(tmp_path, name, scenes, **meta):
    """A ``time_vs_error.json`` in ``tmp_path/name`` holding ``scenes`` (phantom, settings)."""
    curves = {m: curve([1, 2], [20, 22]) for m in ("RL", "SHB", "3DGAT")}
    curves["4DGAT"] = curve([1, 4], [18, 25], sigma=0.2)
    cases = [
        {
            "phantom": phantom,
            "settings": settings,
            "curves": {m: vars(c) for m, c in curves.items()},
            "summary": time_vs_error.summarize(curves),
        }
        for phantom, settings in scenes
    ]
    fields = dict(device_name="GPU", scale="paper", seed=0, iterations=500, static_steps=None)
    path = tmp_path / name / "time_vs_error.json"
    path.parent.mkdir()
    path.write_text(json.dumps({**fields, **meta, "paper_times_s": None, "cases": cases}))
    return path


def test_merge_writes_earlier_results_as_one(tmp_path, monkeypatch, capsys):
    """``--merge``: the cases of separate runs, in order, into one JSON / CSV / plot, with a
    panel for each scene and none for a phantom-setting pair no run holds."""
    first = result(tmp_path, "a", [("beads", "joint")])
    second = result(tmp_path, "b", [("line_sphere", "joint"), ("line_sphere", "ideal optics")])
    figures = []
    monkeypatch.setattr(time_vs_error, "save_figure", lambda figure, path: figures.append(figure))
    out = tmp_path / "merged"
    argv = ["time_vs_error.py", "--merge", str(first), str(second), "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    time_vs_error.main()
    merged = json.loads((out / "time_vs_error.json").read_text())
    scenes = [(case["phantom"], case["settings"]) for case in merged["cases"]]
    assert scenes == [("beads", "joint"), ("line_sphere", "joint"), ("line_sphere", "ideal optics")]
    assert merged["device_name"] == "GPU" and merged["seed"] == 0
    rows = (out / "time_vs_error.csv").read_text().splitlines()
    assert len(rows) == 1 + 3 * 4 * 2  # header, 3 scenes x 4 methods x 2 samples
    titles = sorted(axis.get_title() for axis in figures[0].axes if axis.get_visible())
    assert titles == ["beads, joint", "line_sphere, ideal optics", "line_sphere, joint"]
    assert "line_sphere, joint: SHB peak 22.00 dB" in capsys.readouterr().out


@pytest.mark.parametrize(
    "meta, scenes, message",
    [
        ({"seed": 1}, [("line_sphere", "joint")], "seed is 1 but"),
        ({"device_name": "CPU"}, [("line_sphere", "joint")], "device_name is 'CPU' but"),
        ({}, [("beads", "joint")], "('beads', 'joint') is in"),
    ],
)
def test_merge_refuses_unlike_results(tmp_path, meta, scenes, message):
    first = result(tmp_path, "a", [("beads", "joint")])
    second = result(tmp_path, "b", scenes, **meta)
    with pytest.raises(ValueError, match="b/time_vs_error.json") as error:
        time_vs_error.merge_results([first, second])
    assert message in str(error.value)


def test_merge_refuses_a_file_that_is_not_a_result(tmp_path, monkeypatch, capsys):
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"cases": []}))
    with pytest.raises(ValueError, match="other.json: no device_name, scale, seed"):
        time_vs_error.merge_results([other])
    first = result(tmp_path, "a", [("beads", "joint")])
    argv = ["time_vs_error.py", "--merge", str(first), "--out", str(first.parent)]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit):
        time_vs_error.main()
    assert "holds time_vs_error.json, one of the results to merge" in capsys.readouterr().err
    assert json.loads(first.read_text())["cases"][0]["phantom"] == "beads"


@pytest.mark.slow
def test_static_curves_sample_the_estimated_psfs_error(monkeypatch):
    """4DGAT's samples carry the relative error of its current PSF stack, equal to a float64
    ``||h - h_gt|| / ||h_gt||`` of the engine's PSFs; 3DGAT, whose optics are not estimated,
    carries none."""
    monkeypatch.chdir(ROOT)
    scene, config = time_vs_error.case_scene("beads", "joint", seed=0)
    model = config["model"]["init_args"]
    truth = torch.as_tensor(scene.truth, dtype=torch.float64)
    ideal, _ = time_vs_error.run_static(scene, model, 25, "none", truth)
    assert len(ideal.psf_error) == 2 and all(math.isnan(e) for e in ideal.psf_error)
    curve, engine = time_vs_error.run_static(scene, model, 75, "joint", truth)
    estimate, true = (t.detach().double().numpy() for t in (engine.psf, engine.true_psf))
    expected = np.linalg.norm(estimate - true) / np.linalg.norm(true)
    assert len(curve.psf_error) == 4 and curve.psf_error[-1] == pytest.approx(expected, rel=1e-5)
    assert curve.psf_error[-1] < curve.psf_error[0]


@pytest.mark.parametrize(
    "argv, steps",
    [([], 1600), (["--quick"], 800), (["--paper"], None), (["--paper", "--steps", "4000"], 4000)],
)
def test_steps_reach_every_case(monkeypatch, argv, steps):
    """``--steps`` replaces the scale's static steps (``None``: the paper recipe's own)."""
    seen = []

    def run_case(phantom, settings, seed, iterations, steps, *rest):
        seen.append(steps)
        return {"phantom": phantom, "settings": settings}

    monkeypatch.setattr(time_vs_error, "run_case", run_case)
    monkeypatch.setattr(time_vs_error, "print_case", lambda case: None)
    monkeypatch.setattr(time_vs_error, "write_results", lambda *args: None)
    command = ["time_vs_error.py", *argv, "--phantom", "beads", "--settings", "joint"]
    monkeypatch.setattr(sys, "argv", [*command, "--device", "cpu"])
    time_vs_error.main()
    assert seen == [steps]
