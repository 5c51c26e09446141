"""Richardson-Lucy and scaled-heavy-ball deconvolution: this public path re-exports
:mod:`fgat.recon.deconvolution`, where the code lives."""

from fgat.recon.deconvolution import (  # noqa: F401
    DeconvolutionStep,
    deconvolve,
    iterate_deconvolution,
    momentum,
    pixel_weights,
    poisson_cost,
)

__all__ = [
    "momentum",
    "poisson_cost",
    "DeconvolutionStep",
    "iterate_deconvolution",
    "pixel_weights",
    "deconvolve",
]
