"""The reconstruction layer, plain PyTorch (no Lightning): RL and SHB deconvolution
(:mod:`fgat.recon.deconvolution`), losses and metrics, the JPGM optics estimation, and the
4DGAT engines: a :class:`Scene`, the static stage (:class:`StaticReconstruction`) and the
dynamic stage (:class:`DynamicReconstruction`), each with ``step()``, ``evaluate()`` and
``state_dict()``.

The engines are exported lazily, so that importing one module of this layer (e.g. the
metrics) does not import them all.
"""

import importlib

_EXPORTS = {
    "DynamicReconstruction": "fgat.recon.dynamic",
    "DynamicSettings": "fgat.recon.dynamic",
    "StaticResult": "fgat.recon.dynamic",
    "load_static": "fgat.recon.dynamic",
    "HoldoutStop": "fgat.recon.plateau",
    "Plateau": "fgat.recon.plateau",
    "Scene": "fgat.recon.scene",
    "phantom_scene": "fgat.recon.scene",
    "StaticReconstruction": "fgat.recon.static",
    "StaticSettings": "fgat.recon.static",
    "StepResult": "fgat.recon.static",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'fgat.recon' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
