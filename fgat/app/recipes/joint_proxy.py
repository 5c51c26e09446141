"""Fig. S7's joint estimation on a CPU proxy of the paper's scale: where does it go wrong?

The paper-scale Fig. S7 recipe (20x/0.45, all 17 Zernike terms uniform in +-1 wave, random
lenslet intercepts and slopes, beads, the coarse-to-fine JPGM events of
``configs/base/optics_paper.yaml``) on a smaller field, a coarser depth sampling and a shorter
schedule (``configs/base/optics_proxy.yaml``), so that one joint trial runs in minutes on 2 CPU
cores. Per seed:

* ``SHB``: the static stage's baseline (its ``baseline_iterations``, the ideal PSF);
* ``3DGAT``: the static stage with the ideal PSF held fixed;
* ``4DGAT``: the static stage estimating the optics as the recipe sets it (``--set`` overrides
  make a variant, named by ``--label``);
* ``held``: the recipe's JPGM schedule (the same updates and blur levels) against the true
  volume, held fixed: the optics alone.

After every JPGM event (``held``: every blur level) it records the data loss before and after the
event, sigma = ``||c - c_gt|| / ||c_gt||``, the PSF stack's relative error, the largest intercept
and slope errors without the part a moved scene explains (pixels), and the volume's PSNR as it is
and registered to the truth. The summary has one row per seed and method, and the ideal PSF's
error beside each.

    python benchmarks/joint_proxy.py [--seeds 0-7] [--methods 3DGAT,4DGAT,held]
        [--set optics.blurred_estimate=zernike ...] [--label NAME]
        [--out benchmarks/results/joint_proxy]

Each trial is written to ``OUT/trials/`` under a name holding the digest of what produced it
(its resolved config, method and schedule): a trial already there under the same digest is read
instead of run again, so a killed run resumes and a changed config runs afresh. ``OUT`` gets
``joint_proxy.json`` (every row with its events, and per 4DGAT row its margin over the best of
SHB and 3DGAT, its PSF error over the ideal PSF's and whether it ends above SHB),
``joint_proxy.csv`` (the rows), ``joint_proxy_verdicts.csv`` and ``joint_proxy.png`` (PSNR and
sigma along each 4DGAT run). ``--merge DIR ...`` runs nothing and summarises the trials of
earlier ``--out`` folders into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from fgat.app.fingerprint import fingerprint
from fgat.app.lightning_cli import resolved_config
from fgat.app.recipes.benchmark import static_engine, write_json, write_text
from fgat.app.recipes.jpgm_basin import fixed_truth, fixed_volume_event
from fgat.app.recipes.optics import config_args, recipe_configs
from fgat.app.recipes.optics_trial import aligned_psnr, volume_psnr
from fgat.app.recipes.time_vs_error import best
from fgat.io.files import write_csv
from fgat.recon import StaticReconstruction, names, phantom_scene
from fgat.recon.estimation import OpticsEstimation, psf_errors
from fgat.recon.optics_report import optics_errors
from fgat.sim.simulation import SimulationConfig
from fgat.viz.figures import pyplot, save_figure

PROXY_CONFIG = "configs/base/optics_proxy.yaml"
METHODS = ("3DGAT", "4DGAT", "held")
ROW_FIELDS = (
    "seed",
    "method",
    "label",
    "psnr",
    "psnr_registered",
    "sigma",
    "psf_error",
    "intercept_error_px",
    "slope_error_px",
    "ideal_psf_error",
    "shb_psnr",
    "shb_psnr_registered",
    "wall_s",
)


def proxy_config(seed: int, overrides: list[str]) -> dict:
    """The Fig. S7 recipe at the paper's scale under the proxy's overlay, with ``overrides``
    (``key=value`` of ``model.init_args``, e.g. ``optics.blurred_estimate=zernike``), resolved."""
    options = [f"--model.init_args.{item}" for item in overrides]
    configs = config_args([*recipe_configs("figS7", quick=False), PROXY_CONFIG])
    return resolved_config(["fit", *configs, f"--seed_everything={seed}", *options])


def errors_row(engine: StaticReconstruction, jpgm, psf: torch.Tensor) -> dict:
    """sigma, PSF error and gauge-free shift errors of ``jpgm`` (its stack ``psf``)."""
    errors = optics_errors(jpgm, engine.true_parameters(), psf, engine.true_psf)
    return {
        "sigma": errors[names.ZERNIKE_RESIDUAL],
        "psf_error": errors[names.PSF_ERROR],
        "intercept_error_px": errors[names.SHIFT_ERRORS[1]],
        "slope_error_px": errors[names.SHIFT_ERRORS[3]],
    }


def volume_row(engine: StaticReconstruction) -> dict:
    """The volume's PSNR against the truth, as it is and registered (NaN: does not register)."""
    return {"psnr": volume_psnr(engine), "psnr_registered": aligned_psnr(engine)[0]}


