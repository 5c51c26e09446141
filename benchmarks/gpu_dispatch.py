"""Count the operations a dynamic frame-iteration and a voxelization dispatch on a GPU's code
paths, from any machine.

On a GPU the voxelizer, the HexPlane features, the deformation and the plane regularisers run
as Triton kernels, so a step there dispatches other operations than on a CPU, which takes their
PyTorch paths; and a GPU step of this size is bound by the host dispatching them. Here the
small case of ``dynamic_step.py`` (one frame-iteration) and its 2,000 Gaussians' voxelization
with its backward (as a static step renders them) run with ``backend="triton"`` under Triton's
interpreter, every kernel launch counted as one operation and the interpreter's own operations
left out (the voxel tiles' kernel is only counted, not run: see :data:`KERNELS`), beside the
same with ``backend="torch"``. Operations and host reads are
:class:`~fgat._core.devices.DispatchCount`'s.

    python benchmarks/gpu_dispatch.py [--out benchmarks/results/gpu_dispatch.json]

About a minute and a half on 2 CPU cores (the interpreter runs the kernels program by program).
"""

from __future__ import annotations

import os

os.environ["TRITON_INTERPRET"] = "1"  # before Triton is imported

import torch  # noqa: E402

from fgat._core.devices import DispatchCount  # noqa: E402
from fgat.app.recipes.benchmark import parser, write_json  # noqa: E402
from fgat.app.recipes.dynamic_step import SMALL, frame_case  # noqa: E402
from fgat.dynamics import deformation_triton, hexplane_triton, regularizers_triton  # noqa: E402
from fgat.gaussians import voxelize_triton  # noqa: E402
from fgat.gaussians.cloud import GaussianCloud  # noqa: E402
from fgat.gaussians.voxelize import voxelize  # noqa: E402

KERNELS = (
    (voxelize_triton, "_coefficients_kernel", True),
    (voxelize_triton, "_tiles_kernel", False),
    (hexplane_triton, "_level_kernel", True),
    (deformation_triton, "_deform_kernel", True),
    (regularizers_triton, "_terms_kernel", True),
)
"""The Triton kernels a frame-iteration launches, by module, and whether the count also runs
them. All but the voxel tiles run (a few programs each in the interpreter), so that every value
a later launch depends on is the real one: the voxelizer launches its tile kernel only where
some Gaussian is in the grid, which garbage from a kernel left unrun (or a step driven by it)
can empty. The tiles' volume and gradients are then zeros, which decide no launch."""


class CountedLaunches:
    """Stands in for ``kernel``: ``kernel[grid](...)`` counts a launch in ``counts["launches"]``
    and, when ``run``, runs it, counting in ``counts["inside"]`` the PyTorch operations that
    Triton's interpreter dispatches meanwhile (not the step's)."""

    def __init__(self, kernel, run: bool, counts: dict[str, int]) -> None:
        self.kernel, self.run, self.counts = kernel, run, counts

    def __getitem__(self, grid):
        def launch(*args, **kwargs) -> None:
            self.counts["launches"] += 1
            if self.run:
                with DispatchCount() as inside:
                    self.kernel[grid](*args, **kwargs)
                self.counts["inside"] += inside.total

        return launch


def voxelization(backend: str):
    """The small case's Gaussians rendered and differentiated (all four attributes)."""
    shape, n_gaussians = SMALL[1], SMALL[2]
    cloud = GaussianCloud(shape, (1.5, 0.975, 0.975)).random(n_gaussians, scale=1.5, seed=0)
    grid = (shape, cloud.voxel_size.tolist(), cloud.origin.tolist())

    def run():
        gaussians = (cloud.means, cloud.scales, cloud.quaternions, cloud.intensities)
        voxelize(*gaussians, *grid, backend=backend).sum().backward()

    return run


CASES = {
    "frame-iteration": lambda backend: frame_case(*SMALL[1:], torch.device("cpu"), backend)[2],
    "voxelize + backward": voxelization,
}
"""What is counted: a function of the back-end giving the work to run."""


def count(case: str, backend: str) -> dict:
    """The operations (kernel launches included) and host reads of one run of ``case`` on
    ``backend``, after one run that makes the optimizer's state."""
    counts = {"launches": 0, "inside": 0}
    kept = [(module, name, getattr(module, name)) for module, name, _ in KERNELS]
    for module, name, run in KERNELS:
        setattr(module, name, CountedLaunches(getattr(module, name), run, counts))
    try:
        work = CASES[case](backend)
        work()
        counts.update(launches=0, inside=0)
        with DispatchCount() as dispatched:
            work()
    finally:
        for module, name, kernel in kept:
            setattr(module, name, kernel)
    return {
        "case": case,
        "backend": backend,
        "ops": dispatched.total - counts["inside"] + counts["launches"],
        "kernel_launches": counts["launches"],
        "host_reads": dispatched.host_reads,
    }


def main() -> None:
    args = parser(__doc__, "benchmarks/results/gpu_dispatch.json", "(no effect)").parse_args()
    rows = [count(case, backend) for case in CASES for backend in ("torch", "triton")]
    print(
        f"Operations dispatched per code path, small case of dynamic_step.py ({SMALL[2]} Gaussians)"
    )
    print(f"{'case':>20} {'backend':>8} {'ops':>6} {'Triton launches':>16} {'host reads':>10}")
    for r in rows:
        print(
            f"{r['case']:>20} {r['backend']:>8} {r['ops']:>6} {r['kernel_launches']:>16} "
            f"{r['host_reads']:>10}"
        )
    write_json(args.out, {"rows": rows})


if __name__ == "__main__":
    main()
