"""Shared by the Fig. 5 recipes (:mod:`fgat.app.recipes.fig5_tracking`, :mod:`~.fig5_cytometry`): a
through the FLFM forward model of a small system with fgat's camera.

The grid is that of ``load_system(config.system)`` at ``config.depths_um`` with square views of
``config.view_size`` pixels; the optics are the JPGM PSF stack of
:func:`fgat.sim.simulation.true_psf_model`, ideal or with a recipe's random aberrations; imaging
projects each volume to the views, places them on the sensor and adds fgat's camera noise
(:func:`fgat.sim.simulation.camera`: one photon scale per sequence, ``config.photons`` at its
brightest pixel on ``config.background``), then crops the views back, as
:func:`fgat.sim.simulation.simulate` does. ``config`` is any object with the fields ``system``,
``depths_um``, ``view_size``, ``photons`` and ``background`` (and optionally ``aberrations``,
:class:`fgat.sim.simulation.Aberrations` fields, and ``seed``).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch

from fgat.gaussians.densify import Densification
from fgat.optics.operator import FLFMOperator
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.recon import Scene, StaticReconstruction, StaticSettings
from fgat.recon.estimation import OpticsEstimation
from fgat.sim.simulation import SimulationConfig, camera, true_optics, true_psf_model

ACQUISITION = ("system", "depths_um", "view_size", "photons", "background")
"""The fields of a recipe's config that this module reads."""


def grid(config):
    """The system, depths, volume shape and voxel size ``(dz, dy, dx)`` um of the recipe."""
    system = load_system(config.system)
    depths = parse_depths(config.depths_um)
    shape = (len(depths), config.view_size, config.view_size)
    return system, depths, shape, np.asarray(system.grid_voxel_size_um(depths), dtype=np.float64)


def flfm_optics(config) -> dict:
    """``system``, ``depths``, ``shape``, ``voxel``, the true PSF stack ``psf`` ``(V, Z, h, w)``
    float32 tensor the views are imaged with and its operator ``op`` (:class:`FLFMOperator` on
    ``shape``); the aberration-free optics ``ideal`` (:class:`OpticsSpec`), its PSF stack
    ``ideal_psf`` and operator ``ideal_op``. The true optics are ideal unless ``config`` has an
    ``aberrations`` field (:class:`fgat.sim.simulation.Aberrations` fields, drawn with
    ``config.seed``)."""
    system, depths, shape, voxel = grid(config)
    ideal = OpticsSpec(system, tuple(depths))
    with torch.no_grad():
        psf = true_psf_model(_truth(config), system, depths)().float()
        ideal_psf = ideal.jpgm(dtype=torch.float64)().float() if _aberrations(config) else psf
    return {
        "system": system,
        "depths": depths,
        "shape": shape,
        "voxel": voxel,
        "psf": psf,
        "op": FLFMOperator(psf, shape),
        "ideal": ideal,
        "ideal_psf": ideal_psf,
        "ideal_op": FLFMOperator(ideal_psf, shape),
    }


def flfm_true_zernike(config, indices) -> np.ndarray:
    """The true Zernike coefficients (waves) of :func:`flfm_optics` at the Noll ``indices``."""
    zernike = true_optics(_truth(config), load_system(config.system).n_lenslets)["zernike"]
    return np.array([zernike.get(int(j), 0.0) for j in indices], dtype=np.float64)


def _aberrations(config) -> dict | None:
    return getattr(config, "aberrations", None)


def _truth(config) -> SimulationConfig:
    """The simulation settings of the true optics: the recipe's aberrations and seed."""
    return SimulationConfig(
        system=config.system, aberrations=_aberrations(config), seed=config.seed
    )


def sensor_sequence(volumes, config, optics: dict, seed: int) -> np.ndarray:
    """Noisy sensor images ``(T, H, W)`` float32 of the volumes ``(T, Z, Y, X)`` (arrays or an
    iterable of them, one photon scale for the sequence, noise seed ``(seed, frame)``; a single
    volume uses ``seed``)."""
    system, operator = optics["system"], optics["op"]
    centers = system.lenslet_centers_px()
    clean = []
    for volume in volumes:
        views = operator.forward(torch.as_tensor(np.asarray(volume))).double().clamp(min=0)
        clean.append(FLFMOperator.sensor(views, centers, system.sensor_shape).numpy())
    noise = SimulationConfig(seed=seed, **{name: getattr(config, name) for name in ACQUISITION})
    return np.stack(camera(clean, noise)).astype(np.float32)


def image_sequence(volumes, config, optics: dict, seed: int) -> np.ndarray:
    """Noisy per-view images ``(T, V, Y, X)`` float32: :func:`sensor_sequence` cropped to the
    views."""
    centers = optics["system"].lenslet_centers_px()
    return np.stack(
        [
            FLFMOperator.views_from_sensor(
                torch.from_numpy(image), centers, config.view_size
            ).numpy()
            for image in sensor_sequence(volumes, config, optics, seed)
        ]
    )


def fit_static(
    scene: Scene,
    config,
    *,
    steps: int,
    n_gaussians: int,
    estimation: OpticsEstimation = OpticsEstimation(),
) -> StaticReconstruction:
    """4DGAT's static stage on ``scene``'s reference frame run for ``steps`` steps:
    ``n_gaussians`` canonical Gaussians seeded by ``config.init_iterations`` SHB iterations
    (seed ``config.seed``), no densification, the optics ``estimation`` (default fixed)."""
    engine = StaticReconstruction(
        scene,
        StaticSettings(
            n_gaussians=n_gaussians,
            init_iterations=config.init_iterations,
            baseline_iterations=0,
            seed=config.seed,
        ),
        Densification(enabled=False),
        estimation,
        total_steps=max(steps, 1),
    )
    for _ in range(steps):
        engine.step()
    return engine


def recipe_main(argv, recipe: dict, *, name: str, quick_help: str, results: Path) -> None:
    """The command line of a Fig. 5 recipe, ``[--quick] [--seed N] [--out DIR]``: ``recipe`` is
    the recipe module's namespace (``globals()``) with ``__doc__``, the configs ``QUICK`` and
    ``FULL`` (dataclasses with a ``seed``), ``run(config, out)`` and ``report(summary)``; results
    go to ``results/<name>[_quick]/`` (the script's ``reproduce/results``) unless ``--out`` says
    otherwise."""
    parser = argparse.ArgumentParser(description=recipe["__doc__"].split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    config = dataclasses.replace(recipe["QUICK" if args.quick else "FULL"], seed=args.seed)
    out = args.out or results / (f"{name}_quick" if args.quick else name)
    summary = recipe["run"](config, out)
    print(recipe["report"](summary))
    print(f"-> {out}")