def run_static(engine: StaticReconstruction, steps: int) -> tuple[list[dict], float]:
    """``steps`` static steps of ``engine``; a row after every JPGM event; the seconds spent
    stepping (scoring kept off the clock)."""
    events, elapsed = [], 0.0
    for _ in range(steps):
        start = time.perf_counter()
        result = engine.step()
        elapsed += time.perf_counter() - start
        event = result.events.get("optics")
        if event is not None:
            events.append(
                {
                    "step": engine.steps_done,
                    "elapsed_s": elapsed,
                    "blur_px": event.get("optics/blur_px", 0.0),
                    "loss_before": event["optics/loss_before"],
                    "loss_after": event["optics/loss_after"],
                    "psf_change": event[names.PSF_CHANGE],
                    **errors_row(engine, engine.jpgm, engine.psf),
                    **volume_row(engine),
                }
            )
    return events, elapsed


def run_held(engine: StaticReconstruction, optics: dict) -> tuple[list[dict], float]:
    """The recipe's JPGM updates (events x inner steps, split evenly over its blur levels)
    against the true volume held fixed; a row after every blur level and the seconds spent."""
    schedule = OpticsEstimation(**optics)
    events = sum(schedule.due(step) for step in range(1, engine.total_steps + 1))
    levels = tuple(schedule.blur_px) or (0.0,)
    stage = OpticsEstimation(
        **{
            **optics,
            "blur_px": (),
            "tolerance": 0.0,
            "steps": events * schedule.steps // len(levels),
        }
    )
    jpgm, optimizer = engine.jpgm, stage.optimizer(engine.jpgm)
    with torch.no_grad():
        volume = fixed_truth(engine, engine.true_psf)
    rows, elapsed = [], 0.0
    for blur_px in levels:
        start = time.perf_counter()
        result = fixed_volume_event(engine, jpgm, volume, stage, optimizer, blur_px)
        elapsed += time.perf_counter() - start
        with torch.no_grad():
            psf = jpgm()
        rows.append(
            {
                "step": None,
                "elapsed_s": elapsed,
                "blur_px": blur_px,
                "loss_before": result["loss_before"],
                "loss_after": result["loss_after"],
                **errors_row(engine, jpgm, psf),
            }
        )
    return rows, elapsed


def run_trial(config: dict, seed: int, method: str, label: str) -> dict:
    """One ``method`` trial on the proxy scene of ``seed`` (its resolved ``config``,
    :func:`proxy_config`): its summary row with its events."""
    model, steps = config["model"]["init_args"], int(config["trainer"]["max_steps"])
    simulation = dict(config["data"]["init_args"]["simulation"], seed=seed)
    scene = phantom_scene(SimulationConfig(**simulation), psf=config["data"]["init_args"]["psf"])
    optics = {**model["optics"], "identifiability": False}
    if method == "3DGAT":
        optics["estimate"] = "none"
    start = time.perf_counter()
    engine = static_engine(scene, model, optics, steps)
    seeded = time.perf_counter() - start
    if method == "held":
        events, elapsed = run_held(engine, optics)
    else:
        events, elapsed = run_static(engine, steps)
    with torch.no_grad():
        ideal_error = psf_errors(
            torch.as_tensor(scene.psf), scene.truth_optics.jpgm()(), names.PSF_ERROR
        )[names.PSF_ERROR]
    row = {"seed": seed, "method": method, "label": label if method == "4DGAT" else method}
    if method == "held":
        row.update({"psnr": math.nan, "psnr_registered": math.nan, **events[-1]})
    else:
        row.update(volume_row(engine))
        row.update(errors_row(engine, engine.jpgm, engine.psf) if engine.jpgm else {})
    baseline = engine.baseline_scores
    return {
        **{field: math.nan for field in ROW_FIELDS},
        **{key: value for key, value in row.items() if key in ROW_FIELDS},
        "ideal_psf_error": ideal_error,
        "shb_psnr": baseline.get(names.PSNR + names.SHB, math.nan),
        "shb_psnr_registered": baseline.get(names.PSNR_REGISTERED + names.SHB, math.nan),
        "wall_s": seeded + elapsed,
        "events": events,
    }


def trial_digest(config: dict, method: str) -> str:
    """The digest of what a trial's result depends on: its resolved ``config`` (the settings, not
    the files they came from) and method."""
    return fingerprint({**config, "trial_method": method}).short


def cached_trial(folder: Path, seed: int, method: str, overrides: list[str], label: str) -> dict:
    """The trial's row from ``folder`` when one with the same digest is there, else run and
    written there (atomically)."""
    name = label if method == "4DGAT" else method
    config = proxy_config(seed, overrides)
    path = folder / f"{name}-seed{seed}-{trial_digest(config, method)}.json"
    if path.exists():
        return json.loads(path.read_text())
    row = run_trial(config, seed, method, label)
    write_text(path, json.dumps(row, indent=2))
    return row


