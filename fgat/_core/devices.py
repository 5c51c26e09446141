"""Choosing where tensors live (``device="auto"`` picks CUDA when present) and which kernels can
run on them."""

from __future__ import annotations

import collections
import functools
import os
import re

import torch
from torch.utils._python_dispatch import TorchDispatchMode

DEVICES = "auto, cpu, cuda, cuda:N or mps"


def resolve_device(name: str | torch.device = "auto", *, option: str = "--device") -> torch.device:
    """The device a user named, checked to exist on this machine.

    Parameters
    ----------
    name : str or torch.device
        ``"auto"`` (``cuda`` when a GPU is visible, else ``cpu``), ``"cpu"``, ``"cuda"``,
        ``"cuda:N"`` or ``"mps"``.
    option : str
        What to call the setting in errors (an option or a config field).

    Raises
    ------
    ValueError
        One line naming ``option`` and ``name``: an unknown name (listing the valid ones), or a
        device this machine does not have.
    """
    text = str(name).strip().lower()
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if text == "cpu":
        return torch.device("cpu")
    match = re.fullmatch(r"cuda(?::(\d+))?", text)
    if match:
        if not torch.cuda.is_available():
            build = (
                "CPU build"
                if torch.version.cuda is None
                else f"CUDA {torch.version.cuda} build, no GPU visible"
            )
            raise ValueError(
                f"{option} {name}: CUDA is not available on this machine "
                f"(torch {torch.__version__} {build})"
            )
        index = int(match[1] or 0)
        count = torch.cuda.device_count()
        if index >= count:
            raise ValueError(
                f"{option} {name}: this machine has {count} CUDA device(s), "
                f"cuda:0 to cuda:{count - 1}"
            )
        return torch.device(text)
    if text == "mps":
        if not torch.backends.mps.is_available():
            raise ValueError(f"{option} {name}: Apple MPS is not available on this machine")
        return torch.device("mps")
    raise ValueError(f"{option} {name!r}: unknown device; expected {DEVICES}")


@functools.lru_cache(maxsize=128)
def constant(values: tuple, device: torch.device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``torch.tensor(values)`` on ``device``, made once per values, device and type.

    For small fixed tensors (index pairs, grid sizes, voxel sizes) used at every step: making
    them anew is a copy from the host each time, which on a GPU costs more than the arithmetic
    it serves. The result is shared: never modify it in place. It is made outside inference
    mode, so that one first made during a validation can be saved for a later backward.
    """
    with torch.inference_mode(False):
        return torch.tensor(values, device=device, dtype=dtype)


@functools.cache
def triton_installed() -> bool:
    """Whether Triton can be imported (it comes with PyTorch's CUDA builds on Linux)."""
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


TRITON_BACKENDS = ("auto", "torch", "triton")
"""Back-ends of the operations with Triton kernels: ``torch`` (any device and type), ``triton``
(float32 on a GPU, or on the CPU in Triton's interpreter), ``auto`` (``triton`` for float32 on a
GPU where Triton is installed)."""


def use_triton(backend: str, tensor: torch.Tensor, what: str) -> bool:
    """Whether an operation asked for ``backend`` (one of :data:`TRITON_BACKENDS`) runs its
    Triton kernels on ``tensor`` (``what`` names it in errors).

    Raises
    ------
    ValueError
        An unknown back-end, or ``triton`` asked for where it cannot run (Triton missing, not
        float32, not on a GPU outside Triton's interpreter ``TRITON_INTERPRET=1``).
    """
    if backend not in TRITON_BACKENDS:
        raise ValueError(f"backend must be one of {TRITON_BACKENDS}, got {backend!r}")
    if backend == "torch":
        return False
    if backend == "auto":
        return tensor.is_cuda and tensor.dtype == torch.float32 and triton_installed()
    if not triton_installed():
        raise ValueError(
            "backend='triton' needs Triton, which is not installed: pip install 'fgat[gpu-kernels]'"
        )
    if tensor.dtype != torch.float32:
        raise ValueError(f"backend='triton' takes float32 {what}, got {tensor.dtype}")
    if not tensor.is_cuda and os.environ.get("TRITON_INTERPRET") != "1":
        raise ValueError(
            f"backend='triton' runs on a GPU (or on the CPU in Triton's interpreter, "
            f"TRITON_INTERPRET=1); the {what} are on {tensor.device}"
        )
    return True


def triton_fits(backend: str, tensor: torch.Tensor, what: str, operation: str, needs) -> bool:
    """:func:`use_triton`, and whether a call fits the kernels: ``needs()`` maps what they need
    to whether this call has it (asked only when ``backend`` allows Triton). ``auto`` takes the
    PyTorch path where something is missing; ``triton`` is refused with a ``ValueError`` naming
    ``operation`` and what is missing."""
    if not use_triton(backend, tensor, what):
        return False
    missing = [need for need, ok in needs().items() if not ok]
    if missing and backend == "triton":
        raise ValueError(f"{operation} needs {', '.join(missing)}")
    return not missing


def functorch_wrapped(*tensors: torch.Tensor) -> bool:
    """Whether a functorch transform (``vmap``, ``jvp``, ``grad``) wraps any of ``tensors``:
    then only PyTorch operations apply to them, no custom kernel."""
    return any(torch._C._functorch.is_functorch_wrapped_tensor(t) for t in tensors)


def adam(groups: list[dict], **options) -> torch.optim.Adam:
    """``torch.optim.Adam`` over parameter ``groups`` with its fused kernel where this PyTorch has
    one for their device (CUDA; CPU from torch 2.4), else its default implementation.

    Fused, a step is one update per parameter group instead of a dozen multi-tensor operations
    and a read of each parameter's step count back to the host (what a GPU step waits for); the
    update is the same to rounding. ``options`` are Adam's (``lr``, ``eps``, ...).
    """
    try:
        return torch.optim.Adam(groups, fused=True, **options)
    except RuntimeError:  # no fused kernel for these parameters' device in this PyTorch
        return torch.optim.Adam(groups, **options)


HOST_READS = ("aten::_local_scalar_dense", "aten::is_nonzero")
"""Operations that hand a tensor's value to the host (``.item()``, ``float``, ``bool``): on a
GPU each waits for every kernel queued before it."""


class DispatchCount(TorchDispatchMode):
    """Count the PyTorch operations dispatched while open, backward passes included.

    On a GPU each operation costs host time to record and launch whatever its size, so a step
    whose count is high is bound by the host before the arithmetic; the count is the same on
    any device, so a CPU measures it. ``ops`` maps operation names to counts; ``total`` sums
    them and ``host_reads`` counts :data:`HOST_READS`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.ops: collections.Counter[str] = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func._schema.name] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def host_reads(self) -> int:
        return sum(self.ops[name] for name in HOST_READS)
