"""Benchmark the FLFM operator and the JPGM PSF-stack generator.

1. Forward + adjoint projection in the spectral form (``N_z + N_view`` FFTs per projection)
   against the naive form (one FFT pair per view and depth, same cached OTFs), at the paper's
   size (300 x 300 x 101, 7 views, 161 px PSFs) and a small size, as a ratio measured in the
   same run, with the two forms' agreement; each projection against its floor (its FFTs timed
   in cache, one depth chunk at a time, plus one read of the OTFs at the measured memory
   bandwidth), with the contraction over depth timed apart (streamed, and its arithmetic alone
   in cache); and forward + backward with the adjoint as the backward against differentiating
   through the FFTs.
2. PSF-stack generation of the 20x/0.45 system (7 views, 101 depths, r = 80): the fast
   matrix-Fourier-transform path against the angular-spectrum path, with their relative L2
   difference; and one JPGM update (PSF stack, OTFs, projection, loss, backward) of the fast
   path, the operation Table S7 times at 0.6 s.

    python benchmarks/operator.py [--quick] [--out benchmarks/results/operator.json]
"""

from __future__ import annotations

import math
import platform
import statistics
import time

import torch
from torch import Tensor

from fgat.app.recipes.benchmark import parser, timed, write_json
from fgat.optics.operator import FLFMOperator, _accumulate
from fgat.optics.psf import fast_fft_size
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system