def verdicts(rows: list[dict]) -> list[dict]:
    """Per 4DGAT row, the issue's three checks on its seed: ``margin_db``, its PSNR (registered
    where the volume registers) above the best of SHB's and 3DGAT's (each registered or as
    it is, whichever is higher); ``psf_ratio``, its PSF error over the ideal PSF's; and
    ``above_shb``, whether its PSNR ends above SHB's."""
    baselines = {}
    for row in rows:
        if row["method"] != "4DGAT":
            scores = (row["psnr"], row["psnr_registered"], row["shb_psnr"])
            shb = row["shb_psnr_registered"]
            baselines[row["seed"]] = best([baselines.get(row["seed"], math.nan), *scores, shb])
    return [
        {
            "seed": row["seed"],
            "label": row["label"],
            "margin_db": best([row["psnr_registered"], row["psnr"]])
            - baselines.get(row["seed"], math.nan),
            "psf_ratio": row["psf_error"] / row["ideal_psf_error"],
            "above_shb": bool(row["psnr"] > row["shb_psnr"]),
        }
        for row in rows
        if row["method"] == "4DGAT"
    ]


def write_summary(rows: list[dict], out: Path) -> None:
    """``joint_proxy.json`` (rows with their events, and :func:`verdicts`), ``joint_proxy.csv``
    (the rows), ``joint_proxy_verdicts.csv`` and ``joint_proxy.png`` in ``out``."""
    rows = sorted(rows, key=lambda row: (row["seed"], row["method"], row["label"]))
    checks = verdicts(rows)
    write_json(out / "joint_proxy.json", {"verdicts": checks, "rows": rows})
    write_csv(out / "joint_proxy.csv", ROW_FIELDS, rows)
    write_csv(out / "joint_proxy_verdicts.csv", tuple(checks[0]) if checks else (), checks)
    plot(rows, out / "joint_proxy.png")


def plot(rows: list[dict], path: Path) -> None:
    """Volume PSNR (dB) and sigma after every JPGM event of each 4DGAT run, the SHB baseline
    dotted."""
    figure, (left, right) = pyplot().subplots(1, 2, figsize=(11, 4))
    for row in (r for r in rows if r["method"] == "4DGAT"):
        steps = [event["step"] for event in row["events"]]
        label = f"{row['label']} seed {row['seed']}"
        (line,) = left.plot(steps, [e["psnr"] for e in row["events"]], label=label)
        left.axhline(row["shb_psnr"], color=line.get_color(), linestyle=":")
        right.semilogy(steps, [e["sigma"] for e in row["events"]], color=line.get_color())
    left.set(xlabel="static step", ylabel="volume PSNR (dB)", title="dotted: SHB")
    right.set(xlabel="static step", ylabel="sigma = |c - c_gt| / |c_gt|", title="Zernike error")
    if left.lines:
        left.legend(fontsize=7)
    save_figure(figure, path)


def seeds(text: str) -> list[int]:
    """``--seeds``: ``0-7`` or ``0,3,5``."""
    if "-" in text:
        low, high = (int(word) for word in text.split("-"))
        return list(range(low, high + 1))
    return [int(word) for word in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=seeds, default=seeds("0-2"), help="0-7 or 0,3,5")
    parser.add_argument(
        "--methods", default=",".join(METHODS), help=f"comma-separated, of {', '.join(METHODS)}"
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a model.init_args override of the 4DGAT variant (optics.blurred_estimate=zernike)",
    )
    parser.add_argument("--label", default="4DGAT", help="the 4DGAT variant's name in the rows")
    parser.add_argument("--out", default="benchmarks/results/joint_proxy")
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="DIR",
        help="run nothing: summarise every trial in DIR/trials/ (earlier --out folders)",
    )
    args = parser.parse_args()
    out = Path(args.out)
    if args.merge:
        paths = sorted(
            path for folder in args.merge for path in Path(folder, "trials").glob("*.json")
        )
        write_summary([json.loads(path.read_text()) for path in paths], out)
        return
    methods = args.methods.split(",")
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        parser.error(f"--methods: unknown {', '.join(unknown)}; expected some of {METHODS}")
    rows = []
    for seed in args.seeds:
        for method in methods:
            overrides = args.overrides if method == "4DGAT" else []
            rows.append(cached_trial(out / "trials", seed, method, overrides, args.label))
            print(
                ", ".join(
                    f"{key} {rows[-1][key]:.4g}"
                    if isinstance(rows[-1][key], float)
                    else f"{key} {rows[-1][key]}"
                    for key in ROW_FIELDS
                ),
                flush=True,
            )
    write_summary(rows, out)
