"""Benchmark RL and SHB deconvolution (Note S6, Algorithm S1).

1. Seconds per iteration of RL and SHB at the paper's size (7 views, 101 x 300 x 300) and at
   the small system's size (7 views, 31 x 64 x 64).
2. Wall time to reach a PSNR target on a simulated bead scene (small system): the PSNR RL
   reaches after 200 iterations, SHB against RL in the same run.

Every timing is a median over ``--repeats`` runs (with its min-max spread), after a warm-up
call, with RL and SHB interleaved in alternating order.
3. The single-view, single-depth case against scikit-image's ``richardson_lucy`` (same
   iterations, same result): a speed ratio.

    python benchmarks/deconvolution.py [--quick] [--out benchmarks/results/deconvolution.json]
"""

from __future__ import annotations

import time

import numpy as np
import torch
from skimage.restoration import richardson_lucy

from fgat.app.recipes.benchmark import parser, timed, write_json
from fgat.optics.operator import FLFMOperator
from fgat.recon.deconvolution import deconvolve, iterate_deconvolution
from fgat.recon.metrics import max_normalize, psnr
from fgat.sim.simulation import SimulationConfig, simulate

METHODS = ("rl", "shb")


def per_iteration(
    views: int, depths: int, size: int, psf: int, iterations: int, repeats: int
) -> dict:
    """Seconds per RL and SHB iteration: medians (and spread) over ``repeats`` runs of each,
    interleaved after a warm-up."""
    generator = torch.Generator().manual_seed(0)
    stack = torch.rand(views, depths, psf, psf, generator=generator)
    operator = FLFMOperator(stack / stack.sum(dim=(0, 2, 3), keepdim=True), (depths, size, size))
    measurement = operator.forward(torch.rand(depths, size, size, generator=generator))
    row = {"views": views, "depths": depths, "size": size, "psf": psf, "repeats": repeats}
    samples = interleaved(
        {m: lambda m=m: deconvolve(measurement, operator, iterations, method=m) for m in METHODS},
        repeats,
    )
    for method, seconds in samples.items():
        row.update(spread(f"{method}_s_per_iteration", np.asarray(seconds) / iterations))
    return row


def interleaved(functions: dict, repeats: int) -> dict[str, list[float]]:
    """Wall times of each function over ``repeats`` rounds, after one warm-up call each; the
    order alternates from round to round so that neither always runs first."""
    for function in functions.values():
        function()
    times = {name: [] for name in functions}
    for round_ in range(repeats):
        names = list(functions) if round_ % 2 == 0 else list(functions)[::-1]
        for name in names:
            start = time.perf_counter()
            functions[name]()
            times[name].append(time.perf_counter() - start)
    return times


def spread(name: str, values) -> dict:
    """``name`` (the median), ``name_min`` and ``name_max`` of ``values``."""
    values = np.asarray(values, dtype=float)
    return {
        name: float(np.median(values)),
        f"{name}_min": float(values.min()),
        f"{name}_max": float(values.max()),
    }


def time_to_target(iterations: int, repeats: int) -> dict:
    """Seconds each of RL and SHB needs to reach the PSNR RL has after ``iterations``
    iterations on a simulated bead scene: the algorithm's time only (the PSNR of every iterate
    is computed off the clock), medians and spread over ``repeats`` interleaved runs after a
    warm-up."""
    simulation = simulate(
        SimulationConfig(
            photons=1e4,
            phantom={
                "kind": "beads",
                "n_beads": 40,
                "sigma": 1.0,
                "min_spacing": 6.0,
                "margin": 3.0,
            },
        )
    )
    operator = FLFMOperator(torch.from_numpy(simulation.psf), simulation.truth.shape)
    views = torch.from_numpy(simulation.views)
    truth = max_normalize(torch.from_numpy(simulation.truth))
    curves = {method: [] for method in METHODS}

    def run(method):
        elapsed, scores, start = [], [], time.perf_counter()
        for step in iterate_deconvolution(views, operator, iterations, method=method):
            elapsed.append(time.perf_counter() - start)
            scores.append(float(psnr(max_normalize(step.estimate), truth, 1.0)))
            start = time.perf_counter() - elapsed[-1]
        curves[method].append((np.asarray(scores), np.asarray(elapsed)))

    interleaved({method: lambda m=method: run(m) for method in METHODS}, repeats)
    target = float(curves["rl"][-1][0][-1])
    row = {"target_psnr_db": target, "iterations_run": iterations, "repeats": repeats}
    for method, runs in curves.items():
        scores = runs[-1][0]
        first = int(np.argmax(scores >= target)) if (scores >= target).any() else None
        row[f"{method}_iterations"] = None if first is None else first + 1
        seconds = [elapsed[first] for _, elapsed in runs[1:]] if first is not None else [np.nan]
        row.update(spread(f"{method}_seconds", seconds))
    return row


