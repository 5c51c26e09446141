"""JPGM from zero against the true volume: does the estimate reach the true coefficients?

The controlled half of the large-aberration question. Fig. S6's quick scene (small system,
beads) with all 17 Zernike terms drawn from ``[-A, A]`` waves; the volume is the truth, scaled
by least squares to the measurement, and held fixed; the Zernike coefficients start at zero and
take ``--steps`` Adam updates (the recipe's learning rate, L1 data loss), either plainly or
coarse to fine (``optics.blur_px``: four equal stages at 4, 2, 1 and 0 px of Gaussian blur on
the views). Prints the data loss and sigma = ||c - c_gt|| / ||c_gt|| after every stage and
writes JSON.

    python benchmarks/jpgm_basin.py [--amplitude 1.0] [--seed 0] [--steps 400]
        [--out benchmarks/results/jpgm_basin.json]

``--figure figS6|figS7 [--paper] [--volume truth|seed]``: the same question on a recipe's scene
and optics instead (``benchmarks/time_vs_error.py``'s beads with the recipe's aberrations, and
for Fig. S7 its lenslet shifts; its estimated groups, learning rates and blur levels; the CPU
scale, or the paper's with ``--paper``), coarse to fine only, ``--steps`` split evenly over the
recipe's blur levels; each stage also reports the PSF stack's relative error to the truth and
the largest intercept and slope errors. ``--volume seed`` holds the volume the static stage
starts from instead of the truth (the Gaussians seeded from SHB under the ideal optics,
rendered): how far the optics move against a volume that was fitted to the wrong PSF.
"""

from __future__ import annotations

import argparse
import time

import torch

from fgat.app.recipes.benchmark import static_engine, write_json
from fgat.app.recipes.time_vs_error import case_scene
from fgat.gaussians.densify import Densification
from fgat.optics.psf import JPGM
from fgat.recon import StaticReconstruction, StaticSettings, names, phantom_scene
from fgat.recon.estimation import OpticsEstimation, run_event
from fgat.recon.optics_report import optics_errors
from fgat.sim.simulation import SimulationConfig

BEADS = {"kind": "beads", "n_beads": 40, "sigma": 1.0, "min_spacing": 6.0, "margin": 3.0}
STAGES_PX = (4.0, 2.0, 1.0, 0.0)


def fixed_truth(engine: StaticReconstruction, truth_psf: torch.Tensor) -> torch.Tensor:
    """The true volume on the engine's padded grid, scaled by least squares to the measurement
    under the true PSF."""
    operator = engine.fit_scene.operator(truth_psf, None)
    truth = operator.pad(torch.as_tensor(engine.scene.truth, dtype=torch.float32))
    with torch.no_grad():
        prediction = operator.forward(truth)
        scale = (prediction * engine.measurement).sum() / prediction.square().sum()
    return truth * scale


def fixed_volume_event(
    engine: StaticReconstruction,
    jpgm: JPGM,
    volume: torch.Tensor,
    schedule: OpticsEstimation,
    optimizer: torch.optim.Optimizer,
    blur_px: float,
) -> dict:
    """One JPGM event (:func:`~fgat.recon.estimation.run_event`) of ``schedule.steps`` updates
    of ``jpgm`` against the volume ``(Z, Y', X')`` held fixed, through ``engine``'s forward model,
    the views blurred by ``blur_px`` pixels."""
    return run_event(
        jpgm,
        volume,
        engine.measurement,
        schedule,
        optimizer,
        operator=lambda psf: engine.fit_scene.operator(psf, None),
        blur_px=blur_px,
    )


