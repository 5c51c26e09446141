"""Modal profiles eta^b, eta^s of Tables S2-S3 (Eq. S48) at the paper's optics on a CPU, one
modelling choice changed at a time.

The full analysis at the paper's scale (configs/crossinfo_paper.yaml) needs about 28 GB. The
profiles alone need much less: for beads whose images do not overlap, the cross-information is
a sum over the beads of each bead's own term, which depends on its depth only
(:func:`fgat.optics.crossinfo.bead_cross_information`: one Gaussian bead per plane, the PSF
stack's Jacobian without the volume or the operator). ``cpu_full`` and ``cpu`` check it against
the full cross-information of the CPU scene (configs/crossinfo.yaml); ``cpu_11_planes`` checks
that 11 planes over the same depth range give the same profile as 31. The ``paper*`` settings
use configs/crossinfo_paper.yaml's optics (20x/0.45, aperture disk, 1-wave aberrations, seed 0)
on ``--planes`` planes over its depth range, each with one choice changed:

- ``paper``: as is (-75..75 um); ``paper_21_planes`` on 21 planes, to check ``--planes``;
- ``paper_depth_45um``: the CPU scene's depth range, -22.5..22.5 um;
- ``paper_amplitude_A``: aberrations uniform in [-A, A] waves (A = 0.1 as the CPU scene, 0.3,
  0.5) instead of [-1, 1];
- ``paper_pupil_disk``: the Zernike unit disk on the objective pupil (system 20x/0.45).

Each setting takes 20 s (CPU scene) to 3 min (paper optics, 11 planes) on 2 cores; ``--settings``
runs some of them and merges them into an existing ``--out``.

    python benchmarks/crossinfo_profile.py [--settings cpu,paper,...] [--planes 11]
        [--out benchmarks/results/crossinfo_profile.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from fgat.app.crossinfo_tables import CrossInfoConfig, analysis_scene
from fgat.app.recipes.benchmark import write_json
from fgat.optics.crossinfo import bead_cross_information, cross_information, modal_profiles
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.optics.zernike import zernike_family
from fgat.sim.simulation import true_optics

ROOT = Path(__file__).resolve().parents[1]
PAPER_ABERRATIONS = {"terms": 17, "intercept_range": 2.0, "slope_range": 1.5}
SETTINGS = {
    # name: (config, scene changes, planes over the depth range (None: the config's grid,
    # "planes": --planes), full Jacobian)
    "cpu_full": ("crossinfo.yaml", {}, None, True),
    "cpu": ("crossinfo.yaml", {}, None, False),
    "cpu_11_planes": ("crossinfo.yaml", {"depths_um": "-22.5:22.5:11"}, None, False),
    "paper": ("crossinfo_paper.yaml", {}, "planes", False),
    "paper_21_planes": ("crossinfo_paper.yaml", {}, 21, False),
    "paper_depth_45um": ("crossinfo_paper.yaml", {"depths_um": (-22.5, 22.5)}, "planes", False),
    **{
        f"paper_amplitude_{amplitude:g}": (
            "crossinfo_paper.yaml",
            {"aberrations": {**PAPER_ABERRATIONS, "amplitude": amplitude}},
            "planes",
            False,
        )
        for amplitude in (0.1, 0.3, 0.5)
    },
    "paper_pupil_disk": ("crossinfo_paper.yaml", {"system": "20x/0.45"}, "planes", False),
}
"""The settings: each the CPU scene or the paper's optics with one choice changed."""
PAPER = {"eta_b_11": 0.0795, "median_eta_b": 0.2472, "top5_b": "10, 8, 19, 6, 5"}
"""Note S5.2's numbers (Table S2)."""


def scene(name: str, planes: int) -> tuple[CrossInfoConfig, dict]:
    """The analysis config of setting ``name`` with its scene changed, its system a path in the
    repository when it names one, and paper settings on ``planes`` planes over their range."""
    source, changes, sampled, _ = SETTINGS[name]
    config = CrossInfoConfig.from_yaml(ROOT / "configs" / source)
    values = {**config.scene, **changes}
    if sampled:
        default = parse_depths(config.scene["depths_um"])
        low, high = values["depths_um"] if "depths_um" in changes else (default[0], default[-1])
        count = planes if sampled == "planes" else sampled
        values["depths_um"] = f"{low:g}:{high:g}:{count}"
    system = ROOT / str(values["system"])
    if system.is_file():
        values["system"] = str(system)
    return dataclasses.replace(config, scene=values), values


