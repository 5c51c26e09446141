"""Pixels held out of a fit: a split of the measurement whose loss, never fitted, tells what a
reconstruction learned about the object from what it learned about the noise."""

from __future__ import annotations

import torch
from torch import Tensor


def holdout_split(
    mask: Tensor | None, shape: tuple[int, ...], fraction: float, seed: int, device=None
) -> tuple[Tensor, Tensor]:
    """Split the measurement's pixels into fitted and held-out ones.

    Parameters
    ----------
    mask : Tensor or None
        ``(V, Y, X)`` pixel mask of the measurement (1 = use), ``None`` for all pixels.
    shape : tuple of int
        ``(V, Y, X)`` of the measurement.
    fraction : float
        Share of the pixels held out, in ``(0, 1)``, drawn independently per pixel.
    seed : int
        Seed of the draw (the same split on a resumed run).

    Returns
    -------
    (fit, held) : (Tensor, Tensor)
        Float masks ``(V, Y, X)``: ``mask`` without and restricted to the held-out pixels.
    """
    generator = torch.Generator().manual_seed(int(seed))
    held = (torch.rand(shape, generator=generator) < fraction).to(device=device)
    base = torch.ones(shape, device=device) if mask is None else mask.to(device)
    return base * ~held, base * held