def naive_forward(operator: FLFMOperator, volume: torch.Tensor) -> torch.Tensor:
    """One rfft2/irfft2 pair per (view, depth): the form the spectral operator replaces."""
    z, y, x = operator.volume_shape
    h, w = operator.psf_shape
    otf = operator.otf.reshape(operator.n_views, z, operator.fft_shape[0], -1)
    views = []
    for v in range(operator.n_views):
        total = 0
        for k in range(z):
            total = total + torch.fft.irfft2(
                torch.fft.rfft2(volume[k], s=operator.fft_shape) * otf[v, k], s=operator.fft_shape
            )
        views.append(total[h // 2 : h // 2 + y, w // 2 : w // 2 + x])
    return torch.stack(views)


def naive_adjoint(operator: FLFMOperator, views: torch.Tensor) -> torch.Tensor:
    z, y, x = operator.volume_shape
    h, w = operator.psf_shape
    fy, fx = operator.fft_shape
    otf = operator.otf.reshape(operator.n_views, z, fy, -1)
    padded = torch.nn.functional.pad(views, (w // 2, fx - x - w // 2, h // 2, fy - y - h // 2))
    slices = []
    for k in range(z):
        total = 0
        for v in range(operator.n_views):
            total = total + torch.fft.irfft2(
                torch.fft.rfft2(padded[v]) * otf[v, k].conj(), s=operator.fft_shape
            )
        slices.append(total[:y, :x])
    return torch.stack(slices)


ROUNDS = 3
"""Floor and projections are timed in alternating rounds; the ratio is each round's, median."""


def bench_operator(name: str, views: int, depths: int, size: int, psf: int, repeats: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    stack = torch.rand(views, depths, psf, psf, generator=generator)
    volume = torch.rand(depths, size, size, generator=generator)
    start = time.perf_counter()
    operator = FLFMOperator(stack, (depths, size, size))
    otf_time = time.perf_counter() - start
    residual = operator.forward(volume)
    # The rounds against the floor come first: the naive form's thousands of transient FFT
    # buffers leave the heap in a state no reconstruction puts it in.
    rounds = [
        (
            projection_floor(operator, repeats),
            timed(lambda: operator.forward(volume), repeats),
            timed(lambda: operator.adjoint(residual), repeats),
        )
        for _ in range(ROUNDS)
    ]
    spectral = timed(lambda: operator.adjoint(operator.forward(volume)), repeats)
    naive = timed(
        lambda: naive_adjoint(operator, naive_forward(operator, volume)), max(1, repeats // 3)
    )
    floor = {key: statistics.median(r[0][key] for r in rounds) for key in rounds[0][0]}
    forward_of_floor = [r[0]["forward_floor_s"] / r[1] for r in rounds]
    adjoint_of_floor = [r[0]["adjoint_floor_s"] / r[2] for r in rounds]
    measurement = torch.rand_like(residual)

    def gradient(project):
        def run():
            estimate = volume.clone().requires_grad_(True)
            ((project(estimate) - measurement) ** 2).sum().backward()
            return estimate.grad

        return run

    with_adjoint, traced = gradient(operator.forward), gradient(operator._project)
    backward_agreement = float((with_adjoint() - traced()).norm() / traced().norm())
    agreement = float((naive_forward(operator, volume) - residual).norm() / residual.norm())
    adjoint_agreement = float(
        (naive_adjoint(operator, residual) - operator.adjoint(residual)).norm()
        / operator.adjoint(residual).norm()
    )
    return {
        "case": name,
        "views": views,
        "depths": depths,
        "size": size,
        "psf": psf,
        "fft_shape": list(operator.fft_shape),
        "linear_fft_shape": [fast_fft_size(size + psf - 1)] * 2,
        "otf_build_s": otf_time,
        "depth_chunk": operator.depth_chunk,
        "spectral_fwd_adj_s": spectral,
        "forward_s": statistics.median(r[1] for r in rounds),
        "adjoint_s": statistics.median(r[2] for r in rounds),
        **floor,
        "forward_of_floor": statistics.median(forward_of_floor),
        "forward_of_floor_range": [min(forward_of_floor), max(forward_of_floor)],
        "adjoint_of_floor": statistics.median(adjoint_of_floor),
        "adjoint_of_floor_range": [min(adjoint_of_floor), max(adjoint_of_floor)],
        "fwd_bwd_adjoint_s": timed(with_adjoint, repeats),
        "fwd_bwd_traced_s": timed(traced, repeats),
        "backward_rel_l2": backward_agreement,
        "naive_fwd_adj_s": naive,
        "speedup": naive / spectral,
        "forward_rel_l2": agreement,
        "adjoint_rel_l2": adjoint_agreement,
    }


def projection_floor(operator: FLFMOperator, repeats: int) -> dict:
    """What a projection cannot go below: its transforms, timed on one cache-sized depth chunk
    and scaled to the count a projection needs (``Z`` forward + ``V`` inverse, or the reverse),
    plus one read of the OTFs at the bandwidth of a reduction over a buffer of their size. The
    forward transform is ``rfft2``; the inverse is the operator's own (the columns of every
    frequency, then the rows of the kept window only: less work than ``irfft2``). Each is the
    fastest of ``repeats`` runs: a bound, not a typical time."""
    fy, fx = operator.fft_shape
    planes = torch.rand(operator.depth_chunk, fy, fx)
    spectra = torch.fft.rfft2(planes).flatten(-2)
    forward_fft = min_time(lambda: torch.fft.rfft2(planes), repeats) / len(planes)
    inverse_fft = min_time(lambda: operator._planes(spectra, (0, 0)), repeats) / len(planes)
    otf = operator.otf.detach()
    read = min_time(lambda: torch.view_as_real(otf).sum(), repeats)
    z, v = operator.volume_shape[0], operator.n_views
    return {
        "forward_transform_plane_s": forward_fft,
        "inverse_transform_plane_s": inverse_fft,
        "otf_read_s": read,
        **contraction_times(operator, spectra, repeats),
        "bandwidth_gb_s": otf.numel() * otf.element_size() / read / 1e9,
        "forward_floor_s": z * forward_fft + v * inverse_fft + read,
        "adjoint_floor_s": v * forward_fft + z * inverse_fft + read,
    }


CACHE_BINS = 16384
"""Frequency bins of the in-cache contraction: its accumulator (``V x 16384`` complex, 0.9 MB
at seven views, a half per core) stays in L2 and one chunk's OTFs (13 MB at 14 depths) in L3;
narrower blocks pay more per-call overhead than arithmetic."""


def contraction_times(operator: FLFMOperator, spectra: Tensor, repeats: int) -> dict:
    """The forward's contraction over every depth (``_accumulate`` on one chunk's spectra, the
    OTFs streamed from memory as a projection reads them) and the same number of complex
    multiply-adds on a block of ``CACHE_BINS`` bins (at most the spectrum's) that stays in
    cache, scaled to the whole: what its arithmetic costs without the memory traffic.
    ``spectra`` ``(Zc, F)`` are one depth chunk's slice spectra on the operator's grid. Returns
    ``contraction_s`` and ``contraction_in_cache_s`` in seconds, each the fastest of
    ``repeats`` runs."""
    z, chunk = operator.volume_shape[0], len(spectra)
    otf = operator.otf.detach().unbind(1)
    views = torch.zeros(1, operator.n_views, spectra.shape[-1], dtype=spectra.dtype)

    def streamed():
        for begin in range(0, z, chunk):
            _accumulate(otf[begin : begin + chunk], spectra[None], views)

    bins = min(CACHE_BINS, spectra.shape[-1])
    block = [depth[:, :bins].contiguous() for depth in otf[:chunk]]
    block_views = views[..., :bins].clone()
    block_spectra = spectra[None, :, :bins].contiguous()
    passes = math.ceil(z * spectra.shape[-1] / (chunk * bins))

    def in_cache():
        for _ in range(passes):
            _accumulate(block, block_spectra, block_views)

    arithmetic = min_time(in_cache, repeats) * z * spectra.shape[-1] / (passes * chunk * bins)
    return {"contraction_s": min_time(streamed, repeats), "contraction_in_cache_s": arithmetic}


def min_time(function, repeats: int) -> float:
    """Fastest wall time (s) of ``function()`` over at least ten runs, after one warm-up."""
    return timed(function, max(repeats, 10), statistic=min)


def bench_psf(depths: int, repeats: int) -> dict:
    system = load_system("20x/0.45")
    depth_um = torch.linspace(-75.0, 75.0, depths).tolist()  # 1.5 um steps at 101 depths
    spec = OpticsSpec(system, tuple(depth_um))
    generator = torch.Generator().manual_seed(0)
    zernike = 0.1 * (2 * torch.rand(17, generator=generator) - 1)
    intercepts, slopes = (2 * torch.rand(7, 2, generator=generator) - 1 for _ in range(2))
    # One model per path, each on the pupil grid it chooses for itself (the MFT's is coarser).
    model, reference_model = (spec.jpgm(method=method) for method in ("mft", "asm"))
    with torch.no_grad():
        for jpgm in (model, reference_model):
            jpgm.zernike_coefficients.copy_(zernike)
            jpgm.intercepts.copy_(intercepts)
            jpgm.slopes.copy_(slopes)
        fast_stack = model()
        fast = timed(model, repeats)
        reference_stack = reference_model()
        reference = timed(reference_model, max(1, repeats // 3))
    volume = torch.rand(depths, 300, 300, generator=generator)
    measurement = torch.rand(7, 300, 300, generator=generator)

    def jpgm_update():
        model.zero_grad()
        operator = FLFMOperator(model(), (depths, 300, 300))
        loss = (operator.forward(volume) - measurement).abs().mean()
        loss.backward()

    update = timed(jpgm_update, 1)
    return {
        "system": system.name,
        "views": 7,
        "depths": depths,
        "crop_radius": model.radius,
        "fast_mft_s": fast,
        "angular_spectrum_s": reference,
        "speedup": reference / fast,
        "fast_vs_asm_rel_l2": float((fast_stack - reference_stack).norm() / reference_stack.norm()),
        "jpgm_update_fast_s": update,
        "paper_jpgm_update_s": 0.6,
    }


def main() -> None:
    args = parser(
        __doc__, "benchmarks/results/operator.json", "small operator case and 11 PSF depths only"
    ).parse_args()

    cases = [("small", 7, 31, 64, 65)] + ([] if args.quick else [("paper", 7, 101, 300, 161)])
    operator_rows = [bench_operator(*case, repeats=args.repeats) for case in cases]
    psf_row = bench_psf(11 if args.quick else 101, repeats=max(1, args.repeats // 2))

    print(
        f"FLFM operator, forward + adjoint (torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads)"
    )
    print(
        f"{'case':>6} {'V x Z x Y x X':>18} {'psf':>4} {'spectral s':>11} {'naive s':>9} "
        f"{'speedup':>8} {'rel L2':>9}"
    )
    for r in operator_rows:
        shape = f"{r['views']}x{r['depths']}x{r['size']}x{r['size']}"
        print(
            f"{r['case']:>6} {shape:>18} {r['psf']:>4} {r['spectral_fwd_adj_s']:>11.4f} "
            f"{r['naive_fwd_adj_s']:>9.3f} {r['speedup']:>7.1f}x {r['forward_rel_l2']:>9.1e}"
        )
    print(
        f"\nagainst the floor (FFTs in cache + one OTF read at "
        f"{operator_rows[-1]['bandwidth_gb_s']:.0f} GB/s; median of {ROUNDS} rounds), "
        "and forward + backward"
    )
    print(
        f"{'case':>6} {'chunk':>5} {'forward s':>10} {'of floor':>8} {'adjoint s':>10} "
        f"{'of floor':>8} {'f+b adjoint s':>14} {'f+b traced s':>13} {'grad rel L2':>11}"
    )
    for r in operator_rows:
        print(
            f"{r['case']:>6} {r['depth_chunk']:>5} {r['forward_s']:>10.4f} "
            f"{r['forward_of_floor']:>8.0%} {r['adjoint_s']:>10.4f} {r['adjoint_of_floor']:>8.0%} "
            f"{r['fwd_bwd_adjoint_s']:>14.4f} {r['fwd_bwd_traced_s']:>13.4f} "
            f"{r['backward_rel_l2']:>11.1e}"
        )
    print(
        "\nthe forward's contraction over all depths: streamed from memory as a projection "
        "reads the OTFs, its arithmetic alone (in cache), and one read of the OTFs"
    )
    print(f"{'case':>6} {'streamed ms':>12} {'arithmetic ms':>14} {'OTF read ms':>12}")
    for r in operator_rows:
        print(
            f"{r['case']:>6} {r['contraction_s'] * 1e3:>12.1f} "
            f"{r['contraction_in_cache_s'] * 1e3:>14.1f} {r['otf_read_s'] * 1e3:>12.1f}"
        )
    p = psf_row
    print(
        f"\nJPGM PSF stack, {p['system']}: {p['views']} views x {p['depths']} depths, "
        f"r = {p['crop_radius']}"
    )
    print(f"  fast path (MFT)       {p['fast_mft_s']:8.3f} s")
    print(
        f"  angular spectrum      {p['angular_spectrum_s']:8.3f} s   ({p['speedup']:.1f}x slower)"
    )
    print(f"  relative L2 fast vs angular spectrum: {p['fast_vs_asm_rel_l2']:.2e}")
    print(
        "  one JPGM update (PSF, OTFs, projection, loss, backward): "
        f"{p['jpgm_update_fast_s']:.3f} s "
        f"(paper, on a GPU: {p['paper_jpgm_update_s']} s)"
    )

    write_json(
        args.out,
        {
            "device": "cpu",
            "threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "machine": platform.machine(),
            "operator": operator_rows,
            "psf": psf_row,
        },
    )


if __name__ == "__main__":
    main()