def against_scikit_image(size: int, psf_size: int, iterations: int, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    image = rng.random((size, size)) + 0.1
    psf = rng.random((psf_size, psf_size))
    psf /= psf.sum()
    operator = FLFMOperator(torch.tensor(psf[None, None], dtype=torch.float32), (1, size, size))
    measurement = torch.tensor(image[None], dtype=torch.float32)

    def ours():
        return deconvolve(measurement, operator, iterations, method="rl")

    def theirs():
        return richardson_lucy(
            image.astype(np.float32), psf.astype(np.float32), num_iter=iterations, clip=False
        )

    times = {
        name: timed(function, repeats) for name, function in (("fgat", ours), ("skimage", theirs))
    }
    reference = theirs()
    difference = float(np.abs(ours()[0].numpy() - reference).max() / np.abs(reference).max())
    return {
        "size": size,
        "psf": psf_size,
        "iterations": iterations,
        "fgat_s": times["fgat"],
        "skimage_s": times["skimage"],
        "speedup": times["skimage"] / times["fgat"],
        "max_relative_difference": difference,
    }


def main() -> None:
    args = parser(
        __doc__, "benchmarks/results/deconvolution.json", "skip the paper-size case"
    ).parse_args()

    sizes = [("small", 7, 31, 64, 65, 50)] + (
        [] if args.quick else [("paper", 7, 101, 300, 161, 5)]
    )
    rows = [{"case": name, **per_iteration(*case, repeats=args.repeats)} for name, *case in sizes]
    target = time_to_target(200, args.repeats)
    single = against_scikit_image(512, 31, 30, repeats=args.repeats)

    print(
        f"RL / SHB seconds per iteration (torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads)"
    )
    print(f"{'case':>6} {'V x Z x Y x X':>16} {'RL s/it (min-max)':>26} {'SHB s/it (min-max)':>26}")
    for r in rows:
        shape = f"{r['views']}x{r['depths']}x{r['size']}x{r['size']}"
        cells = [
            f"{r[f'{m}_s_per_iteration']:.4f} ({r[f'{m}_s_per_iteration_min']:.4f}-"
            f"{r[f'{m}_s_per_iteration_max']:.4f})"
            for m in METHODS
        ]
        print(f"{r['case']:>6} {shape:>16} {cells[0]:>26} {cells[1]:>26}")
    print(
        f"\nTime to RL's 200-iteration PSNR ({target['target_psnr_db']:.2f} dB), "
        "small system, beads:"
    )
    for method in METHODS:
        print(
            f"  {method.upper():>3}: {target[f'{method}_iterations']} iterations, "
            f"{target[f'{method}_seconds']:.3f} s ({target[f'{method}_seconds_min']:.3f}-"
            f"{target[f'{method}_seconds_max']:.3f} over {target['repeats']} runs)"
        )
    if target["shb_seconds"]:
        print(f"  SHB is {target['rl_seconds'] / target['shb_seconds']:.1f}x faster in wall time")
    print(
        f"\nSingle view, {single['size']}^2 image, {single['psf']}^2 PSF, "
        f"{single['iterations']} RL iterations:"
    )
    print(
        f"  fgat {single['fgat_s']:.3f} s, scikit-image {single['skimage_s']:.3f} s -> "
        f"{single['speedup']:.1f}x "
        f"(max relative difference {single['max_relative_difference']:.1e})"
    )

    write_json(
        args.out,
        {"per_iteration": rows, "time_to_target": target, "single_view_vs_skimage": single},
    )


if __name__ == "__main__":
    main()
