"""JPGM self-estimation events of the static stage (Note S3.5.2, Table S7's note).

Every ``every`` steps from ``start`` on, an event runs ``steps`` inner optimisation steps of the
JPGM parameters against the current (fixed) volume: regenerate the PSF stack from
``(c_j, b_v, s_v)``, rebuild the OTFs, project, compare with the measurement, back-propagate to
the JPGM parameters. Which parameters move is set by ``estimate``: ``"shifts"`` (Fig. S5),
``"zernike"`` (Fig. S6), ``"joint"`` (Figs. S7-S9), or ``"none"`` (optics fixed: no event runs).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from fgat._core.devices import adam
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.psf import METHODS as PSF_METHODS
from fgat.recon.losses import blurred_pixel_loss

ESTIMATES = {
    "none": (),
    "shifts": ("intercepts", "slopes"),
    "zernike": ("zernike_coefficients",),
    "joint": ("zernike_coefficients", "intercepts", "slopes"),
}

# JPGM parameter -> the suffix of its learning rate's setting (``lr_<suffix>``).
LEARNING_RATES = {
    "zernike_coefficients": "zernike",
    "intercepts": "intercepts",
    "slopes": "slopes",
}


AUTO = "auto"

CPU_DEPTH_CHUNK = 16
"""Depths per chunk of ``depth_chunk="auto"`` on a CPU. On 2 CPU cores one paper-size update
(101 depths) took 6.4 s and peaked at 2.78 GB in chunks of 16, against 6.6 s and 5.52 GB with
the whole stack (``python benchmarks/jpgm_update.py --memory 16``)."""


@dataclass(frozen=True)
class OpticsEstimation:
    """Schedule and learning rates of the JPGM events.

    Attributes
    ----------
    estimate : {"none", "shifts", "zernike", "joint"}
        Parameter groups that are estimated.
    start, every, steps : int
        First event after step ``start``, then every ``every`` steps, each ``steps`` inner steps
        (Table S7: 200, 50, 100).
    lr_zernike : float
        Adam learning rate of the Zernike coefficients (waves per step).
    lr_intercepts, lr_slopes : float
        Adam learning rates of ``b_v`` and ``s_v`` (pixels per step).
    p : int
        Pixel-loss exponent of the inner objective (Eq. S23).
    psf_method : {"auto", "mft", "asm"}
        Path of the estimated JPGM (:class:`~fgat.optics.psf.JPGM`): ``"auto"`` takes the matrix
        Fourier transform where :meth:`~fgat.optics.psf.JPGM.crosstalk_bound` allows it, else
        angular-spectrum propagation; ``"mft"`` always takes the faster transform, leaving out
        the light neighbouring lenslets send into a view's crop (that bound says how much).
    identifiability : bool
        At the end of the fit, the standard error of every estimated parameter from the local
        cross-information (Note S4) at the final optics and volume, under the noise level of
        the residual (:func:`fgat.recon.optics_report.identifiability`): logged as
        ``zernike/stderr_c{j}``, ``shift/stderr_b{v}_y``, ..., with ``identifiability.csv`` and
        ``identifiability.png`` among the results.
    stderr_tolerance : float
        A parameter is flagged as poorly determined when its standard error exceeds this
        fraction of the magnitude of its estimate.
    tolerance : float
        Skip what converged optics do not need (0: off, every event runs all its steps). An
        event's inner steps stop once the data loss has improved by less than this fraction
        over the last quarter of the event's steps; an event is quiet when its data loss fell by
        less than this fraction and no parameter moved by more than ``parameter_tolerance``;
        after two quiet events in a row the optics count as converged and no further event
        runs.
    parameter_tolerance : float
        Largest change of any estimated parameter over a quiet event (waves for Zernike
        coefficients, pixels for intercepts and slopes).
    depth_chunk : int or "auto"
        Bound the memory of an inner step (0: off, the whole PSF stack's graph at once): the
        prediction is made without a graph, and the gradient accumulated over chunks of this
        many depths, each chunk's PSFs recomputed with their graph (the same gradient, exactly:
        the prediction is linear in each depth's PSFs; about one more PSF evaluation per step).
        ``"auto"`` (:class:`DepthChunks`): on a GPU the whole stack, halved into chunks each
        time an update runs out of GPU memory; on a CPU chunks of :data:`CPU_DEPTH_CHUNK`.
    blur_px : tuple of float
        Coarse to fine (empty: off): event ``k`` compares the predicted and measured views
        blurred by a Gaussian of standard deviation ``blur_px[k // blur_events]`` pixels, the
        last entry for every later event (e.g. ``(4, 2, 1, 0)``). Blurred views see large
        aberrations through a smoother loss, so the estimate finds the basin of the true
        coefficients before the sharp views refine it. An event counts as quiet only without
        blur.
    blur_events : int
        Events per entry of ``blur_px``.
    blurred_estimate : {"", "none", "shifts", "zernike", "joint"}
        The blurred events estimate those of ``estimate``'s groups that are also this one's
        (``""``: all of ``estimate``'s, every event alike); the sharp events estimate
        ``estimate``'s. A lenslet's shift is a tilt of its
        sub-aperture's wavefront, so the part of an aberration that tilts the sub-apertures
        differently is also a set of shifts (the leakage of Note S5); blurred views see the
        large aberrations but hardly the shifts, and with both free the shifts take up that
        part and hold the Zernike estimate away from the truth. ``"zernike"`` fits the pupil
        through the blurred events and the shifts from the first sharp one on.
    """

    estimate: str = "none"
    start: int = 200
    every: int = 50
    steps: int = 100
    lr_zernike: float = 0.01
    lr_intercepts: float = 0.02
    lr_slopes: float = 0.02
    p: int = 1
    psf_method: str = "auto"
    identifiability: bool = True
    stderr_tolerance: float = 0.5
    tolerance: float = 0.0
    parameter_tolerance: float = 1e-3
    depth_chunk: int | str = 0
    blur_px: tuple[float, ...] = ()
    blur_events: int = 1
    blurred_estimate: str = ""

    def __post_init__(self) -> None:
        if self.estimate not in ESTIMATES:
            raise ValueError(
                f"optics.estimate must be one of {sorted(ESTIMATES)}, got {self.estimate!r}"
            )
        if self.psf_method not in PSF_METHODS:
            raise ValueError(
                f"optics.psf_method must be one of {list(PSF_METHODS)}, got {self.psf_method!r}"
            )
        if self.blurred_estimate and self.blurred_estimate not in ESTIMATES:
            raise ValueError(
                f"optics.blurred_estimate must be '' or one of {sorted(ESTIMATES)}, got "
                f"{self.blurred_estimate!r}"
            )
        if not isinstance(self.blur_events, int) or isinstance(self.blur_events, bool):
            raise ValueError(
                f"optics.blur_events must be a whole number of events, got {self.blur_events!r}"
            )
        if self.every < 1 or self.steps < 1 or self.start < 0 or self.blur_events < 1:
            raise ValueError(
                "optics.start must be >= 0 and optics.every, optics.steps, optics.blur_events >= 1"
            )
        if not isinstance(self.identifiability, bool):
            raise ValueError(
                f"optics.identifiability must be true or false, got {self.identifiability!r}"
            )
        for name in ("tolerance", "parameter_tolerance"):
            value = getattr(self, name)
            if isinstance(value, bool) or not 0 <= value < 1:
                raise ValueError(f"optics.{name} must be a number in [0, 1), got {value!r}")
        if self.depth_chunk != AUTO and (
            isinstance(self.depth_chunk, bool)
            or not (isinstance(self.depth_chunk, int) and self.depth_chunk >= 0)
        ):
            raise ValueError(
                "optics.depth_chunk must be a number of depths >= 0 (0: the whole stack at "
                f"once) or 'auto', got {self.depth_chunk!r}"
            )
        if not isinstance(self.blur_px, (tuple, list)) or any(
            isinstance(b, bool) or not isinstance(b, (int, float)) or not 0 <= b < math.inf
            for b in self.blur_px
        ):
            raise ValueError(
                f"optics.blur_px must be a list of finite blurs >= 0 (pixels), got {self.blur_px!r}"
            )
        if isinstance(self.stderr_tolerance, bool) or not self.stderr_tolerance > 0:
            raise ValueError(
                "optics.stderr_tolerance must be a positive number (a fraction of each "
                f"estimate), got {self.stderr_tolerance!r}"
            )
        if self.enabled and any(self.blur_px) and not self.estimated_at(max(self.blur_px)):
            raise ValueError(
                f"optics.blurred_estimate {self.blurred_estimate!r} leaves the blurred events "
                f"none of optics.estimate {self.estimate!r}'s parameters to estimate"
            )

    @property
    def enabled(self) -> bool:
        return self.estimate != "none"

    def due(self, step: int) -> bool:
        """Whether an event runs after optimizer step ``step`` (1-based count of steps done)."""
        return self.enabled and step > self.start and (step - self.start) % self.every == 0

    def blur_at(self, step: int) -> float:
        """The blur (pixels) of the event after optimizer step ``step`` (see ``blur_px``)."""
        if not self.blur_px:
            return 0.0
        level = max((step - self.start) // self.every - 1, 0) // self.blur_events
        return float(self.blur_px[min(level, len(self.blur_px) - 1)])

    def estimated_at(self, blur_px: float) -> tuple[str, ...]:
        """The JPGM parameters an event with views blurred by ``blur_px`` pixels estimates."""
        groups = ESTIMATES[self.estimate]
        if blur_px > 0 and self.blurred_estimate:
            return tuple(name for name in groups if name in ESTIMATES[self.blurred_estimate])
        return groups

    def optimizer(self, jpgm: JPGM) -> torch.optim.Optimizer:
        """Adam over the estimated groups only; the others stay frozen."""
        groups = [
            {"params": [getattr(jpgm, name)], "lr": getattr(self, f"lr_{LEARNING_RATES[name]}")}
            for name in ESTIMATES[self.estimate]
        ]
        return adam(groups)


class DepthChunks:
    """Depths per chunk of the JPGM updates of one fit (``optics.depth_chunk``), kept from one
    event to the next.

    A number is used as it is. ``"auto"`` starts on a GPU with the whole stack (0, the fastest:
    one paper-size update took 49 ms against 100 ms in chunks of 16 on an H200) and,
    each time an update runs out of GPU memory, retries it with half as many depths per chunk;
    on a CPU it uses chunks of :data:`CPU_DEPTH_CHUNK` (faster and smaller there), or the whole
    stack when it has no more depths than that.

    Parameters
    ----------
    setting : int or "auto"
        ``optics.depth_chunk``.
    n_depths : int
        Depths of the PSF stack.
    device : torch.device or str
        Where the updates run.
    """

    def __init__(self, setting: int | str, n_depths: int, device: torch.device | str) -> None:
        self.adaptive = setting == AUTO and torch.device(device).type == "cuda"
        self.n_depths = int(n_depths)
        if setting != AUTO:
            self.size = int(setting)
        else:
            self.size = 0 if self.adaptive or n_depths <= CPU_DEPTH_CHUNK else CPU_DEPTH_CHUNK

    def shrink(self) -> bool:
        """Halve the depths per chunk after running out of memory; ``False`` when the setting
        is fixed or a chunk is already one depth."""
        if not self.adaptive or self.size == 1:
            return False
        self.size = math.ceil((self.size or self.n_depths) / 2)
        return True


def fitted_update(
    jpgm: JPGM,
    operator: Callable[[Tensor], object],
    volume: Tensor,
    measurement: Tensor,
    p: int,
    mask: Tensor | None,
    chunks: DepthChunks,
    blur_px: float = 0.0,
) -> Tensor:
    """:func:`data_loss_backward` in ``chunks``, retried in smaller chunks while it runs out of
    GPU memory (``"auto"``; a warning says the new size). Returns the loss."""
    while True:
        try:
            return data_loss_backward(
                jpgm, operator, volume, measurement, p, mask, chunks.size, blur_px
            )
        except torch.OutOfMemoryError:
            if not chunks.shrink():
                raise
        jpgm.zero_grad(set_to_none=True)
        if volume.is_cuda:
            torch.cuda.empty_cache()
        warnings.warn(
            f"JPGM update: out of GPU memory; retrying in chunks of {chunks.size} of "
            f"{chunks.n_depths} depths (optics.depth_chunk = 'auto')",
            RuntimeWarning,
            stacklevel=2,
        )


def run_event(
    jpgm: JPGM,
    volume: Tensor,
    measurement: Tensor,
    schedule: OpticsEstimation,
    optimizer: torch.optim.Optimizer,
    operator: Callable[[Tensor], object] | None = None,
    mask: Tensor | None = None,
    chunks: DepthChunks | None = None,
    blur_px: float = 0.0,
) -> dict[str, float]:
    """One JPGM event: ``schedule.steps`` updates of the JPGM parameters estimated at this
    blur (:meth:`OpticsEstimation.estimated_at`).

    Parameters
    ----------
    jpgm : JPGM
        The generator; its estimated parameters are updated in place.
    volume : Tensor
        ``(Z, Y', X')`` current reconstruction (held fixed), on the operator's grid.
    measurement : Tensor
        ``(V, Y, X)`` measured views.
    operator : callable, optional
        ``operator(psf_stack)``: the forward model of a PSF stack ``(V, Z, h, w)`` (e.g. a
        :class:`~fgat.optics.acquisition.MeasuredOperator` with the acquisition's gains and
        guard band); default ``FLFMOperator(psf_stack, volume.shape)``.
    mask : Tensor, optional
        Pixel mask of the data loss, broadcastable to ``(V, Y, X)`` (1 = use).
    chunks : DepthChunks, optional
        Depths per chunk of the updates, shrunk in place on running out of memory (pass the
        same one to every event of a fit); default from ``schedule.depth_chunk``.
    blur_px : float
        Gaussian blur (pixels) of the views in the data loss (``schedule.blur_at``).

    Returns
    -------
    dict
        ``loss_before``, ``loss_after`` (data loss of the first and last inner step),
        ``ms_per_step`` (wall time of one inner step), ``steps`` (inner steps run: fewer than
        ``schedule.steps`` when they stopped on a plateau), ``quiet`` (with
        ``schedule.tolerance``: the event barely changed the loss and the parameters), and
        ``unconverged`` (:func:`still_moving`: parameter name -> entries still moving at full
        speed at the end).
    """
    volume = volume.detach()
    operator = operator or (lambda psf: FLFMOperator(psf, (psf.shape[1], *volume.shape[1:])))
    chunks = chunks or DepthChunks(schedule.depth_chunk, volume.shape[0], volume.device)
    trainable = set(schedule.estimated_at(blur_px))
    for name, parameter in jpgm.named_parameters():
        parameter.requires_grad_(name in trainable)
    losses, history = [], []  # the estimated parameters before each inner step (a few numbers)
    window = max(schedule.steps // 4, 1)
    start = time.perf_counter()
    for _ in range(schedule.steps):
        history.append({name: getattr(jpgm, name).detach().clone() for name in trainable})
        if plateaued(losses, window, schedule.tolerance):
            break
        optimizer.zero_grad(set_to_none=True)
        loss = fitted_update(jpgm, operator, volume, measurement, schedule.p, mask, chunks, blur_px)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"JPGM event: the data loss is {float(loss)} after {len(losses)} inner steps"
            )
        optimizer.step()
        losses.append(float(loss.detach()))
    elapsed = time.perf_counter() - start
    moved = max(
        float((getattr(jpgm, name).detach() - value).abs().max())
        for name, value in history[0].items()
    )
    stalled = len(losses) < schedule.steps
    return {
        "loss_before": losses[0],
        "loss_after": losses[-1],
        "ms_per_step": 1e3 * elapsed / len(losses),
        "steps": len(losses),
        "quiet": schedule.tolerance > 0
        and blur_px == 0
        and moved <= schedule.parameter_tolerance
        and losses[0] - losses[-1] <= schedule.tolerance * abs(losses[0]),
        "unconverged": {} if stalled else still_moving(jpgm, history[-window], optimizer, window),
    }


def data_loss_backward(
    jpgm: JPGM,
    operator: Callable[[Tensor], object],
    volume: Tensor,
    measurement: Tensor,
    p: int,
    mask: Tensor | None = None,
    depth_chunk: int = 0,
    blur_px: float = 0.0,
) -> Tensor:
    """The data loss of ``volume`` under the JPGM's PSFs, its gradient accumulated into the
    JPGM parameters' ``.grad`` (none when the loss is not finite); returns the loss (no graph).

    With ``depth_chunk`` the prediction ``A(H) V = sum_c A(H_c) V_c`` is made without a graph;
    ``g = dL / d(prediction)`` is taken there, and each chunk ``c`` of depths contributes
    ``<g, d(A(H_c) V_c) / d theta>`` with only its own PSFs' graph alive: the same gradient
    (the prediction is linear in each depth's PSFs and volume slice) at the memory of one chunk.
    With ``blur_px`` the loss compares blurred views
    (:func:`~fgat.recon.losses.blurred_pixel_loss`).
    """
    if not depth_chunk:
        loss = blurred_pixel_loss(operator(jpgm()).forward(volume), measurement, p, mask, blur_px)
        if torch.isfinite(loss):
            loss.backward()
        return loss.detach()
    with torch.no_grad():
        prediction = operator(jpgm()).forward(volume)
    prediction.requires_grad_(True)
    loss = blurred_pixel_loss(prediction, measurement, p, mask, blur_px)
    if not torch.isfinite(loss):
        return loss.detach()
    (grad,) = torch.autograd.grad(loss, prediction)
    for begin in range(0, volume.shape[0], depth_chunk):
        depths = slice(begin, begin + depth_chunk)
        operator(jpgm(depths)).forward(volume[depths]).backward(grad)
    return loss.detach()


def plateaued(losses: list[float], window: int, tolerance: float) -> bool:
    """Whether the data loss improved by at most ``tolerance`` (relative) over the last
    ``window`` inner steps; never with ``tolerance`` 0."""
    if tolerance <= 0 or len(losses) <= window:
        return False
    earlier = losses[-window - 1]
    return earlier - losses[-1] <= tolerance * abs(earlier)


SATURATION = 0.8  # fraction of the largest Adam motion (lr per step) that counts as still moving


def still_moving(
    jpgm: JPGM, before: dict[str, Tensor], optimizer: torch.optim.Optimizer, window: int
) -> dict[str, int]:
    """How many entries of each estimated parameter were still moving at full speed.

    Adam moves a parameter by at most about its learning rate per step; an entry that moved by
    more than ``SATURATION x lr x window`` over the last ``window`` inner steps of an event was
    still being pushed the same way at every step, so its value is where the step budget ran
    out, not an estimate (e.g. every shift ending at exactly ``lr x steps``).

    Parameters
    ----------
    before : dict
        Parameter name -> its value ``window`` steps before the end of the event.

    Returns
    -------
    dict
        Parameter name -> number of entries still moving (names with none are left out).
    """
    rates = {id(p): group["lr"] for group in optimizer.param_groups for p in group["params"]}
    counts = {}
    for name, start in before.items():
        parameter = getattr(jpgm, name)
        moved = (parameter.detach() - start).abs()
        count = int((moved >= SATURATION * rates[id(parameter)] * window).sum())
        if count:
            counts[name] = count
    return counts


def remove_scene_gauge(differences: Tensor, offsets: Tensor) -> Tensor:
    """Per-view shift differences without the part that a change of the scene reproduces exactly.

    Shifting every view's PSF by a common ``t`` is indistinguishable from translating the scene
    laterally by ``-t``, and shifting each view along its lenslet's offset from the optical axis,
    ``alpha (c_v - c_0)``, from moving it along z (parallax); for slopes the same two patterns are
    a shear and an axial stretch of the scene. No reconstruction can tell these apart from the
    scene, so estimated and true shifts are compared after removing the least-squares fit
    ``t + alpha (c_v - c_0)`` from their difference.

    Parameters
    ----------
    differences : Tensor
        ``(V, 2)`` estimated minus true intercepts (or slopes), (row, col) pixels.
    offsets : Tensor
        ``(V, 2)`` lenslet centres minus the on-axis lenslet's, ``c_v - c_0``, pixels.

    Returns
    -------
    Tensor
        ``(V, 2)`` residual differences.
    """
    differences = differences.detach().double()
    offsets = offsets.detach().to(differences)
    n = differences.shape[0]
    design = torch.zeros(n, 2, 3, dtype=differences.dtype, device=differences.device)
    design[:, 0, 0] = design[:, 1, 1] = 1.0
    design[:, :, 2] = offsets
    fit = torch.linalg.lstsq(design.reshape(2 * n, 3), differences.reshape(2 * n, 1)).solution
    return (differences.reshape(-1) - (design.reshape(2 * n, 3) @ fit).reshape(-1)).reshape(n, 2)


def psf_errors(psf: Tensor, truth: Tensor, name: str) -> dict[str, float]:
    """Relative L2 distance ``||h - h_gt|| / ||h_gt||`` of a PSF stack ``(V, Z, h, w)`` to the
    truth: the whole stack as ``name`` and each view as ``{name}_view{v}``."""
    difference = (psf.to(truth) - truth).flatten(1).norm(dim=1)
    reference = truth.flatten(1).norm(dim=1).clamp(min=1e-12)
    metrics = {name: float(difference.norm() / reference.norm())}
    metrics.update(
        {f"{name}_view{v}": float(e) for v, e in enumerate((difference / reference).tolist())}
    )
    return metrics
