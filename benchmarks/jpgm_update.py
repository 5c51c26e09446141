"""Benchmark one JPGM update (the inner step of a self-estimation event) against the paper's 0.6 s.

One update regenerates the PSF stack from (c_j, b_v, s_v), rebuilds the OTFs, projects the
current volume, evaluates the data loss and back-propagates to the JPGM parameters, then takes
an Adam step: what ``time/jpgm_iter_ms`` logs. Measured for the matrix-Fourier fast path and the
angular-spectrum reference on the same inputs (their PSF stacks are compared too), at the
paper's size (20x/0.45, 101 depths, 161 px crops, 300 x 300 views, all 17 Zernike terms and the
shifts estimated) and at the small CPU size (small system, 31 depths, 64 x 64 views, ASM only:
the small system's crosstalk needs it). On a GPU the paper-size figure is compared with the
paper's 0.6 s per update (Note S3.5.2). Each row also counts the PyTorch operations one update
dispatches and the values it reads back to the host (:class:`~fgat._core.devices.DispatchCount`): on
a GPU each operation costs host time whatever its size, and each read waits for the queue.
Last, the paper-size fast-path PSF stack of the sampled optics (1 wave) on its automatic pupil
grid and on the point-sampled ``s = 1`` grid, each against the point-sampled ``s = 2`` one.

``--profile N`` instead prints and writes (``<out>_profile.txt``) ``torch.profiler``'s table of
``N`` fast-path updates at the paper's size (``--quick``: the small system's ASM update): each
operation's own GPU (on a CPU, host) time, its host time and its calls.

``--tiny`` runs the small system's ASM update on a tiny scene instead (7 depths, 32 x 32 views;
seconds on a CPU): a check that the script runs, not a timing.

``--memory N`` instead measures the peak memory of one paper-size fast-path update with the
whole stack's graph and with depth chunks of ``N`` (``optics.depth_chunk``), each in a fresh
process: the peak resident set on a CPU (``ru_maxrss``), the peak allocation on a GPU, with the
time of that update and the largest gradient difference between the two (written to
``<out>_memory.json``).

    python benchmarks/jpgm_update.py [--quick | --tiny] [--repeats 3] [--memory 16 | --profile 5]
        [--out benchmarks/results/jpgm_update.json]
"""

from __future__ import annotations

import multiprocessing
import resource
import time
from pathlib import Path

import torch

from fgat._core.devices import DispatchCount, adam, resolve_device
from fgat.app.recipes.benchmark import (
    parser,
    profile_table,
    synchronize,
    timed,
    write_json,
    write_text,
)
from fgat.optics.operator import FLFMOperator
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.recon.estimation import data_loss_backward
from fgat.sim.phantoms import beads
from fgat.sim.simulation import sample_aberrations

PAPER_UPDATE_S = 0.6
PAPER = ("20x/0.45", "-75:75:101", 300)  # system, depths (um), view size (px)
SMALL = ("small", "-22.5:22.5:31", 64)
TINY = ("small", "-4.5:4.5:7", 32)


def sampled_optics(system_name: str, depths: str) -> OpticsSpec:
    """The system and depths with sampled optics (1 wave, 0.1 on the small system)."""
    system = load_system(system_name)
    optics = sample_aberrations(
        system.n_lenslets,
        amplitude=0.1 if system_name == "small" else 1.0,
        intercept_range=1.0,
        slope_range=1.0,
        seed=0,
    )
    return OpticsSpec(system, tuple(parse_depths(depths)), **optics)


def paper_or_small(system_name: str, depths: str, view_size: int, device: torch.device):
    """The system, depths, a bead volume and its measurement under sampled optics."""
    spec = sampled_optics(system_name, depths)
    system, depths_um = spec.system, list(spec.depths_um)
    volume = torch.from_numpy(
        beads((len(depths_um), view_size, view_size), 40, sigma=1.0, seed=0)
    ).to(device)
    with torch.no_grad():
        truth = spec.jpgm(device=device)()
    measurement = FLFMOperator(truth, tuple(volume.shape)).forward(volume)
    return system, depths_um, volume, measurement


