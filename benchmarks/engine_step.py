"""Benchmark one step of each reconstruction engine as a fit runs it, guards included.

The quick dynamic recipe (``configs/base/common.yaml``, ``configs/dynamic_quick.yaml`` with
``configs/dynamic_quick_static.yaml`` or ``configs/dynamic_quick_dynamic.yaml``: a beating
shell, 21 x 48 x 48 voxels, 10 frames) resolved as ``python -m fgat pipeline`` resolves its two
stages, without Lightning: the static engine (:class:`~fgat.recon.StaticReconstruction`)
on the reference frame for ``--static-steps`` steps, then the dynamic engine
(:class:`~fgat.recon.DynamicReconstruction`) on its Gaussians. For each, one step's
PyTorch operations and reads back to the host (:class:`~fgat._core.devices.DispatchCount`: what a
step on a GPU waits for the host to launch and to read) and its median wall time. On a GPU the
voxelizer and the lenslet fields take their Triton kernels, so the counts there are the GPU's.
``--tiny`` shrinks the recipe's scene (:data:`TINY`; seconds on a CPU): a check that the script
runs, not a count or a timing of the recipe.

    python benchmarks/engine_step.py [--quick | --tiny] [--static-steps 50] [--repeats 5]
        [--out benchmarks/results/engine_step.json]
"""

from __future__ import annotations

import torch

from fgat._core.devices import DispatchCount, resolve_device
from fgat.app.lightning_cli import resolved_config
from fgat.app.modules.shell import flat_settings
from fgat.app.recipes.benchmark import parser, static_engine, timed, write_json
from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.recon import DynamicReconstruction, DynamicSettings, phantom_scene
from fgat.sim.simulation import SimulationConfig

RECIPE = ("configs/base/common.yaml", "configs/dynamic_quick.yaml")
STAGES = {
    "static": "configs/dynamic_quick_static.yaml",
    "dynamic": "configs/dynamic_quick_dynamic.yaml",
}
"""The quick dynamic recipe's files, and each stage's file laid over them."""
TINY = (
    "--data.init_args.simulation.depths_um=-4.5:4.5:7",
    "--data.init_args.simulation.view_size=32",
    "--data.init_args.simulation.frames=3",
    "--model.init_args.n_gaussians=200",
    "--model.init_args.init_iterations=2",
    "--model.init_args.baseline_iterations=0",
)
"""``--tiny``: the static stage's scene (which both engines fit) shrunk to 32 x 32 x 7 voxels and
3 frames, with 200 Gaussians seeded after 2 SHB iterations and no SHB baseline."""


def stage_config(stage: str, overrides: tuple[str, ...] = ()) -> dict:
    """The resolved ``fit`` config of one stage of the quick dynamic recipe, with ``overrides``
    (``--key=value`` arguments) after its files."""
    files = [*RECIPE, STAGES[stage]]
    configs = (arg for path in files for arg in ("--config", path))
    return resolved_config(["fit", *configs, *overrides])


def measure(name: str, step, device: torch.device, repeats: int) -> dict:
    """One ``step()``'s operations and host reads (after a warm-up step) and its median time."""
    step()
    with DispatchCount() as count:
        step()
    return {
        "engine": name,
        "ops": count.total,
        "host_reads": count.host_reads,
        "step_s": timed(step, repeats, device),
    }


def main() -> None:
    arguments = parser(
        __doc__,
        "benchmarks/results/engine_step.json",
        "fewer static steps",
        "a tiny scene, fewer static steps",
    )
    arguments.add_argument(
        "--static-steps", type=int, default=50, help="static steps before the one measured"
    )
    args = arguments.parse_args()
    device = resolve_device("auto")
    static = stage_config("static", TINY if args.tiny else ())
    dynamic = stage_config("dynamic")
    data, model = static["data"]["init_args"], static["model"]["init_args"]
    scene = phantom_scene(SimulationConfig(**data["simulation"]), psf=data["psf"])
    total = int(static["trainer"]["max_steps"])
    engine = static_engine(scene, model, model["optics"], total, device)
    for _ in range(10 if args.quick or args.tiny else args.static_steps):
        engine.step()
    rows = [measure("static", engine.step, device, args.repeats)]
    options = dynamic["model"]["init_args"]
    frames = DynamicReconstruction.from_static(
        scene,
        engine.cloud,
        None,
        None,
        HexPlaneSettings(**options["hexplane"]),
        flat_settings(DynamicSettings, options),
        device=device,
    )
    rows.append(measure("dynamic", frames.step, device, args.repeats))
    print(f"One engine step, quick dynamic recipe, on {device.type} (torch {torch.__version__})")
    print(f"{'engine':>8} {'ops':>6} {'host reads':>10} {'step s':>8}")
    for r in rows:
        print(f"{r['engine']:>8} {r['ops']:>6} {r['host_reads']:>10} {r['step_s']:>8.4f}")
    write_json(args.out, {"device": device.type, "torch": torch.__version__, "steps": rows})


if __name__ == "__main__":
    main()