def profile(name: str, planes: int) -> dict:
    """The modal profiles of setting ``name``: eta^b, eta^s per Noll index, eta_11^b, the
    median eta^b, the rank of j = 11, the top 5 of Table S2 and ||C_s||_F / ||C_b||_F."""
    config, values = scene(name, planes)
    full = SETTINGS[name][3]
    simulation = config.simulation()
    start = time.perf_counter()
    if full:
        jpgm, volume = analysis_scene(simulation)
        cross = cross_information(jpgm, volume).C
    else:
        system = load_system(simulation.system)
        spec = OpticsSpec(
            system,
            tuple(parse_depths(simulation.depths_um)),
            None,
            **true_optics(simulation, system.n_lenslets),
        )
        jpgm = spec.jpgm(dtype=torch.float64)
        sigma = float(simulation.phantom.get("sigma", 1.0))
        cross = bead_cross_information(jpgm, sigma_px=sigma)
    seconds = time.perf_counter() - start
    eta_b, eta_s = (eta.cpu().numpy() for eta in modal_profiles(cross))
    indices = list(jpgm.zernike_indices)
    k = indices.index(11)
    half = cross.shape[1] // 2
    order = np.argsort(-eta_b, kind="stable")
    return {
        "setting": name,
        "method": "full Jacobian" if full else "isolated beads",
        "system": load_system(simulation.system).name,
        "depths_um": values["depths_um"],
        "amplitude_waves": float(values["aberrations"]["amplitude"]),
        "eta_b_11": float(eta_b[k]),
        "median_eta_b": float(np.median(eta_b)),
        "rank_11": int((eta_b > eta_b[k]).sum()) + 1,
        "top5_b": ", ".join(str(indices[i]) for i in order[:5]),
        "frobenius_ratio_s_over_b": float(cross[:, half:].norm() / cross[:, :half].norm()),
        "seconds": seconds,
        "eta_b": dict(zip(map(str, indices), eta_b.tolist())),
        "eta_s": dict(zip(map(str, indices), eta_s.tolist())),
    }


def tables(results: dict) -> dict:
    """``summary``: one row per setting (and the paper's); ``eta_b``: one row per Noll index,
    a column per setting."""
    summary = [{"setting": "paper (Table S2)", **PAPER}]
    summary += [
        {
            key: row[key]
            for key in (
                "setting",
                "method",
                "system",
                "depths_um",
                "amplitude_waves",
                "eta_b_11",
                "median_eta_b",
                "rank_11",
                "top5_b",
                "seconds",
            )
        }
        for row in results.values()
    ]
    first = next(iter(results.values()))
    modes = [
        {
            "noll": int(j),
            "family": zernike_family(int(j)),
            **{name: row["eta_b"][j] for name, row in results.items()},
        }
        for j in first["eta_b"]
    ]
    return {"summary": summary, "eta_b_by_mode": modes}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated names")
    parser.add_argument("--planes", type=int, default=11, help="planes of the paper settings")
    parser.add_argument("--out", default=str(ROOT / "benchmarks/results/crossinfo_profile.json"))
    args = parser.parse_args(argv)
    names = [name.strip() for name in args.settings.split(",") if name.strip()]
    unknown = sorted(set(names) - set(SETTINGS))
    if unknown:
        parser.error(f"unknown settings {unknown}; choose from {list(SETTINGS)}")
    out = Path(args.out)
    results = json.loads(out.read_text())["results"] if out.is_file() else {}
    for name in names:
        command = shlex.join(["python", *sys.argv])
        results[name] = {**profile(name, args.planes), "command": command}
        row = results[name]
        print(
            f"{name:<22} eta_11^b {row['eta_b_11']:.4f}  median {row['median_eta_b']:.4f}  "
            f"rank {row['rank_11']:>2}  top5 {row['top5_b']}  ({row['seconds']:.0f} s)"
        )
    ordered = {name: results[name] for name in SETTINGS if name in results}
    write_json(out, {"planes": args.planes, **tables(ordered), "results": ordered})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
