"""The lenslet fields of the JPGM's fast path as Triton kernels: the GPU path of
:class:`fgat.optics.psf._DefocusedField`.

The fields ``u = A exp(i (Phi + z D - q f^2))``, ``f = a0 + z a1 + z^2 a2``, of every view at
every depth are a ``(V, Z, B, B)`` complex stack computed from six ``(V, 1, B, B)`` maps. As a
chain of PyTorch operations each step reads and writes a stack-sized intermediate; here one
program takes a block of ``BLOCK`` pixels of one view, loads the maps there once and walks the
depths, so the forward writes the stack once and reads nothing stack-sized. The backward walks
the same blocks, recomputes the phase and the field at each depth instead of reading a saved
stack (which it therefore does not keep), forms ``dL/dphase = Im(g) Re(u) - Re(g) Im(u)`` from
the incoming gradient ``g`` and accumulates the five moments ``sum_z z^k dL/dphase`` (``k = 0,
1``) and ``-2 q sum_z z^k f dL/dphase`` (``k = 0, 1, 2``) in registers: it reads the gradient
once. The arithmetic follows the PyTorch path operation for operation (``fma`` where it uses
``addcmul``) and the sines and cosines are libdevice's precise ones (the phases reach hundreds of
radians), so the two agree to float32 rounding. Float32 only (the PyTorch path serves other
types). Triton's interpreter (``TRITON_INTERPRET=1``) runs the same kernels on CPU tensors, which
is how the tests compare them with the PyTorch path on a machine without a GPU.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor
from triton.language.extra import libdevice

BLOCK = 256
"""Pixels of one view per program."""


@triton.jit
def _maps(amplitude, zernike, defocus, a0, a1, a2, at, inside):
    """The six maps at the flat pixel indices ``at`` (zero outside the box)."""
    return (
        tl.load(amplitude + at, mask=inside, other=0.0),
        tl.load(zernike + at, mask=inside, other=0.0),
        tl.load(defocus + at, mask=inside, other=0.0),
        tl.load(a0 + at, mask=inside, other=0.0),
        tl.load(a1 + at, mask=inside, other=0.0),
        tl.load(a2 + at, mask=inside, other=0.0),
    )


@triton.jit
def _field(amplitude, zernike, defocus, a0, a1, a2, z, neg_quartic, LIBDEVICE: tl.constexpr):
    """Squared local frequency ``f = a0 + z (a1 + z a2)`` and the field's real and imaginary
    parts at depth ``z``, in the PyTorch path's order of operations. The cosine and sine are
    libdevice's when compiled (``tl.cos`` may lower to an approximation that is off by far more
    than float32 rounding at these phases) and NumPy's in the interpreter, which has no
    libdevice."""
    frequency = tl.fma(z, tl.fma(z, a2, a1), a0)
    phase = tl.fma(neg_quartic, frequency * frequency, tl.fma(z, defocus, zernike))
    if LIBDEVICE:
        cos, sin = libdevice.cos(phase), libdevice.sin(phase)
    else:
        cos, sin = tl.cos(phase), tl.sin(phase)
    return frequency, amplitude * cos, amplitude * sin


@triton.jit
def _field_kernel(
    field,
    amplitude,
    zernike,
    defocus,
    a0,
    a1,
    a2,
    depths,
    neg_quartic,
    pixels,
    n_depths,
    BLOCK: tl.constexpr,
    LIBDEVICE: tl.constexpr,
):
    """One block of one view's pixels at every depth into ``field``, the interleaved real and
    imaginary parts ``(V, Z, pixels, 2)`` of the complex stack."""
    view = tl.program_id(1).to(tl.int64)
    offsets = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    inside = offsets < pixels
    amp, phi, d, c0, c1, c2 = _maps(
        amplitude, zernike, defocus, a0, a1, a2, view * pixels + offsets, inside
    )
    parts = tl.arange(0, 2)[None, :]
    k = 0
    while k < n_depths:  # not range(n_depths), which Triton 3.6's interpreter fails on
        _, real, imag = _field(amp, phi, d, c0, c1, c2, tl.load(depths + k), neg_quartic, LIBDEVICE)
        plane = (view * n_depths + k) * pixels
        tl.store(
            field + 2 * (plane + offsets)[:, None] + parts,
            tl.join(real, imag),
            mask=inside[:, None],
        )
        k += 1


@triton.jit
def _moments_kernel(
    moments,
    grad,
    amplitude,
    zernike,
    defocus,
    a0,
    a1,
    a2,
    depths,
    neg_quartic,
    pixels,
    n_views,
    n_depths,
    BLOCK: tl.constexpr,
    LIBDEVICE: tl.constexpr,
):
    """One block of one view's pixels: the incoming gradient ``grad`` (interleaved like the
    field) reduced over the depths into the five moments ``(5, V, pixels)``."""
    view = tl.program_id(1).to(tl.int64)
    offsets = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    inside = offsets < pixels
    amp, phi, d, c0, c1, c2 = _maps(
        amplitude, zernike, defocus, a0, a1, a2, view * pixels + offsets, inside
    )
    parts = tl.arange(0, 2)[None, :]
    d_sum = tl.zeros((BLOCK,), tl.float32)
    d_z = tl.zeros((BLOCK,), tl.float32)
    w_sum = tl.zeros((BLOCK,), tl.float32)
    w_z = tl.zeros((BLOCK,), tl.float32)
    w_zz = tl.zeros((BLOCK,), tl.float32)
    k = 0
    while k < n_depths:  # as in _field_kernel
        z = tl.load(depths + k)
        frequency, real, imag = _field(amp, phi, d, c0, c1, c2, z, neg_quartic, LIBDEVICE)
        plane = (view * n_depths + k) * pixels
        g = tl.load(grad + 2 * (plane + offsets)[:, None] + parts, mask=inside[:, None], other=0.0)
        g_real, g_imag = tl.split(g)
        d_phase = g_imag * real - g_real * imag
        weighted = frequency * d_phase
        d_sum += d_phase
        d_z += z * d_phase
        w_sum += weighted
        w_z += z * weighted
        w_zz += (z * z) * weighted
        k += 1
    scale = 2.0 * neg_quartic  # d phase / d f = -2 q f
    tl.store(moments + view * pixels + offsets, d_sum, mask=inside)
    tl.store(moments + (n_views + view) * pixels + offsets, d_z, mask=inside)
    tl.store(moments + (2 * n_views + view) * pixels + offsets, w_sum * scale, mask=inside)
    tl.store(moments + (3 * n_views + view) * pixels + offsets, w_z * scale, mask=inside)
    tl.store(moments + (4 * n_views + view) * pixels + offsets, w_zz * scale, mask=inside)


_COMPILED = isinstance(_field_kernel, triton.runtime.JITFunction)
"""Whether the kernels are compiled (else Triton's interpreter runs them, ``TRITON_INTERPRET=1``
when this module was imported)."""


def _flat_maps(maps: tuple[Tensor, ...]) -> tuple[tuple[Tensor, ...], tuple[int, ...]]:
    """The maps broadcast to their common shape ``(V, 1, H, W)``, contiguous, and that shape."""
    shape = torch.broadcast_shapes(*(m.shape for m in maps))
    if len(shape) != 4 or shape[1] != 1:
        raise ValueError(f"the maps must broadcast to (V, 1, H, W), got {tuple(shape)}")
    for m in maps:
        if m.dtype != torch.float32:
            raise TypeError(f"the Triton lenslet fields take float32 maps, got {m.dtype}")
    return tuple(m.expand(shape).contiguous() for m in maps), tuple(shape)


def _grid(shape: tuple[int, ...]) -> tuple[int, int]:
    return triton.cdiv(shape[2] * shape[3], BLOCK), shape[0]


def defocused_field(
    amplitude: Tensor,
    zernike: Tensor,
    defocus: Tensor,
    a0: Tensor,
    a1: Tensor,
    a2: Tensor,
    depths: Tensor,
    quartic: float,
) -> Tensor:
    """The lenslet fields ``A exp(i (Phi + z D - q (a0 + z a1 + z^2 a2)^2))``.

    Parameters
    ----------
    amplitude, zernike, defocus, a0, a1, a2 : Tensor
        float32 maps broadcasting to ``(V, 1, H, W)``: the aperture ``A``, the Zernike phase
        ``Phi`` (rad), the defocus phase per depth ``D`` (rad/um), and the coefficients of the
        squared local frequency in depth, ``a0`` (cycles^2/px^2), ``a1`` (cycles^2/px^2 per um) and
        ``a2`` (cycles^2/px^2 per um^2).
    depths : Tensor
        ``(Z,)`` float32 depths ``z``, um.
    quartic : float
        ``q``, rad per (cycles^2/px^2)^2.

    Returns
    -------
    Tensor
        ``(V, Z, H, W)`` complex64.
    """
    maps, shape = _flat_maps((amplitude, zernike, defocus, a0, a1, a2))
    depths = depths.to(torch.float32).contiguous()
    views, _, rows, cols = shape
    field = torch.empty(
        (views, len(depths), rows, cols), dtype=torch.complex64, device=depths.device
    )
    if field.numel():
        _field_kernel[_grid(shape)](
            torch.view_as_real(field),
            *maps,
            depths,
            -float(quartic),
            rows * cols,
            len(depths),
            BLOCK=BLOCK,
            LIBDEVICE=_COMPILED,
        )
    return field


def defocused_field_moments(
    grad: Tensor,
    amplitude: Tensor,
    zernike: Tensor,
    defocus: Tensor,
    a0: Tensor,
    a1: Tensor,
    a2: Tensor,
    depths: Tensor,
    quartic: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Gradients of the maps from the gradient ``grad`` of :func:`defocused_field`'s output.

    Parameters
    ----------
    grad : Tensor
        ``(V, Z, H, W)`` complex64 ``dL/du``.
    amplitude, zernike, defocus, a0, a1, a2, depths, quartic
        As :func:`defocused_field`.

    Returns
    -------
    tuple of Tensor
        ``dL/dPhi = sum_z dL/dphase``, ``dL/dD = sum_z z dL/dphase`` and ``dL/da_k = -2 q sum_z
        z^k f dL/dphase`` (``k = 0, 1, 2``), each ``(V, 1, H, W)`` float32.
    """
    maps, shape = _flat_maps((amplitude, zernike, defocus, a0, a1, a2))
    depths = depths.to(torch.float32).contiguous()
    views, _, rows, cols = shape
    expected = (views, len(depths), rows, cols)
    if tuple(grad.shape) != expected or grad.dtype != torch.complex64:
        raise ValueError(f"grad must be complex64 {expected}, got {grad.dtype} {tuple(grad.shape)}")
    moments = torch.zeros((5, *shape), dtype=torch.float32, device=depths.device)
    if moments.numel() and len(depths):
        _moments_kernel[_grid(shape)](
            moments,
            torch.view_as_real(grad.resolve_conj().contiguous()),
            *maps,
            depths,
            -float(quartic),
            rows * cols,
            views,
            len(depths),
            BLOCK=BLOCK,
            LIBDEVICE=_COMPILED,
        )
    return tuple(moments.unbind(0))
