"""Time one 4DGAT trial of an optics figure end to end, with sigma after every JPGM event.

The trial is the recipe's static stage (``reproduce/optics.py``'s configs: the paper's scale,
or ``--quick`` the CPU one) run through :class:`~fgat.recon.StaticReconstruction`
without Lightning or MLflow: the simulation and the SHB pre-pass, then every static step with
its JPGM events, then the volume scores. After each event it prints the elapsed seconds, the
normalised Zernike error ``sigma = ||c - c_gt|| / ||c_gt||``, the inner steps run and the time
per inner step; the end-of-fit standard errors (``optics.identifiability``) are left out, as
they are a diagnostic and not part of the reconstruction. Table S6 gives about 30 min per
paper-size Fig. S6 trial.

    python benchmarks/optics_trial.py [--figure figS6] [--quick] [--seed N] [--depth-chunk N]
        [--tolerance T --parameter-tolerance P] [--amplitude A] [--blur-px 4,2,1,0
        --blur-events N] [--start N --every N --steps N] [--max-steps N] [--event-psnr]
        [--out benchmarks/results/optics_trial.json]

``--depth-chunk`` overrides the recipe's ``optics.depth_chunk`` (``auto`` at the paper's scale:
the whole stack's graph on a GPU, smaller chunks only when it runs out of memory; chunks of 16
depths on a CPU); ``--tolerance`` and ``--parameter-tolerance`` turn on the converged-optics
skip; ``--amplitude`` draws the Zernike terms from ``[-A, A]`` waves instead of the recipe's;
``--blur-px`` and ``--blur-events`` set the coarse-to-fine data loss of the JPGM events
(``optics.blur_px``, ``optics.blur_events``: the paper-scale recipes blur by 4, 2 and 1 px for
six events each, then compare sharp views; ``--blur-px 0`` makes every event sharp);
``--start``, ``--every`` and ``--steps`` the JPGM schedule (``optics.start``, ``optics.every``,
``optics.steps``) and ``--max-steps`` the static steps. Each event also reports the PSF stack's
relative error to the truth, and with ``--event-psnr`` the volume's PSNR, as it is and after its
registration to the truth (:func:`fgat.recon.metrics.registered_psnr`; the final volume's is always
reported).
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from fgat._core.devices import resolve_device
from fgat.app.lightning_cli import resolved_config
from fgat.app.recipes.benchmark import static_engine, synchronize, write_json
from fgat.app.recipes.optics import config_args, recipe_configs
from fgat.recon import names, phantom_scene
from fgat.recon.metrics import max_normalize, psnr, registered_psnr
from fgat.sim.simulation import SimulationConfig


def trial_settings(args) -> tuple[dict, dict, dict, int]:
    """The recipe's simulation, model arguments (with the data's ``psf``), optics settings (the
    recipe's estimate, overrides from ``args``) and step count."""
    config = resolved_config(
        [
            "fit",
            *config_args(recipe_configs(args.figure, args.quick)),
            f"--seed_everything={args.seed}",
        ]
    )
    simulation = dict(config["data"]["init_args"]["simulation"], seed=args.seed)
    if args.amplitude is not None:
        simulation["aberrations"] = {**simulation["aberrations"], "amplitude": args.amplitude}
    model = config["model"]["init_args"]
    optics = {**model["optics"], "identifiability": False}
    overrides = ("depth_chunk", "tolerance", "parameter_tolerance", "blur_px", "blur_events")
    for name in (*overrides, "start", "every", "steps"):
        if getattr(args, name) is not None:
            optics[name] = getattr(args, name)
    steps = config["trainer"]["max_steps"] if args.max_steps is None else args.max_steps
    return simulation, {**model, "psf": config["data"]["init_args"]["psf"]}, optics, int(steps)


def volume_psnr(engine) -> float:
    """The volume's PSNR against the truth as :func:`~fgat.recon.metrics.compare_volumes` scores it,
    on the volume's device."""
    truth = torch.as_tensor(engine.scene.truth, device=engine.device)
    return float(psnr(max_normalize(engine.volume()), max_normalize(truth), 1.0))


def aligned_psnr(engine) -> tuple[float, list[float] | None]:
    """The volume's PSNR registered to the truth, and the shift (voxels; None where it does not
    register): without the translation of the scene that the lenslet shifts' gauge leaves open
    (:func:`~fgat.recon.metrics.registered_psnr`)."""
    volume = engine.volume().cpu().double().numpy()
    score, shift = registered_psnr(volume, engine.scene.truth)
    return score, None if shift is None else list(shift)


def run_trial(args, device: torch.device) -> dict:
    """The trial: times of its phases, sigma after every event, final scores. The seconds spent
    scoring the events (``scoring_s``) are kept out of the phases' and the events' times."""
    start = time.perf_counter()
    simulation, model, optics, steps = trial_settings(args)
    scene = phantom_scene(SimulationConfig(**simulation), psf=model["psf"])
    simulated = time.perf_counter()
    engine = static_engine(scene, model, optics, steps, device)
    synchronize(device)
    built = time.perf_counter()
    events, scoring = [], 0.0  # seconds spent scoring the events, kept off the clock
    for step in range(1, steps + 1):
        result = engine.step()
        if "optics" in result.events:
            synchronize(device)
            scored = time.perf_counter()
            elapsed = scored - start - scoring
            event, errors = result.events["optics"], engine.optics_errors()
            raw, aligned, shift = None, None, None
            if args.event_psnr:  # PSNR alone: a paper-size volume's SSIM takes seconds on a CPU
                raw = volume_psnr(engine)
                aligned, shift = aligned_psnr(engine)
            scoring += time.perf_counter() - scored
            events.append(
                {
                    "step": step,
                    "elapsed_s": elapsed,
                    "sigma": errors[names.ZERNIKE_RESIDUAL],
                    "psf_error": errors[names.PSF_ERROR],
                    "psnr": raw,
                    "psnr_aligned": aligned,
                    "shift_zyx": shift,
                    "inner_steps": event["optics/inner_steps"],
                    "jpgm_iter_ms": event["time/jpgm_iter_ms"],
                    "converged": names.OPTICS_CONVERGED in event,
                }
            )
            print(
                f"step {step:5d}  {events[-1]['elapsed_s']:7.1f} s  sigma "
                f"{events[-1]['sigma']:.4f}  PSF error {events[-1]['psf_error']:.4f}  "
                + (f"PSNR {raw:.2f} dB, aligned {aligned:.2f} dB  " if args.event_psnr else "")
                + f"{event['optics/inner_steps']:.0f} inner steps of "
                f"{event['time/jpgm_iter_ms']:.1f} ms"
                + ("  (converged)" * events[-1]["converged"]),
                flush=True,
            )
    synchronize(device)
    fitted = time.perf_counter()
    scores, errors = engine.evaluate(), engine.optics_errors()
    shift = [scores[name] for name in names.REGISTRATION_SHIFT]
    return {
        "figure": args.figure,
        "quick": args.quick,
        "seed": args.seed,
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "optics": optics,
        "steps": steps,
        "simulation_s": simulated - start,
        "engine_s": built - simulated,
        "fit_s": fitted - built - scoring,
        "total_s": fitted - start - scoring,
        "scoring_s": scoring,
        "sigma": errors[names.ZERNIKE_RESIDUAL],
        "psf_error": errors[names.PSF_ERROR],
        "psnr": scores.get(names.PSNR),
        "psnr_shb": scores.get(names.PSNR + names.SHB),
        "psnr_aligned": scores[names.PSNR_REGISTERED],
        "shift_zyx": None if math.isnan(shift[0]) else shift,
        "oversampling": engine.jpgm.oversampling,
        "events": events,
    }


def depth_chunk(text: str) -> int | str:
    """``--depth-chunk``: a number of depths or ``auto``."""
    return text if text == "auto" else int(text)


def positive(text: str) -> int:
    """A positive whole number of steps."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"a positive number of steps expected, got {text}")
    return value


def blurs(text: str) -> tuple[float, ...]:
    """``--blur-px``: comma-separated blurs (pixels)."""
    return tuple(float(word) for word in text.split(","))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--figure", default="figS6", choices=("figS5", "figS6", "figS7", "figS8"))
    parser.add_argument("--quick", action="store_true", help="the CPU scale of the recipe")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--depth-chunk", dest="depth_chunk", type=depth_chunk, default=None, help="N or auto"
    )
    parser.add_argument("--tolerance", type=float, default=None)
    parser.add_argument(
        "--amplitude", type=float, default=None, help="Zernike terms uniform in +-A waves"
    )
    parser.add_argument(
        "--blur-px", dest="blur_px", type=blurs, default=None, help="coarse to fine: 4,2,1,0"
    )
    parser.add_argument("--blur-events", dest="blur_events", type=int, default=None)
    parser.add_argument("--parameter-tolerance", dest="parameter_tolerance", type=float)
    for name, meaning in (
        ("start", "JPGM events from this static step on (the first one --every later)"),
        ("every", "static steps between JPGM events"),
        ("steps", "inner steps per JPGM event"),
    ):
        parser.add_argument(f"--{name}", type=positive, default=None, help=meaning)
    parser.add_argument(
        "--max-steps", dest="max_steps", type=positive, default=None, help="static steps"
    )
    parser.add_argument(
        "--event-psnr", dest="event_psnr", action="store_true", help="volume PSNR at every event"
    )
    parser.add_argument("--device", default="auto")
    parser.add_argument("--out", default="benchmarks/results/optics_trial.json")
    args = parser.parse_args()
    result = run_trial(args, resolve_device(args.device))
    print(
        f"{result['figure']}{' --quick' * args.quick} seed {args.seed} on {result['device']}: "
        f"{result['total_s']:.1f} s (simulation {result['simulation_s']:.1f} s, SHB pre-pass and "
        f"set-up {result['engine_s']:.1f} s, {result['steps']} steps {result['fit_s']:.1f} s); "
        f"sigma {result['sigma']:.4f}, PSNR {result['psnr']:.2f} dB (SHB {result['psnr_shb']:.2f}; "
        f"registered to the truth {result['psnr_aligned']:.2f} dB, shift {result['shift_zyx']})"
    )
    write_json(args.out, result)
