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
"""

from __future__ import annotations

import argparse
import time

import torch
from common import write_json

from fgat.gaussians.densify import Densification
from fgat.optics.estimation import OpticsEstimation, run_event
from fgat.reconstruction import StaticReconstruction, StaticSettings, phantom_scene
from fgat.simulation import SimulationConfig

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
        result = run_event(
            jpgm,
            volume,
            engine.measurement,
            schedule,
            optimizer,
            operator=lambda psf: engine.fit_scene.operator(psf, None),
            blur_px=blur_px,
        )
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


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--amplitude", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--out", default="benchmarks/results/jpgm_basin.json")
    args = parser.parse_args()
    rows = [
        row
        for blurred in (False, True)
        for row in run(args.amplitude, args.seed, args.steps, blurred)
    ]
    write_json(args.out, {**vars(args), "rows": rows})


if __name__ == "__main__":
    main()