def run(amplitude: float, seed: int, steps: int, blurred: bool) -> list[dict]:
    simulation = SimulationConfig(
        phantom=BEADS,
        aberrations={"amplitude": amplitude},
        photons=10000,
        background=100,
        seed=seed,
    )
    scene = phantom_scene(simulation, psf="ideal")
    optics = OpticsEstimation(estimate="zernike", identifiability=False)
    engine = StaticReconstruction(
        scene, StaticSettings(init_iterations=30), Densification(enabled=False), optics
    )
    jpgm = engine.jpgm
    truth_jpgm = scene.truth_optics.jpgm(zernike_indices=jpgm.zernike_indices)
    truth = truth_jpgm.zernike_coefficients.detach()
    with torch.no_grad():
        volume = fixed_truth(engine, truth_jpgm())
    optimizer = optics.optimizer(jpgm)
    stages = STAGES_PX if blurred else (0.0,)
    rows, start = [], time.perf_counter()
    for blur_px in stages:
        schedule = OpticsEstimation(
            estimate="zernike", steps=steps // len(stages), identifiability=False
        )
        result = fixed_volume_event(engine, jpgm, volume, schedule, optimizer, blur_px)
        sigma = float((jpgm.zernike_coefficients.detach() - truth).norm() / truth.norm())
        rows.append(
            {
                "blurred": blurred,
                "blur_px": blur_px,
                "loss_before": result["loss_before"],
                "loss_after": result["loss_after"],
                "sigma": sigma,
                "elapsed_s": time.perf_counter() - start,
            }
        )
        print(
            f"{'coarse to fine' if blurred else 'plain':>14} blur {blur_px:3.0f} px: loss "
            f"{result['loss_before']:.4f} -> {result['loss_after']:.4f}, sigma {sigma:.3f} "
            f"({rows[-1]['elapsed_s']:.0f} s)",
            flush=True,
        )
    return rows


def recipe_run(figure: str, paper: bool, seed: int, steps: int, held: str = "truth") -> list[dict]:
    """Coarse-to-fine JPGM on ``figure``'s recipe scene (beads) against its true volume (``held``
    ``"truth"``) or the static stage's starting volume (``"seed"``), from the recipe's starting
    optics, ``steps`` updates split over the recipe's blur levels."""
    scene, config = case_scene("beads", "joint" if figure == "figS7" else "aberrated", seed, paper)
    model = config["model"]["init_args"]
    recipe = {**model["optics"], "identifiability": False}
    engine = static_engine(scene, model, recipe, config["trainer"]["max_steps"])
    jpgm, truth_psf = engine.jpgm, engine.true_psf
    with torch.no_grad():
        volume = fixed_truth(engine, truth_psf) if held == "truth" else engine.grid_volume()
    levels = tuple(recipe["blur_px"]) or (0.0,)
    stage = OpticsEstimation(  # every update runs: no plateau stop
        **{**recipe, "blur_px": (), "tolerance": 0.0, "steps": max(1, steps // len(levels))}
    )
    optimizer = stage.optimizer(jpgm)
    rows, start = [], time.perf_counter()

    def report(blur_px: float | None, result: dict) -> None:
        with torch.no_grad():
            errors = optics_errors(jpgm, engine.true_parameters(), jpgm(), truth_psf)
        row = {
            "figure": figure,
            "volume": held,
            "blur_px": blur_px,
            **result,
            "sigma": errors[names.ZERNIKE_RESIDUAL],
            "psf_error": errors[names.PSF_ERROR],
            "intercept_error_px": errors[names.SHIFT_ERRORS[0]],
            "slope_error_px": errors[names.SHIFT_ERRORS[2]],
            "elapsed_s": time.perf_counter() - start,
        }
        rows.append(row)
        label = "start" if blur_px is None else f"blur {blur_px:3.0f} px, {row['steps']} steps"
        loss = f"loss {row['loss_before']:.4f} -> {row['loss_after']:.4f}, " if result else ""
        print(
            f"{figure} {label}: {loss}sigma {row['sigma']:.3f}, PSF error {row['psf_error']:.3f}, "
            f"intercepts {row['intercept_error_px']:.2f} px, slopes {row['slope_error_px']:.2f} px "
            f"({row['elapsed_s']:.0f} s)",
            flush=True,
        )

    report(None, {})
    for blur_px in levels:
        result = fixed_volume_event(engine, jpgm, volume, stage, optimizer, blur_px)
        keys = ("steps", "loss_before", "loss_after")
        report(blur_px, {key: result[key] for key in keys})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--amplitude", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--figure", choices=("figS6", "figS7"), help="a recipe's scene instead")
    parser.add_argument("--paper", action="store_true", help="with --figure: the paper's scale")
    parser.add_argument(
        "--volume",
        choices=("truth", "seed"),
        default="truth",
        help="with --figure: the volume held fixed",
    )
    parser.add_argument("--out", default="benchmarks/results/jpgm_basin.json")
    args = parser.parse_args()
    if args.figure is None and (args.paper or args.volume != "truth"):
        parser.error("--paper and --volume need --figure figS6 or figS7")
    if args.figure is not None:
        rows = recipe_run(args.figure, args.paper, args.seed, args.steps, args.volume)
    else:
        rows = [
            row
            for blurred in (False, True)
            for row in run(args.amplitude, args.seed, args.steps, blurred)
        ]
    write_json(args.out, {**vars(args), "rows": rows})