def one_update(jpgm, optimizer, volume, measurement, depth_chunk: int = 0) -> None:
    """One JPGM update as a self-estimation event's inner step makes it."""
    optimizer.zero_grad(set_to_none=True)
    data_loss_backward(
        jpgm,
        lambda psf: FLFMOperator(psf, (psf.shape[1], *volume.shape[1:])),
        volume,
        measurement,
        1,
        depth_chunk=depth_chunk,
    )
    optimizer.step()


def update_case(
    system_name: str,
    depths: str,
    view_size: int,
    methods: tuple[str, ...],
    device: torch.device,
    repeats: int,
) -> list[dict]:
    system, depths_um, volume, measurement = paper_or_small(system_name, depths, view_size, device)
    rows, stacks = [], {}
    for method in methods:
        jpgm = OpticsSpec(system, tuple(depths_um)).jpgm(method=method, device=device)
        optimizer = adam(list(jpgm.parameters()), lr=1e-3)

        seconds = timed(
            lambda jpgm=jpgm, optimizer=optimizer: one_update(jpgm, optimizer, volume, measurement),
            repeats,
            device,
        )
        with DispatchCount() as count:
            one_update(jpgm, optimizer, volume, measurement)
        with torch.no_grad():
            stacks[method] = jpgm()
            psf_s = timed(jpgm, repeats, device)
        rows.append(
            {
                "case": f"{system_name}, {len(depths_um)} depths, {view_size}^2 views",
                "method": method,
                "device": str(device),
                "update_s": seconds,
                "psf_s": psf_s,
                "vs_paper": PAPER_UPDATE_S / seconds,
                "ops": count.total,
                "host_reads": count.host_reads,
            }
        )
    if len(stacks) == 2:
        fast, reference = stacks["mft"], stacks["asm"]
        error = float((fast - reference).norm() / reference.norm())
        for row in rows:
            row["mft_vs_asm_rel_l2"] = error
            row["speedup_vs_asm"] = rows[-1]["update_s"] / row["update_s"]
    return rows


def sampling_rows(device: torch.device) -> list[dict]:
    """The paper-size fast-path PSF stack of the sampled optics on the automatic pupil grid and
    on the point-sampled grids of ``s = 1`` and ``s = 2``, each against the ``s = 2`` stack."""
    spec = sampled_optics(*PAPER[:2])
    rows, stacks = [], {}
    for oversampling in (None, 1, 2):
        jpgm = spec.jpgm(method="mft", oversampling=oversampling, device=device)
        with torch.no_grad():
            stacks[oversampling] = jpgm()
        box = jpgm.basis.shape[-1]
        rows.append({"requested": oversampling, "oversampling": jpgm.oversampling, "box": box})
    for row in rows:
        stack = stacks[row["requested"]]
        row["rel_l2_vs_s2"] = float((stack - stacks[2]).norm() / stacks[2].norm())
    return rows


def peak_memory(depth_chunk: int) -> dict:
    """One paper-size fast-path update in this (fresh) process: peak memory, time, gradient."""
    device = resolve_device("auto")
    system, depths_um, volume, measurement = paper_or_small(*PAPER, device)
    jpgm = OpticsSpec(system, tuple(depths_um)).jpgm(method="mft", device=device)
    optimizer = torch.optim.SGD(jpgm.parameters(), lr=0.0)  # the gradient, parameters kept
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    start = time.perf_counter()
    one_update(jpgm, optimizer, volume, measurement, depth_chunk)
    synchronize(device)
    seconds = time.perf_counter() - start
    peak = (
        torch.cuda.max_memory_allocated(device)
        if device.type == "cuda"
        else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    )
    return {
        "depth_chunk": depth_chunk,
        "device": str(device),
        "peak_gb": peak / 1e9,
        "before_gb": before / 1e9,
        "update_s": seconds,
        "gradient": [p.grad.cpu() for p in jpgm.parameters()],
    }


