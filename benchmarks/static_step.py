"""Benchmark one static-stage step (Table S7): voxelize, projection, full step.

At the paper's grid (300 x 300 x 101, 7 views, 161 px PSFs, 20,000 Gaussians) and a small one
(64 x 64 x 31, 2,000 Gaussians). On a GPU the times are compared with Table S7's (0.004 s
voxelization, 0.03 s cached projection, 0.07 s regular step) as ratios; on a CPU they are
reported as CPU figures. The windowed voxelizer is also compared with a dense evaluation of
every Gaussian at every voxel (same result) at a size the dense one fits in memory. ``--tiny``
runs a tiny grid instead (24 x 24 x 7, 100 Gaussians; seconds on a CPU): a check that the
script runs, not a timing.

    python benchmarks/static_step.py [--quick | --tiny] [--out benchmarks/results/static_step.json]
"""

from __future__ import annotations

import torch

from fgat._core.devices import adam, resolve_device, triton_installed
from fgat.app.recipes.benchmark import parser, timed, write_json
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.voxelize import voxelize, voxelize_dense
from fgat.optics.operator import FLFMOperator
from fgat.recon.losses import static_loss

TABLE_S7_S = {"voxelize": 0.004, "projection": 0.03, "step": 0.07}
SMALL = ("small", (31, 64, 64), 2000, 65)
PAPER = ("paper", (101, 300, 300), 20000, 161)
TINY = ("tiny", (7, 24, 24), 100, 15)
"""Cases: name, grid (Z, Y, X), Gaussians, PSF size."""
DENSE = ((48, 48, 48), 1000)
TINY_DENSE = ((16, 16, 16), 100)
"""The windowed against the dense voxelizer: grid, Gaussians."""


def bench_step(
    name: str,
    shape: tuple[int, int, int],
    n_gaussians: int,
    psf_size: int,
    device: torch.device,
    repeats: int,
) -> dict:
    generator = torch.Generator().manual_seed(0)
    cloud = (
        GaussianCloud(shape, (1.5, 0.975, 0.975)).random(n_gaussians, scale=1.5, seed=0).to(device)
    )
    psf = torch.rand(7, shape[0], psf_size, psf_size, generator=generator)
    operator = FLFMOperator((psf / psf.sum(dim=(0, 2, 3), keepdim=True)).to(device), shape)
    measurement = operator.forward(cloud().detach()) * 1.1
    optimizer = adam(list(cloud.parameters()), lr=1e-3)
    volume = cloud().detach()

    def step():
        optimizer.zero_grad()
        loss = static_loss(operator.forward(cloud()), measurement, step=0, total_steps=1)["total"]
        loss.backward()
        optimizer.step()

    def rendered_and_differentiated(backend: str):
        grid = (shape, cloud.voxel_size.tolist(), cloud.origin.tolist())

        def run():
            gaussians = (cloud.means, cloud.scales, cloud.quaternions, cloud.intensities)
            voxelize(*gaussians, *grid, backend=backend).sum().backward()

        return run

    with torch.no_grad():
        voxelize_s = timed(cloud, repeats, device)
        projection_s = timed(lambda: operator.forward(volume), repeats, device)
    row = {
        "case": name,
        "shape": list(shape),
        "gaussians": n_gaussians,
        "views": 7,
        "psf": psf_size,
        "voxelize_s": voxelize_s,
        "projection_s": projection_s,
        "step_s": timed(step, repeats, device),
    }
    if device.type == "cuda" and triton_installed():  # the two voxelizer paths, same process
        for backend in ("torch", "triton"):
            row[f"voxelize_forward_backward_{backend}_s"] = timed(
                rendered_and_differentiated(backend), repeats, device
            )
    if device.type == "cuda":
        row.update({f"{key}_vs_table_s7": TABLE_S7_S[key] / row[f"{key}_s"] for key in TABLE_S7_S})
    return row


def bench_dense(shape: tuple[int, int, int], n: int, device: torch.device) -> dict:
    cloud = GaussianCloud(shape, (1.0, 1.0, 1.0)).random(n, scale=1.5, seed=1).to(device)
    arguments = (
        cloud.means.detach(),
        cloud.scales.detach(),
        cloud.quaternions.detach(),
        cloud.intensities.detach(),
        shape,
        (1.0, 1.0, 1.0),
        cloud.origin.tolist(),
    )
    windowed = timed(lambda: voxelize(*arguments), 3, device)
    dense = timed(lambda: voxelize_dense(*arguments), 1, device)
    difference = float((voxelize(*arguments) - voxelize_dense(*arguments)).abs().max())
    return {
        "shape": list(shape),
        "gaussians": n,
        "windowed_s": windowed,
        "dense_s": dense,
        "speedup": dense / windowed,
        "max_abs_difference": difference,
    }


def main() -> None:
    args = parser(
        __doc__, "benchmarks/results/static_step.json", "small case only", "tiny case only"
    ).parse_args()
    device = resolve_device("auto")
    cases = [TINY] if args.tiny else [SMALL] if args.quick else [SMALL, PAPER]
    rows = [bench_step(*case, device=device, repeats=args.repeats) for case in cases]
    dense = bench_dense(*(TINY_DENSE if args.tiny else DENSE), device)
    print(f"Static step on {device.type} (torch {torch.__version__})")
    print(
        f"{'case':>6} {'grid':>12} {'N':>6} {'voxelize s':>11} {'projection s':>13} {'step s':>8}"
    )
    for r in rows:
        grid = "x".join(str(s) for s in r["shape"])
        print(
            f"{r['case']:>6} {grid:>12} {r['gaussians']:>6} {r['voxelize_s']:>11.4f} "
            f"{r['projection_s']:>13.4f} "
            f"{r['step_s']:>8.4f}"
        )
    for r in rows:
        if "voxelize_forward_backward_triton_s" in r:
            print(
                f"{r['case']}: voxelize forward + backward, PyTorch path "
                f"{r['voxelize_forward_backward_torch_s']:.4f} s, Triton path "
                f"{r['voxelize_forward_backward_triton_s']:.4f} s"
            )
    print(
        f"Table S7 (GPU): voxelize {TABLE_S7_S['voxelize']} s, "
        f"projection {TABLE_S7_S['projection']} s, "
        f"step {TABLE_S7_S['step']} s"
        + ("" if device.type == "cuda" else " (no GPU here: CPU figures above)")
    )
    print(
        f"windowed voxelizer vs dense, {dense['gaussians']} Gaussians on {dense['shape']}: "
        f"{dense['windowed_s']:.3f} s "
        f"vs {dense['dense_s']:.3f} s ({dense['speedup']:.0f}x), "
        f"max difference {dense['max_abs_difference']:.1e}"
    )
    write_json(args.out, {"device": device.type, "steps": rows, "dense": dense})


if __name__ == "__main__":
    main()
