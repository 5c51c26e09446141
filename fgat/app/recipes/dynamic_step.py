"""Benchmark one dynamic-stage frame-iteration (Note S7.2): deformation, voxelize, full step.

A frame-iteration queries the HexPlane + MLP field for every canonical Gaussian (at t and at
t_ref, for the exact anchoring; the spatial planes sampled once for both), applies the
deformation (Eq. S22), voxelizes, projects, and back-propagates L_dyn (Eq. S29, with the plane
regularisers) to the field. At the size of Fig. 3a (384 x 384 x 62, 7 views, 161 px PSFs,
20,000 Gaussians, HexPlane 64 x 64 x 64 x 65) and a small one (64 x 64 x 31, 2,000 Gaussians,
16 x 16 x 16 x 8). On a GPU the step is compared with the paper's 0.1 s per frame-iteration; on
a CPU it is reported as a CPU figure. Each row also counts the PyTorch operations one step
dispatches and its reads back to the host (:class:`~fgat._core.devices.DispatchCount`; on a CPU with
the voxelizer's PyTorch path and Adam's per-tensor loop, each ``.item()`` of its step counts a
read): on a GPU the step is bound by the host launching them.

``--profile N`` instead prints and writes (``<out>_profile.txt``) ``torch.profiler``'s table of
N steps of the largest case. ``--tiny`` runs a tiny case instead (24 x 24 x 7, 100 Gaussians,
4 x 4 x 4 x 4; seconds on a CPU): a check that the script runs, not a timing.

    python benchmarks/dynamic_step.py [--quick | --tiny] [--repeats 5] [--profile 5]
        [--out benchmarks/results/dynamic_step.json]
"""

from __future__ import annotations

from pathlib import Path

import torch

from fgat._core.devices import DispatchCount, adam, resolve_device
from fgat.app.recipes.benchmark import parser, profile_table, timed, write_json, write_text
from fgat.dynamics import DeformationField, HexPlane
from fgat.dynamics.deformation import normalized_positions
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.voxelize import voxelize
from fgat.optics.operator import FLFMOperator
from fgat.recon.losses import dynamic_loss

PAPER_FRAME_ITERATION_S = 0.1  # Note S7.2
SMALL = ("small", (31, 64, 64), 2000, 65, 16, 8)
FIG3A = ("fig3a", (62, 384, 384), 20000, 161, 64, 65)
TINY = ("tiny", (7, 24, 24), 100, 15, 4, 4)
"""Cases: name, grid (Z, Y, X), Gaussians, PSF size, HexPlane spatial and temporal resolution."""


def frame_case(
    shape: tuple[int, int, int],
    n_gaussians: int,
    psf_size: int,
    spatial: int,
    temporal: int,
    device: torch.device,
    backend: str = "auto",
):
    """``(deform, grid, step)`` of one case: the deformation alone, the voxel grid, and a whole
    frame-iteration (deformation, voxelize, projection, ``L_dyn``, backward, Adam step), with
    the deformation, the voxelizer and the plane regularisers on ``backend``."""
    generator = torch.Generator().manual_seed(0)
    voxel = (1.5, 0.975, 0.975)
    cloud = GaussianCloud(shape, voxel).random(n_gaussians, scale=1.5, seed=0).to(device)
    gaussians = [
        value.detach()
        for value in (cloud.means, cloud.scales, cloud.quaternions, cloud.intensities)
    ]
    grid = (shape, voxel, cloud.origin.tolist())
    psf = torch.rand(7, shape[0], psf_size, psf_size, generator=generator)
    operator = FLFMOperator((psf / psf.sum(dim=(0, 2, 3), keepdim=True)).to(device), shape)
    measurement = operator.forward(voxelize(*gaussians, *grid)) * 1.1
    torch.manual_seed(0)  # the MLP's initialisation: the voxelizer's window groups depend on it
    field = DeformationField(HexPlane(16, (spatial,) * 3, temporal), reference_time=0.0).to(device)
    extent = [n * v for n, v in zip(shape, voxel)]
    positions = normalized_positions(gaussians[0], cloud.origin.tolist(), extent)
    optimizer = adam(list(field.parameters()), lr=1e-3)
    time = torch.tensor(0.3, device=device)

    def deform():
        return field.deform(positions, time, gaussians, backend=backend)

    def step():
        optimizer.zero_grad()
        prediction = operator.forward(voxelize(*deform(), *grid, backend=backend))
        dynamic_loss(prediction, measurement, field.hexplane, backend=backend)["total"].backward()
        optimizer.step()

    return deform, grid, step


def bench_frame(case: tuple, device: torch.device, repeats: int) -> dict:
    """Times and counts of one case (:data:`SMALL`, :data:`FIG3A`)."""
    name, shape, n_gaussians, psf_size, spatial, temporal = case
    deform, grid, step = frame_case(*case[1:], device)
    with torch.no_grad():
        deform_s = timed(deform, repeats, device)
        voxelize_s = timed(lambda: voxelize(*deform(), *grid), repeats, device) - deform_s
    step()  # the optimizer's state made before the count
    with DispatchCount() as count:
        step()
    row = {
        "case": name,
        "shape": list(shape),
        "gaussians": n_gaussians,
        "psf": psf_size,
        "hexplane": [spatial] * 3 + [temporal],
        "deformation_s": deform_s,
        "voxelize_s": voxelize_s,
        "step_s": timed(step, repeats, device),
        "ops": count.total,
        "host_reads": count.host_reads,
    }
    if device.type == "cuda":
        row["step_vs_paper"] = PAPER_FRAME_ITERATION_S / row["step_s"]
    return row


def main() -> None:
    command = parser(
        __doc__, "benchmarks/results/dynamic_step.json", "small case only", "tiny case only"
    )
    command.add_argument(
        "--profile", type=int, default=0, help="profile this many steps of the largest case instead"
    )
    args = command.parse_args()
    if args.profile < 0:
        command.error(f"--profile must be a positive number, got {args.profile}")
    device = resolve_device("auto")
    cases = [TINY] if args.tiny else [SMALL] if args.quick else [SMALL, FIG3A]
    if args.profile:
        table = profile_table(frame_case(*cases[-1][1:], device)[2], args.profile, device)
        print(table)
        out = Path(args.out)
        write_text(out.with_name(f"{out.stem}_profile.txt"), table)
        return
    rows = [bench_frame(case, device, args.repeats) for case in cases]
    print(f"Dynamic frame-iteration on {device.type} (torch {torch.__version__})")
    print(
        f"{'case':>6} {'grid':>12} {'N':>6} {'HexPlane':>14} {'deform s':>9} "
        f"{'voxelize s':>11} {'step s':>8} {'ops':>6} {'host reads':>10}"
    )
    for r in rows:
        grid = "x".join(str(s) for s in r["shape"])
        planes = "x".join(str(s) for s in r["hexplane"])
        print(
            f"{r['case']:>6} {grid:>12} {r['gaussians']:>6} {planes:>14} "
            f"{r['deformation_s']:>9.4f} "
            f"{r['voxelize_s']:>11.4f} {r['step_s']:>8.4f} {r['ops']:>6} {r['host_reads']:>10}"
        )
    print(
        f"paper (Note S7.2, GPU): {PAPER_FRAME_ITERATION_S} s per frame-iteration"
        + ("" if device.type == "cuda" else " (no GPU here: CPU figures above)")
    )
    write_json(args.out, {"device": device.type, "steps": rows})