def memory_rows(depth_chunk: int) -> list[dict]:
    """:func:`peak_memory` of the whole stack and of ``depth_chunk``, each in a new process."""
    context = multiprocessing.get_context("spawn")
    rows = []
    for chunk in (0, depth_chunk):
        with context.Pool(1) as pool:
            rows.append(pool.apply(peak_memory, (chunk,)))
    whole, chunked = (row.pop("gradient") for row in rows)
    difference = max(
        float((a - b).abs().max() / b.abs().max().clamp(min=1e-30)) for a, b in zip(chunked, whole)
    )
    print(f"{'depth chunk':>11} {'peak (GB)':>10} {'before (GB)':>12} {'update (s)':>11}")
    for row in rows:
        row["gradient_rel_difference"] = difference
        print(
            f"{row['depth_chunk'] or 'whole':>11} {row['peak_gb']:>10.2f} "
            f"{row['before_gb']:>12.2f} {row['update_s']:>11.1f}"
        )
    print(f"largest gradient difference, relative to each parameter's largest: {difference:.1e}")
    return rows


def update_profile(case: tuple, updates: int, device: torch.device) -> str:
    """``torch.profiler``'s table of ``updates`` updates after a warm-up: the fast path at the
    paper's size (:data:`PAPER`; another ``case``: ASM), operations sorted by their own GPU time
    (CPU time on a CPU), with each one's host time and calls."""
    system, depths_um, volume, measurement = paper_or_small(*case, device)
    jpgm = OpticsSpec(system, tuple(depths_um)).jpgm(
        method="mft" if case == PAPER else "asm", device=device
    )
    optimizer = torch.optim.Adam(jpgm.parameters(), lr=1e-3)
    return profile_table(lambda: one_update(jpgm, optimizer, volume, measurement), updates, device)


def main() -> None:
    command = parser(
        __doc__, "benchmarks/results/jpgm_update.json", "small CPU case only", "tiny case only"
    )
    command.add_argument(
        "--memory", type=int, default=0, help="peak memory with depth chunks of this many depths"
    )
    command.add_argument(
        "--profile", type=int, default=0, help="profile this many fast-path updates instead"
    )
    args = command.parse_args()
    for option in ("memory", "profile"):
        if getattr(args, option) < 0:
            command.error(f"--{option} must be a positive number, got {getattr(args, option)}")
    small = TINY if args.tiny else SMALL
    if args.profile:
        table = update_profile(
            small if args.quick or args.tiny else PAPER, args.profile, resolve_device("auto")
        )
        print(table)
        out = Path(args.out)
        write_text(out.with_name(f"{out.stem}_profile.txt"), table)
        return
    if args.memory:
        out = Path(args.out)
        write_json(out.with_name(f"{out.stem}_memory.json"), {"memory": memory_rows(args.memory)})
        return
    device = resolve_device("auto")
    rows = update_case(*small, ("asm",), device, args.repeats)
    if not (args.quick or args.tiny):
        rows += update_case(*PAPER, ("mft", "asm"), device, args.repeats)
    print(
        f"{'case':<38} {'method':>6} {'update (s)':>11} {'PSF (s)':>8} "
        f"{'0.6 s / update':>15} {'vs ASM':>7} {'ops':>6} {'host reads':>10}"
    )
    for row in rows:
        print(
            f"{row['case']:<38} {row['method']:>6} {row['update_s']:>11.3f} {row['psf_s']:>8.3f} "
            f"{row['vs_paper']:>15.2f} {row.get('speedup_vs_asm', float('nan')):>7.2f} "
            f"{row['ops']:>6} {row['host_reads']:>10}"
        )
    if any("mft_vs_asm_rel_l2" in row for row in rows):
        print(f"fast path vs ASM PSF stack, relative L2: {rows[-1]['mft_vs_asm_rel_l2']:.2e}")
    sampling = [] if args.quick or args.tiny else sampling_rows(device)
    for row in sampling:
        print(
            f"fast-path pupil grid s = {row['oversampling']:g} ({row['box']} samples across a "
            f"lenslet{', automatic' if row['requested'] is None else ''}): relative L2 to the "
            f"point-sampled s = 2 stack {row['rel_l2_vs_s2']:.2e}"
        )
    write_json(args.out, {"device": str(device), "rows": rows, "sampling": sampling})


if __name__ == "__main__":
    main()
