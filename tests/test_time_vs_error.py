"""``benchmarks/time_vs_error.py``: its summary against hand-computed curves, its recipes at the
paper's scale, and the paper's Table S7 times on its plot."""

import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT / "benchmarks"))
import time_vs_error  # noqa: E402


def curve(times, psnrs, sigma=math.nan):
    return time_vs_error.Curve(
        time_s=list(times), psnr=list(psnrs), ssim=[0.0] * len(psnrs), sigma=[sigma] * len(psnrs)
    )


def test_summary_times_ratios_and_crossover():
    curves = {
        "RL": curve([1, 2, 4], [20, 25, 27]),
        "SHB": curve([0.5, 1, 2], [22, 26, 24]),  # peaks at 26 dB after 1 s
        "3DGAT": curve([3, 6], [26.5, 28]),  # the best of the three: 28 dB
        "4DGAT": curve([3, 6, 9, 12], [20, 27, 29, 35], sigma=0.1),
    }
    summary = time_vs_error.summarize(curves)
    rows = {row["method"]: row for row in summary["rows"]}
    assert summary["shb_peak_psnr"] == 26
    assert rows["RL"]["time_to_shb_peak_s"] == 4 and rows["RL"]["ratio_to_shb"] == 4
    assert rows["3DGAT"]["ratio_to_shb"] == 3 and rows["4DGAT"]["ratio_to_shb"] == 6
    assert summary["crossover_psnr"] == 28 and summary["crossover_s"] == 9
    assert rows["4DGAT"]["final_sigma"] == 0.1 and rows["4DGAT"]["best_psnr"] == 35
    curves["4DGAT"] = curve([3, 6], [20, 27])
    assert math.isnan(time_vs_error.summarize(curves)["crossover_s"])


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
