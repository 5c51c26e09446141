"""Densification and pruning of the Gaussian set (end of Note S3.5.2, after 3D Gaussian splatting).

A :class:`DensificationStrategy` accumulates the norm of each Gaussian's positional gradient
after every backward pass; every ``interval`` steps between ``start`` and ``stop`` it clones
small Gaussians and splits large ones whose mean gradient exceeds ``grad_threshold``, and prunes
Gaussians whose intensity has vanished next to the brightest Gaussian inside the field of view
(:func:`pruned_set`: the guard band's Gaussians do not set the scale, and the field never
empties). Intensities add up in the rendered volume (Eq. S16), so a
clone and its original, and the two children of a split, each get half the intensity (as in
R2-Gaussian's density-based densification). The pure functions :func:`select_gaussians` and
:func:`append_gaussians` change a cloud's parameters and their Adam moments together, so the
optimizer state stays aligned with the Gaussians it belongs to.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from fgat._core.validation import require, require_non_negative, require_positive
from fgat.gaussians.cloud import (
    PARAMETER_NAMES,
    GaussianCloud,
    inverse_sigmoid,
    inverse_softplus,
)
from fgat.gaussians.rotation import quaternion_to_rotation

SPLIT_SHRINK = 1.6  # scale divisor of the two Gaussians a split makes (3D Gaussian splatting)


def _replace(
    cloud: GaussianCloud,
    optimizer: torch.optim.Optimizer | None,
    name: str,
    values: Tensor,
    moments,
) -> None:
    """Swap parameter ``name`` for ``values`` and transform its Adam moments with ``moments``."""
    old = getattr(cloud, name)
    new = nn.Parameter(values.detach().contiguous())
    setattr(cloud, name, new)
    if optimizer is None:
        return
    for group in optimizer.param_groups:
        for i, parameter in enumerate(group["params"]):
            if parameter is old:
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state:
                    for key in ("exp_avg", "exp_avg_sq"):
                        if key in state:
                            state[key] = moments(state[key])
                    optimizer.state[new] = state


def select_gaussians(
    cloud: GaussianCloud, optimizer: torch.optim.Optimizer | None, keep: Tensor
) -> None:
    """Keep the Gaussians where ``keep`` (bool ``(N,)``) is true, parameters and Adam moments
    alike."""
    for name in PARAMETER_NAMES:
        _replace(cloud, optimizer, name, getattr(cloud, name)[keep], lambda m: m[keep])


def append_gaussians(
    cloud: GaussianCloud, optimizer: torch.optim.Optimizer | None, raw: dict[str, Tensor]
) -> None:
    """Append Gaussians given by raw parameters (``PARAMETER_NAMES`` -> ``(M, ...)``); their Adam
    moments start at zero."""
    for name in PARAMETER_NAMES:
        extra = raw[name].to(getattr(cloud, name))
        _replace(
            cloud,
            optimizer,
            name,
            torch.cat([getattr(cloud, name).detach(), extra]),
            lambda m, extra=extra: torch.cat([m, torch.zeros_like(extra)]),
        )


@dataclass(frozen=True)
class Densification:
    """When and how the Gaussian set grows and shrinks (settings; the state is
    :class:`DensificationStrategy`'s).

    Attributes
    ----------
    enabled : bool
        Off: the set never changes.
    start, stop, interval : int
        Densify after steps ``start, start + interval, ...`` below ``stop``.
    grad_threshold : float
        Mean positional-gradient norm (loss per voxel of displacement) above which a Gaussian
        is cloned or split; the default suits the MAE of max-normalised views (Eq. S23, p = 1),
        where it selects roughly the top tenth of the Gaussians.
    split_scale : float
        Gaussians whose largest scale exceeds this many lateral voxels are split, smaller ones
        cloned.
    min_intensity : float
        Prune Gaussians whose intensity is below this fraction of the largest intensity of the
        Gaussians inside the field of view (the guard band left out): the scene's own intensity
        scale in the fit's units, so a measurement in counts and a normalised one prune alike.
    min_gaussians : int
        Pruning never leaves fewer Gaussians than this inside the field of view (nor fewer than
        were there): the brightest of those it would remove stay.
    max_gaussians : int
        No growth beyond this count.
    stable_fraction : float
        Stop densifying for good once ``stable_events`` events in a row each cloned, split and
        pruned together at most this fraction of the Gaussians (the count has settled); 0
        never stops before ``stop``.
    stable_events : int
        Events in a row that must be that quiet.
    seed : int
        Seed of the split children's positions.

    Raises
    ------
    ValueError
        A field out of its range, naming it (``densification.interval must be ...``).
    """

    enabled: bool = True
    start: int = 100
    stop: int = 1500
    interval: int = 100
    grad_threshold: float = 5e-6
    split_scale: float = 2.0
    min_intensity: float = 0.01
    min_gaussians: int = 100
    max_gaussians: int = 200_000
    stable_fraction: float = 0.0
    stable_events: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        require(self.start >= 0, "densification.start", self.start, "a step >= 0")
        require(
            self.interval >= 1,
            "densification.interval",
            self.interval,
            "a positive number of steps",
        )
        require(
            self.stop >= self.start,
            "densification.stop",
            self.stop,
            f">= densification.start ({self.start})",
        )
        require(
            self.max_gaussians >= 1,
            "densification.max_gaussians",
            self.max_gaussians,
            "a positive integer",
        )
        require(
            0 <= self.min_intensity < 1,
            "densification.min_intensity",
            self.min_intensity,
            "a fraction of the largest intensity in [0, 1)",
        )
        require(
            self.min_gaussians >= 1,
            "densification.min_gaussians",
            self.min_gaussians,
            "a positive integer (Gaussians kept inside the field of view)",
        )
        require(
            0 <= self.stable_fraction < 1,
            "densification.stable_fraction",
            self.stable_fraction,
            "a fraction of the Gaussian count in [0, 1) (0: never stop early)",
        )
        require(
            self.stable_events >= 1,
            "densification.stable_events",
            self.stable_events,
            "a positive number of events",
        )
        require_non_negative("densification", grad_threshold=self.grad_threshold)
        require_positive("densification", split_scale=self.split_scale)

    def due(self, step: int) -> bool:
        """Whether the set changes after optimizer step ``step`` (1-based count of steps done)."""
        return (
            self.enabled
            and self.start <= step < self.stop
            and (step - self.start) % self.interval == 0
        )


class DensificationStrategy:
    """:class:`Densification` applied to a cloud: the positional-gradient statistics since the
    last change, the change itself, and whether the count has settled.

    Parameters
    ----------
    settings : Densification
        When and how.
    guard_px : int
        The cloud's grid is the field of view padded laterally by this many voxels on each
        side (the guard band, :class:`~fgat.optics.acquisition.MeasuredOperator`); 0: the grid
        is the field.

    Attributes
    ----------
    stopped_at : int or None
        The step after which densification stopped because the count settled
        (``stable_fraction``), or None.
    """

    def __init__(self, settings: Densification, guard_px: int = 0) -> None:
        self.settings = settings
        self.guard_px = int(guard_px)
        self._grad_sum: Tensor | None = None
        self._grad_count: Tensor | None = None
        self.quiet_events = 0
        self.stopped_at: int | None = None

    def state_dict(self) -> dict:
        """The accumulated statistics (``None`` before the first backward pass after a change)
        and the settling state."""
        return {
            "grad_sum": self._grad_sum,
            "grad_count": self._grad_count,
            "quiet_events": self.quiet_events,
            "stopped_at": self.stopped_at,
        }

    def load_state_dict(self, state: dict, device: torch.device | str | None = None) -> None:
        """Restore :meth:`state_dict` (the statistics moved to ``device``, when given)."""
        self._grad_sum, self._grad_count = (
            None if state[key] is None else state[key].to(device)
            for key in ("grad_sum", "grad_count")
        )
        self.quiet_events = state.get("quiet_events", 0)
        self.stopped_at = state.get("stopped_at")

    @property
    def active(self) -> bool:
        """Enabled and not stopped on a settled count."""
        return self.settings.enabled and self.stopped_at is None

    def update_statistics(self, cloud: GaussianCloud) -> None:
        """Accumulate each Gaussian's positional-gradient norm (call after backward)."""
        grad = cloud.means.grad
        if not self.active or grad is None:
            return
        norm = grad.detach().norm(dim=1) * cloud.unit  # per voxel of displacement
        if self._grad_sum is None or self._grad_sum.shape != norm.shape:
            self._grad_sum, self._grad_count = torch.zeros_like(norm), torch.zeros_like(norm)
        self._grad_sum += norm
        self._grad_count += (norm > 0).to(norm.dtype)

    def step(
        self, cloud: GaussianCloud, optimizer: torch.optim.Optimizer | None, step: int
    ) -> dict[str, int] | None:
        """Densify and prune when ``step`` is due (call after the optimizer step); what changed
        (with ``stopped_at_step`` when this event settled the count), or None."""
        if not self.active or not self.settings.due(step) or self._grad_sum is None:
            return None
        before = cloud.count
        changes = self.densify_and_prune(cloud, optimizer)
        changed = changes["cloned"] + changes["split"] + changes["pruned"]
        settled = changed <= self.settings.stable_fraction * before
        self.quiet_events = self.quiet_events + 1 if settled else 0
        if self.settings.stable_fraction > 0 and self.quiet_events >= self.settings.stable_events:
            self.stopped_at = step
            self._grad_sum = self._grad_count = None
            changes["stopped_at_step"] = step
        return changes

    def densify_and_prune(
        self, cloud: GaussianCloud, optimizer: torch.optim.Optimizer | None
    ) -> dict[str, int]:
        """Clone, split, then prune; resets the gradient statistics."""
        mean_grad = self._grad_sum / self._grad_count.clamp(min=1)
        settings = self.settings
        candidates = mean_grad >= settings.grad_threshold
        room = max(0, settings.max_gaussians - cloud.count)
        if int(candidates.sum()) > room:  # keep the strongest when capped
            order = torch.argsort(mean_grad, descending=True)
            capped = torch.zeros_like(candidates)
            capped[order[:room]] = True
            candidates &= capped
        large = cloud.scales.detach().amax(dim=1) > settings.split_scale * cloud.unit
        clone, split = candidates & ~large, candidates & large
        n_split = int(split.sum())
        # Intensities add up in a density volume: a clone and its original share the intensity.
        halved = inverse_softplus(cloud.intensities.detach() / 2)
        with torch.no_grad():
            cloud.raw_intensities[clone] = halved[clone]
        new = {name: getattr(cloud, name).detach()[clone] for name in PARAMETER_NAMES}
        if n_split:
            new = {
                name: torch.cat([new[name], part])
                for name, part in self._split(cloud, split, halved).items()
            }
        start_count = cloud.count
        append_gaussians(cloud, optimizer, new)
        keep = torch.ones(cloud.count, dtype=torch.bool, device=cloud.means.device)
        keep[:start_count][split] = False  # a split Gaussian is replaced by its two children
        alive = keep.clone()
        keep = pruned_set(
            cloud.intensities.detach(),
            alive,
            in_field(cloud, self.guard_px),
            settings.min_intensity,
            settings.min_gaussians,
        )
        select_gaussians(cloud, optimizer, keep)
        self._grad_sum = self._grad_count = None
        return {
            "cloned": int(clone.sum()),
            "split": n_split,
            "pruned": int((alive & ~keep).sum()),
            "count": cloud.count,
        }

    def _split(self, cloud: GaussianCloud, split: Tensor, halved: Tensor) -> dict[str, Tensor]:
        """Two children per selected Gaussian: means drawn from it, scales divided by 1.6, each
        with half the intensity (``halved``: raw half intensities of every Gaussian)."""
        generator = torch.Generator(device="cpu").manual_seed(self.settings.seed)
        scales = cloud.scales.detach()[split]
        rotation = quaternion_to_rotation(cloud.quaternions.detach()[split])
        samples = torch.randn((2, *scales.shape), generator=generator).to(scales) * scales
        means = (cloud.means.detach()[split] + (rotation @ samples[..., None]).squeeze(-1)).reshape(
            -1, 3
        )
        low, high = cloud.scale_range
        child = (scales / SPLIT_SHRINK / cloud.unit - low) / (high - low)
        return {
            "means": means,
            "raw_scales": inverse_sigmoid(child).repeat(2, 1),
            "raw_quats": cloud.raw_quats.detach()[split].repeat(2, 1),
            "raw_intensities": halved[split].repeat(2),
        }


def in_field(cloud: GaussianCloud, guard_px: int) -> Tensor:
    """Whether each Gaussian's mean lies in the field of view (bool ``(N,)``): inside the
    cloud's grid and outside its lateral guard band of ``guard_px`` voxels."""
    index = (cloud.means.detach() - cloud.origin) / cloud.voxel_size  # voxels from the corner
    low = torch.tensor([0, guard_px, guard_px], dtype=index.dtype, device=index.device)
    high = torch.tensor(cloud.shape, dtype=index.dtype, device=index.device) - low
    return ((index >= low) & (index < high)).all(dim=1)


def pruned_set(
    intensities: Tensor, alive: Tensor, inside: Tensor, min_intensity: float, floor: int
) -> Tensor:
    """The Gaussians a pruning keeps (bool ``(N,)``).

    Of the ``alive`` ones, those whose intensity reaches ``min_intensity`` times the largest
    intensity of the alive Gaussians ``inside`` the field of view (of all alive ones when none
    is inside). The guard band's Gaussians see the views through a fraction of their light and
    carry larger intensities for the light they explain; they neither set the scale nor, by
    it, prune the field. Then, when fewer than ``min(floor, alive inside)`` inside Gaussians
    would stay, the brightest of the inside ones removed stay too: a pruning never empties the
    field of view.

    Parameters
    ----------
    intensities : Tensor
        ``(N,)`` non-negative intensities (any units: the rule is scale-free).
    alive : Tensor
        ``(N,)`` bool, the candidates (e.g. not replaced by a split's children).
    inside : Tensor
        ``(N,)`` bool, in the field of view (:func:`in_field`).
    min_intensity : float
        Fraction of the field's largest intensity below which a Gaussian goes.
    floor : int
        Inside Gaussians that always stay (or all of them when fewer).
    """
    scope = alive & inside if bool((alive & inside).any()) else alive
    scale = intensities[scope].max() if bool(scope.any()) else intensities.new_zeros(())
    keep = alive & (intensities >= min_intensity * scale)
    missing = min(floor, int((alive & inside).sum())) - int((keep & inside).sum())
    if missing > 0:
        removed = alive & inside & ~keep
        ranked = torch.where(removed, intensities, torch.full_like(intensities, -torch.inf))
        keep[torch.topk(ranked, missing).indices] = True
    return keep
