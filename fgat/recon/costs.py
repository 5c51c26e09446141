"""Cost estimates of a run before it starts: memory of the operator, the deconvolution and
the Gaussian stages, and the run time measured on a few steps (refusing runs that would
take too long unless allowed).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from fgat._core.resources import (
    Affine,
    available_memory,
    device_memory,
    fastest_seconds,
    format_bytes,
    format_seconds,
)
from fgat.optics.operator import operator_memory
from fgat.recon.guards import synchronize
from fgat.recon.joint_step import CG_ITERATIONS, PROBES
from fgat.recon.losses import pixel_loss, static_loss
from fgat.recon.optics_report import identifiability_columns, identifiability_plan


def deconvolution_memory(
    psf_shape: tuple[int, int, int, int],
    volume_shape: tuple[int, int, int],
    *,
    itemsize: int = 4,
    guard_px: int = 0,
) -> int:
    """Bytes of an RL/SHB deconvolution (:func:`fgat.recon.deconvolution.deconvolve`), upper bound:
    :func:`operator_memory` plus Algorithm S1's six volumes (estimate, previous, extrapolated
    point, update, ``A^T 1``, the callback's copy) on the grid padded by ``guard_px`` (see
    :func:`operator_memory`) and five view stacks (measurement, its normalised copy, prediction,
    ratio, ``A^T`` input, counted at the padded size; weights broadcast a given mask)."""
    n_views = int(psf_shape[0])
    z, y, x = (int(n) + 2 * guard_px * (axis > 0) for axis, n in enumerate(volume_shape))
    return (
        operator_memory(psf_shape, volume_shape, itemsize=itemsize, guard_px=guard_px)
        + (6 * z + 5 * n_views) * y * x * itemsize
    )


def window_voxels(scale: float, axial_ratio: float) -> int:
    """Voxels in the voxelizer's window around a Gaussian of ``scale`` lateral voxels (its 3-sigma
    box, at least the smallest window), the axial voxel being ``axial_ratio`` lateral voxels."""
    lateral = 2 * math.floor(3 * scale + 0.5) + 1
    axial = 2 * max(1, math.floor(3 * scale / axial_ratio + 0.5)) + 1
    return lateral * lateral * axial


def gaussian_bytes(count: int, window: int) -> int:
    """Memory of ``count`` Gaussians in a training step: 11 float32 parameters with their
    gradients and two Adam moments, and per window voxel what the voxelizer keeps for the
    backward pass (quadratic form, exponential, values, mask, int64 voxel index: about 32 bytes).
    A lower bound: windows grow when the Gaussians do."""
    return count * (11 * 4 * 4 + 32 * window)


def plane_seconds(
    run: Callable[[int], object],
    planes: tuple[int, int],
    synchronize: Callable[[], None] = lambda: None,
) -> Affine:
    """Calibrate an operation whose work grows with its planes: ``run(k)`` on ``k`` planes,
    once at ``planes[0]`` to warm up (allocations, kernel choice), then timed at both sizes
    (:func:`fastest_seconds`); the line through the two times, its slope and intercept floored
    at 0 (timing noise), so that ``seconds(Z)`` extrapolates to the whole stack."""
    small, large = planes
    run(small)
    t_small = fastest_seconds(lambda: run(small), synchronize)
    if large <= small:
        return Affine(t_small, 0.0)
    t_large = fastest_seconds(lambda: run(large), synchronize)
    slope = max(t_large - t_small, 0.0) / (large - small)
    fixed = max(t_small - slope * small, 0.0)
    return Affine(fixed, slope)


def optics_events(start: int, every: int, first_step: int, last_step: int) -> int:
    """JPGM events of a schedule after steps ``first_step + 1 .. last_step`` (an event runs
    after step ``k`` when ``k > start`` and ``(k - start) % every == 0``)."""
    if last_step <= start:
        return 0
    done = max(first_step - start, 0) // every
    return max((last_step - start) // every - done, 0)


@dataclass
class CostEstimate:
    """The time and peak memory a computation is expected to take.

    Attributes
    ----------
    what : str
        The computation, e.g. ``"deconvolution"`` or ``"static fit"``.
    seconds : dict
        Part -> estimated wall seconds (``"steps"``, ``"optics events"``, ...); a part already
        run is given as measured.
    memory : dict
        Part -> estimated peak bytes of this process while it runs (the process's own memory
        included); the peak is the largest.
    notes : list of str
        How the parts were counted (``"2000 steps x 0.12 s"``).
    levers : list of str
        Options that reduce the time or memory, most effective first.
    device : str
        Where it runs.
    """

    what: str
    seconds: dict[str, float] = field(default_factory=dict)
    memory: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    levers: list[str] = field(default_factory=list)
    device: str = "cpu"

    @property
    def total_seconds(self) -> float:
        return float(sum(self.seconds.values()))

    @property
    def peak_bytes(self) -> int:
        return int(max(self.memory.values(), default=0))

    def lines(self) -> list[str]:
        """The estimate as printed before the run: total, parts, peak and its part, levers."""
        largest = max(self.memory, key=self.memory.get) if self.memory else ""
        where = "GPU" if self.device.startswith("cuda") else "host"
        lines = [
            f"estimated {self.what}: about {format_seconds(self.total_seconds)} and "
            f"{format_bytes(self.peak_bytes)} peak {where} memory (largest: {largest}) on "
            f"{self.device}"
        ]
        lines += [f"  {part}: {format_seconds(t)}" for part, t in self.seconds.items() if t > 0]
        lines += [f"  {note}" for note in self.notes]
        if self.levers:
            lines.append("  to reduce: " + "; ".join(self.levers))
        return lines

    def params(self, prefix: str = "cost") -> dict[str, float]:
        """Flat numbers for a tracking server: ``cost/seconds``, ``cost/peak_bytes``,
        ``cost/seconds_<part>`` and ``cost/bytes_<part>`` (spaces as underscores)."""
        params = {f"{prefix}/seconds": round(self.total_seconds, 3)}
        params[f"{prefix}/peak_bytes"] = self.peak_bytes
        for part, value in self.seconds.items():
            params[f"{prefix}/seconds_{part.replace(' ', '_')}"] = round(value, 3)
        for part, value in self.memory.items():
            params[f"{prefix}/bytes_{part.replace(' ', '_')}"] = int(value)
        return params


def deconvolution_cost(
    operator,
    iterations: int,
    *,
    device: str = "cpu",
    setup_seconds: float = 0.0,
    options: dict[str, str] | None = None,
) -> CostEstimate:
    """The time and peak memory of an RL/SHB deconvolution
    (:func:`fgat.recon.deconvolution.deconvolve`).

    Time: ``iterations`` forward and adjoint projections of ``operator`` (Algorithm S1's other
    work is a few passes over a volume), one of them timed here on a random volume of its
    grid (:func:`fastest_seconds`). Memory: this process's current size
    (:func:`device_memory`: on a GPU, the device's) plus :func:`deconvolution_memory`.

    Parameters
    ----------
    operator : MeasuredOperator
        The forward model the deconvolution uses, built (its construction is part of
        ``setup_seconds``).
    iterations : int
        Iterations of the deconvolution.
    device : str
        Where it runs.
    setup_seconds : float
        Time already spent (reading the data, the PSF, the operator), the part ``"setup"``.
    options : dict, optional
        Option names for the levers: ``{"planes": "--depth-step", "size": "--view-size", ...}``.
    """
    options = options or {}
    now, _ = device_memory(device)
    generator = torch.Generator().manual_seed(0)
    volume = torch.rand(operator.volume_shape, generator=generator).to(device, operator.dtype)

    def project() -> None:
        with torch.no_grad():
            operator.adjoint(operator.forward(volume))

    project()
    projection = fastest_seconds(project, lambda: synchronize(torch.device(device)))
    psf_shape = (operator.n_views, operator.volume_shape[0], *operator.psf_shape)
    unpadded = (operator.volume_shape[0], *operator.view_shape)
    need = deconvolution_memory(psf_shape, unpadded, guard_px=operator.guard_px)
    cost = CostEstimate(
        "deconvolution",
        {"setup": setup_seconds, "iterations": iterations * projection},
        {"deconvolution": now + need},
        [f"{iterations} iterations x {format_seconds(projection)} (forward + adjoint)"],
        device=str(device),
    )
    cost.levers = [
        f"fewer planes ({options.get('planes', 'fewer PSF depths')})",
        f"fewer iterations ({options.get('iterations', 'iterations')})",
        f"a smaller view or guard band ({options.get('size', 'view size')})",
    ]
    if not str(device).startswith("cuda"):
        cost.levers.append(f"a GPU ({options.get('device', '--device cuda')})")
    return cost


LONG_RUN_SECONDS = 24 * 3600.0
"""The longest estimated run (s) a command starts without ``--allow-long``: a day. A request
beyond it (``--iterations 1e9``) is far more often a typo than an intent, and is refused with
its estimate (:func:`check_long_run`)."""


def check_long_run(cost: CostEstimate, *, allow: bool, lever: str) -> None:
    """Refuse a run whose estimated time exceeds :data:`LONG_RUN_SECONDS` unless ``allow``.

    Parameters
    ----------
    cost : CostEstimate
        The run's estimate (its ``notes`` say how it was counted).
    allow : bool
        The user's explicit consent (``--allow-long``).
    lever : str
        What to lower instead, e.g. ``"--iterations"``.

    Raises
    ------
    ValueError
        ``"the deconvolution would take about 55000.0 h (1000000000 iterations x 0.2 s), more
        than 24 h: lower --iterations, or pass --allow-long to run it"``.
    """
    seconds = cost.total_seconds
    if allow or seconds <= LONG_RUN_SECONDS:
        return
    how = f" ({'; '.join(cost.notes)})" if cost.notes else ""
    raise ValueError(
        f"the {cost.what} would take about {format_seconds(seconds)}{how} on {cost.device}, more "
        f"than {format_seconds(LONG_RUN_SECONDS)}: lower {lever}, or pass --allow-long to run it"
    )


GRAPH_FACTOR = 3
"""Memory of a JPGM evaluation with its autograd graph, in units of
:meth:`~fgat.optics.psf.JPGM.memory_bytes` (one evaluation without): the saved fields, phases
and their gradients."""

JVP_FACTOR = 1.2
"""Time of one forward-mode Jacobian column of the predicted views, in float32 evaluations of the
PSF stack and its projection without a graph: a float64 column costs about 0.6 float64
evaluations (the vectorised tangents share the primal pass), a float64 evaluation about two
float32 ones."""


def _gaussian_step_seconds(engine, loss: Callable[[], object], parameters) -> float:
    """Seconds of one forward and backward pass of a fit's data loss (``loss()`` -> the loss
    tensor), warm then timed; the gradients of ``parameters`` are cleared after each."""

    def run() -> None:
        loss().backward()
        for parameter in parameters():
            parameter.grad = None

    device = torch.device(engine.device)
    run()
    return fastest_seconds(run, lambda: synchronize(device))


def _step_memory(engine, psf_shape, grid_shape, volume_shape, scales_um) -> int:
    """Bytes a fit step adds to what the process holds: the forward model, the Gaussians'
    windows at their median scale (:func:`gaussian_bytes`), and the graph's volume and views
    (values, gradients and the loss's temporaries: three of each)."""
    dz, _, dx = engine.scene.voxel_size_um
    z, y, x = grid_shape
    n_views, (rows, cols) = psf_shape[0], engine.scene.view_shape
    scale = float(scales_um.detach().median()) / dx if len(scales_um) else 1.0
    return (
        operator_memory(psf_shape, volume_shape, guard_px=engine.scene.guard_px)
        + gaussian_bytes(len(scales_um), window_voxels(scale, dz / dx))
        + 3 * 4 * (z * y * x + n_views * rows * cols)
    )


def fit_levers(optics: bool, identifiability: bool, device: str) -> list[str]:
    """Options of ``python -m fgat fit`` that reduce its time or memory."""
    levers = [
        "fewer planes (data.depths_um, or a coarser depth step)",
        "fewer steps (trainer.max_steps)",
        "fewer Gaussians (model.n_gaussians)",
    ]
    if optics:
        levers[:0] = [
            "optics fixed (model.optics.estimate = none), or fewer JPGM updates "
            "(model.optics.every larger, model.optics.steps smaller, model.optics.tolerance > 0)",
            "a smaller PSF crop (the system's crop_radius_px)",
        ]
    if identifiability:
        levers.append("no standard errors at the end (model.optics.identifiability = false)")
    if not device.startswith("cuda"):
        levers.append("a GPU (trainer.accelerator = gpu)")
    return levers


def static_fit_cost(engine, total_steps: int, setup_seconds: float = 0.0) -> CostEstimate:
    """The time and peak memory of the rest of a static fit (3DGAT, or 4DGAT with the optics
    estimated) from its engine (:class:`~fgat.recon.static.StaticReconstruction`),
    calibrated on this machine at the fit's own sizes.

    Time: ``setup_seconds`` (the SHB initialisation and model building, measured), the steps
    left times one step's forward and backward pass (timed on the fit's Gaussians, forward
    model and loss), the JPGM events the schedule runs (:func:`optics_events`) times
    ``optics.steps`` inner updates (timed on one and three planes with the graph,
    :func:`plane_seconds`, and extrapolated to the stack in the fit's depth chunks) plus the
    PSF recomputed after each event, and the standard errors at the end (``P`` Jacobian
    columns of :data:`JVP_FACTOR` graph-free evaluations each, and the joint Gauss-Newton
    step's conjugate-gradient iterations and probes, each about a step's forward and reverse
    pass). Events stopping early on ``optics.tolerance`` and the solve stopping early make
    this an upper bound.

    Memory: the process's peak so far (the setup), and its present size plus a step's
    (:func:`operator_memory`, :func:`gaussian_bytes`, the graph's volumes), an update's
    (:data:`GRAPH_FACTOR` JPGM evaluations of a depth chunk and its forward model with the
    OTFs' gradients) or the standard errors'
    (:func:`~fgat.recon.optics_report.identifiability_plan`).
    """
    device = str(engine.device)
    now, peak = device_memory(device)
    steps = max(int(total_steps) - engine.steps_done, 0)
    s = engine.settings

    def loss():
        prediction = engine.operator.forward(engine.cloud())
        return static_loss(
            prediction,
            engine.measurement,
            step=engine.steps_done,
            total_steps=max(int(total_steps), 1),
            p=s.p,
            lambda_fourier=s.lambda_fourier,
            lambda_ssim=s.lambda_ssim,
            mask=engine.mask,
        )["total"]

    step = _gaussian_step_seconds(engine, loss, lambda: [p for _, p in engine.named_parameters()])
    cost = CostEstimate(
        "static fit",
        {"setup": setup_seconds, "steps": steps * step},
        {
            "setup": peak,
            "steps": now
            + _step_memory(
                engine,
                engine.scene.psf.shape,
                engine.fit_scene.grid_shape,
                engine.fit_scene.volume_shape,
                engine.cloud.scales.reshape(-1),
            ),
        },
        [f"{steps} steps x {format_seconds(step)}"],
        device=device,
    )
    estimation = engine.estimation
    jpgm = engine.jpgm
    optics = jpgm is not None and engine.optics_converged_at is None
    if optics:
        events = optics_events(estimation.start, estimation.every, engine.steps_done, total_steps)
        n_depths = jpgm.n_depths
        chunk = engine.depth_chunks.size or n_depths
        volume = engine.grid_volume().detach()
        gains = engine.gains()
        gains = None if gains is None else gains.detach()

        def operator(psf):
            return engine.fit_scene.operator(psf, gains)

        def update(k: int) -> None:
            depths = slice(0, k)
            prediction = operator(jpgm(depths)).forward(volume[depths])
            pixel_loss(prediction, engine.measurement, estimation.p, engine.mask).backward()
            jpgm.zero_grad(set_to_none=True)

        def evaluate(k: int) -> None:
            with torch.no_grad():
                operator(jpgm(slice(0, k))).forward(volume[:k])

        sync = lambda: synchronize(torch.device(device))  # noqa: E731
        planes = (1, min(3, n_depths))
        graph = plane_seconds(update, planes, sync)
        plain = fastest_seconds(lambda: evaluate(1), sync) / max(graph(1), 1e-9)
        forward = Affine(graph.fixed * plain, graph.per_unit * plain)
        inner = (
            graph(n_depths)
            if chunk >= n_depths
            else forward(n_depths) + math.ceil(n_depths / chunk) * graph(chunk)
        )
        cost.seconds["optics events"] = events * (estimation.steps * inner + forward(n_depths))
        cost.notes.append(
            f"{events} JPGM events x {estimation.steps} updates x {format_seconds(inner)} "
            f"({n_depths} planes" + (f" in chunks of {chunk}" if chunk < n_depths else "") + ")"
        )
        side = 2 * jpgm.radius + 1
        cost.memory["optics events"] = (
            now
            + GRAPH_FACTOR * jpgm.memory_bytes(chunk)
            + 2
            * (
                operator_memory(
                    (jpgm.n_views, chunk, side, side),
                    (chunk, *engine.fit_scene.volume_shape[1:]),
                    adjoint=False,
                    guard_px=engine.scene.guard_px,
                )
            )
        )
        if estimation.identifiability:
            double = copy.deepcopy(jpgm).to(torch.float64)
            available = available_memory(engine.device)
            plan = identifiability_plan(
                double,
                engine.fit_scene.volume_shape,
                engine.scene.guard_px,
                estimation.estimate,
                available,
            )
            columns = identifiability_columns(double, estimation.estimate)
            del double
            cost.seconds["standard errors"] = (
                JVP_FACTOR * columns * forward(n_depths) + (CG_ITERATIONS + PROBES) * step
            )
            cost.memory["standard errors"] = now + plan.nbytes
            cost.notes.append(
                f"standard errors: {columns} Jacobian columns in passes of {plan.chunk_size} "
                f"columns x {plan.depth_chunk} planes, {format_bytes(plan.nbytes)}"
            )
            if available is not None and plan.nbytes > available:
                cost.notes.append(
                    f"the standard errors need {format_bytes(plan.nbytes)}, more than the "
                    f"{format_bytes(available)} available: they will be skipped"
                )
    cost.levers = fit_levers(optics, optics and estimation.identifiability, device)
    return cost


def dynamic_fit_cost(engine, total_steps: int, setup_seconds: float = 0.0) -> CostEstimate:
    """The time and peak memory of the rest of a dynamic fit from its engine
    (:class:`~fgat.recon.dynamic.DynamicReconstruction`): ``setup_seconds`` and the
    steps left times one frame step's forward and backward pass (the deformation field, the
    Gaussians, the forward model and the loss, timed on the first frame); memory as in
    :func:`static_fit_cost` for the deformed Gaussians."""

    device = str(engine.device)
    now, peak = device_memory(device)
    steps = max(int(total_steps) - engine.steps_done, 0)

    def loss():
        return engine.frame_loss(0)["total"]

    step = _gaussian_step_seconds(
        engine, loss, lambda: [p for _, p in engine.field.named_parameters()]
    )
    memory = _step_memory(
        engine,
        engine.scene.psf.shape,
        engine.scene.grid_shape,
        engine.scene.volume_shape,
        engine.g0["scales"].reshape(-1),
    )
    return CostEstimate(
        "dynamic fit",
        {"setup": setup_seconds, "steps": steps * step},
        {"setup": peak, "steps": now + memory},
        [f"{steps} frame steps x {format_seconds(step)}"],
        fit_levers(False, False, device),
        device,
    )
