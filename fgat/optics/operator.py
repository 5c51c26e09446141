"""The linear FLFM forward operator ``A`` and its adjoint ``A^T`` (Eqs. S3, S52, S53).

View ``v`` of ``A V`` is ``sum_z V_z * H_{v,z}``: a linear (zero-padded) convolution of each
depth slice with that view's PSF, cropped to the volume's lateral size with the PSF centre at
index ``(h // 2, w // 2)``; for odd PSF sizes this is ``scipy.signal.fftconvolve(mode="same")``
per depth. The circular convolutions run on the smallest grid whose wrap-around stays outside
that crop (:func:`spectral_grid`), not on the full ``Y + h - 1``. It is computed in the
spectral form: one real FFT per depth slice, a contraction with the cached OTFs over depth in
the Fourier domain, one inverse FFT per view, so ``N_z + N_view`` FFTs per projection instead
of ``N_z x N_view`` FFT pairs. The adjoint mirrors it with conjugate OTFs (Eq. S53).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from fgat._core.devices import functorch_wrapped
from fgat.optics.patches import crop_patches, place_patches
from fgat.optics.psf import fast_fft_size

CHUNK_BYTES = 2**23
"""Spectrum bytes per depth chunk on a CPU (8 MiB: a few slices at paper size stay in L3)."""


def spectral_grid(lateral_shape: tuple[int, int], psf_shape: tuple[int, int]) -> tuple[int, int]:
    """FFT grid ``(fy, fx)`` of the operator's circular convolutions, per axis the fast size of
    ``max(n + p // 2, p)`` for a volume of ``n`` pixels and a PSF of ``p``.

    The linear convolution of ``n`` and ``p`` samples fills ``n + p - 1``; the operator keeps
    ``[p // 2, p // 2 + n)``. On a circular grid of ``N`` those entries are exact when their
    aliases ``i - N`` fall below 0 and ``i + N`` past ``n + p - 2``, that is ``N >= n + p // 2``
    (overlap-save). ``N >= p`` keeps the PSF whole in its OTF. At paper size (300 px, 161 px
    PSFs) that is 384 instead of the 480 of the full linear convolution: 36% fewer bins.
    """
    return tuple(
        fast_fft_size(max(int(n) + int(p) // 2, int(p))) for n, p in zip(lateral_shape, psf_shape)
    )


class FLFMOperator:
    """Forward projection ``(..., Z, Y, X) -> (..., V, Y, X)`` for a PSF stack ``(V, Z, h, w)``.

    The OTFs are computed once, here; build a new operator when the PSF changes (a JPGM step).
    Gradients flow to the volume and, through the OTFs, to ``psf_stack``.

    Parameters
    ----------
    psf_stack : Tensor
        ``(V, Z, h, w)`` real PSFs; dtype float32 or float64 sets the operator's precision.
    volume_shape : tuple of int
        ``(Z, Y, X)`` of the volumes it acts on (``Z`` must match the PSF stack).
    depth_chunk : int, optional
        Depth slices transformed together. Default: all of them on a GPU; on a CPU as many as
        fit in :data:`CHUNK_BYTES` of spectrum, and at least one, so that each chunk's FFTs and
        its share of the contraction run in cache (the result does not depend on it, bit for
        bit).
    """

    def __init__(
        self,
        psf_stack: Tensor,
        volume_shape: tuple[int, int, int],
        *,
        depth_chunk: int | None = None,
    ) -> None:
        if not isinstance(psf_stack, Tensor):
            psf_stack = torch.as_tensor(psf_stack)
        if psf_stack.ndim != 4:
            raise ValueError(
                f"psf_stack must have shape (V, Z, h, w), got {tuple(psf_stack.shape)}"
            )
        if psf_stack.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"psf_stack must be float32 or float64, got {psf_stack.dtype}")
        if len(volume_shape) != 3 or not all(int(n) > 0 for n in volume_shape):
            raise ValueError(f"volume_shape must be (Z, Y, X) positive sizes, got {volume_shape!r}")
        n_views, n_depths, h, w = psf_stack.shape
        if n_depths != volume_shape[0]:
            raise ValueError(
                f"psf_stack has {n_depths} depths but volume_shape has Z = {volume_shape[0]}"
            )
        self.volume_shape = tuple(int(n) for n in volume_shape)
        self.psf_shape = (h, w)
        self.n_views = n_views
        _, y, x = self.volume_shape
        self.fft_shape = spectral_grid((y, x), (h, w))
        self.otf = torch.fft.rfft2(psf_stack, s=self.fft_shape).flatten(2)  # (V, Z, F)
        self._conjugate_otf: Tensor | None = None
        self._scratch = _Scratch(self.device, self.dtype)
        if depth_chunk is None:
            plane_bytes = self.otf.shape[-1] * self.otf.element_size()
            in_cache = max(CHUNK_BYTES // plane_bytes, 1)  # one plane even when it outgrows it
            depth_chunk = n_depths if self.device.type == "cuda" else in_cache
        if int(depth_chunk) < 1:
            raise ValueError(f"depth_chunk must be a positive number of slices, got {depth_chunk}")
        self.depth_chunk = min(int(depth_chunk), n_depths)

    @property
    def dtype(self) -> torch.dtype:
        return self.otf.real.dtype

    @property
    def device(self) -> torch.device:
        return self.otf.device

    def _check(self, tensor: Tensor, shape: tuple[int, ...], name: str) -> None:
        if tensor.shape[-3:] != shape:
            raise ValueError(f"{name} must end in shape {shape}, got {tuple(tensor.shape)}")

    def forward(self, volume: Tensor) -> Tensor:
        """``A V``: views ``(..., V, Y, X)`` of a volume ``(..., Z, Y, X)`` (Eq. S52).

        Differentiable in ``volume`` (its backward is :meth:`adjoint`, the exact transpose) and,
        when the OTFs carry gradients (a JPGM update), in the PSF stack.
        """
        self._check(volume, self.volume_shape, "volume")
        volume = volume.to(self.dtype)
        if self._adjoint_backward(volume):
            return _Projection.apply(volume, self, True)
        return self._project(volume)

    __call__ = forward

    def adjoint(self, views: Tensor) -> Tensor:
        """``A^T r``: volume ``(..., Z, Y, X)`` from views ``(..., V, Y, X)`` (Eq. S53)."""
        _, y, x = self.volume_shape
        self._check(views, (self.n_views, y, x), "views")
        views = views.to(self.dtype)
        if self._adjoint_backward(views):
            return _Projection.apply(views, self, False)
        return self._back_project(views)

    def _adjoint_backward(self, tensor: Tensor) -> bool:
        """Whether a projection of ``tensor`` takes :class:`_Projection` (the transposed
        projection as its backward, the projection itself as its forward-mode derivative): when
        ``tensor`` alone carries derivatives, in reverse mode or under a functorch transform
        (the joint Gauss-Newton step's Jacobian-vector products). With the OTFs learned (a JPGM
        update) or transformed (the cross-information's Jacobians in the optics) it is
        differentiated through its FFTs instead."""
        if self.otf.requires_grad or functorch_wrapped(self.otf):
            return False
        return (torch.is_grad_enabled() and tensor.requires_grad) or functorch_wrapped(tensor)

    def _transformed(self, tensor: Tensor) -> bool:
        """Whether a functorch transform (``vmap``, ``jvp``) wraps ``tensor`` or the OTFs."""
        return functorch_wrapped(tensor, self.otf)

    def _depth_chunks(self) -> list[tuple[int, int]]:
        z = self.volume_shape[0]
        return [(k, min(z, k + self.depth_chunk)) for k in range(0, z, self.depth_chunk)]

    def _project(self, volume: Tensor) -> Tensor:
        """Forward projection, depth chunk by depth chunk: each chunk's slices are transformed
        while their share of the contraction still sits in cache, and added into the views'
        spectrum in place one depth at a time (each OTF read once; no ``(B, V, Z, F)`` product).
        Slices come from ``unbind``, whose backward stacks the per-depth gradients once. With the
        OTFs learned (a JPGM update) each chunk is one :class:`_Contraction` instead: the same
        sums in the same order, recorded as one node rather than two per depth, whose recording
        and backward otherwise cost more host time than a GPU spends on the arithmetic."""
        z, y, x = self.volume_shape
        h, w = self.psf_shape
        batch = volume.shape[:-3]
        volume = volume.reshape(-1, z, y, x)
        scratch = self._scratch_for(volume)
        learned = self._learned_otf(volume)
        otf = None if learned else self.otf.unbind(1)
        buffer = scratch("views", (volume.shape[0], self.n_views, self.otf.shape[-1]), True)
        views = None
        for begin, end in self._depth_chunks():
            spectrum = self._padded_spectrum(volume[:, begin:end], (0, 0), scratch, "slices")
            if learned:
                views = _Contraction.apply(self.otf[:, begin:end], spectrum, views)
            else:
                views = _accumulate(otf[begin:end], spectrum, views, out=buffer)
        views = self._planes(views, (h // 2, w // 2)).contiguous()
        return views.view(*batch, self.n_views, y, x)

    def _learned_otf(self, tensor: Tensor) -> bool:
        """Whether a reverse-mode graph records the OTFs (a JPGM update) with no functorch
        transform around the projection of ``tensor``: :class:`_Contraction` has no forward-mode
        or vmap rule, so the cross-information's Jacobians take the per-depth operations."""
        return torch.is_grad_enabled() and self.otf.requires_grad and not self._transformed(tensor)

    def _back_project(self, views: Tensor) -> Tensor:
        """Adjoint projection: one FFT per view, then depth chunk by depth chunk the contraction
        over views and that chunk's inverse FFTs (mirrors :meth:`_project`)."""
        z, y, x = self.volume_shape
        h, w = self.psf_shape
        batch = views.shape[:-3]
        views = views.reshape(-1, self.n_views, y, x)
        scratch = self._scratch_for(views)
        spectrum = self._padded_spectrum(views, (h // 2, w // 2), scratch, "views")  # (B, V, F)
        otf, slices = self.conjugate_otf, spectrum[:, :, None].unbind(1)
        volume = views.new_empty(views.shape[0], z, y, x)
        for begin, end in self._depth_chunks():
            shape = (views.shape[0], end - begin, self.otf.shape[-1])
            chunk = torch.mul(otf[0, begin:end], slices[0], out=scratch("slices", shape, True))
            for v in range(1, self.n_views):
                chunk.addcmul_(otf[v, begin:end], slices[v])
            volume[:, begin:end] = self._planes(chunk, (0, 0))
        return volume.reshape(*batch, z, y, x)

    def _padded_spectrum(
        self, planes: Tensor, corner: tuple[int, int], scratch: _Buffers, name: str
    ) -> Tensor:
        """``rfft2`` ``(..., F)`` of ``planes`` ``(..., y, x)`` zero-padded onto the FFT grid with
        their first pixel at ``corner`` (row, col)."""
        (fy, fx), (r, c), (y, x) = self.fft_shape, corner, planes.shape[-2:]
        padded = scratch(f"{name} padded", (*planes.shape[:-2], fy, fx), False)
        if padded is None:
            padded = torch.nn.functional.pad(planes, (c, fx - x - c, r, fy - y - r))
        else:
            padded[..., r : r + y, c : c + x] = planes
        return torch.fft.rfft2(padded).flatten(-2)

    def _planes(self, spectrum: Tensor, corner: tuple[int, int]) -> Tensor:
        """The ``(..., Y, X)`` window at ``corner`` (row, col) of the inverse ``rfft2`` of
        ``(..., F)``: the inverse transforms along the columns of every frequency, then the
        real inverse transforms of the ``Y`` rows in the window only (of ``fy``)."""
        (fy, fx), (r, c) = self.fft_shape, corner
        _, y, x = self.volume_shape
        columns = torch.fft.ifft(spectrum.unflatten(-1, (fy, fx // 2 + 1)), dim=-2)
        return torch.fft.irfft(columns[..., r : r + y, :], n=fx, dim=-1)[..., c : c + x]

    def _scratch_for(self, tensor: Tensor) -> _Buffers:
        """The operator's reused buffers where no autograd graph or functorch transform sees
        the projection of ``tensor``, else a scratch that hands out ``None`` (fresh tensors)."""
        graph = torch.is_grad_enabled() and (tensor.requires_grad or self.otf.requires_grad)
        return _fresh if graph or self._transformed(tensor) else self._scratch

    @property
    def conjugate_otf(self) -> Tensor:
        """``conj(OTF)`` ``(V, Z, F)`` for the adjoint, materialised on first use and kept (a
        deconvolution calls the adjoint every iteration; a forward-only user never pays for it)."""
        if self._conjugate_otf is None:
            self._conjugate_otf = self.otf.conj().resolve_conj()
        return self._conjugate_otf

    @staticmethod
    def sensor(views: Tensor, centers: Tensor, sensor_shape: tuple[int, int]) -> Tensor:
        """Place view patches ``(..., V, h, w)`` on a sensor ``(..., H, W)``.

        Patch ``v``'s pixel ``(h // 2, w // 2)`` lands on ``round(centers[v])`` (row, col);
        overlapping patches add. The exact adjoint of :meth:`views_from_sensor`.
        """
        return place_views(views, centers, sensor_shape)

    @staticmethod
    def views_from_sensor(image: Tensor, centers: Tensor, size: int | tuple[int, int]) -> Tensor:
        """Crop patches ``(..., V, h, w)`` centred on ``round(centers)`` from ``(..., H, W)``."""
        return crop_views(image, centers, size)


class _Scratch:
    """Named buffers reused from one projection to the next, so that a deconvolution or a fit
    does not allocate (and, on a CPU, page-fault in) its padded planes and accumulators every call.

    ``scratch(name, shape, complex_)`` is a zero-initialised contiguous ``shape`` view of the
    buffer ``name``, grown when too small. A padded buffer keeps zeros outside the window that
    each call writes, since every call writes the same window of every plane. Buffers are made
    outside inference mode so that both modes may write them. Projections of one operator must
    therefore not run concurrently in two threads.
    """

    def __init__(self, device: torch.device, dtype: torch.dtype):
        self.device, self.dtype = device, dtype
        self._flat: dict[str, Tensor] = {}

    def __call__(self, name: str, shape: tuple[int, ...], complex_: bool) -> Tensor:
        size = math.prod(shape)
        flat = self._flat.get(name)
        if flat is None or flat.numel() < size:
            dtype = self.dtype.to_complex() if complex_ else self.dtype
            with torch.inference_mode(False):
                flat = self._flat[name] = torch.zeros(size, dtype=dtype, device=self.device)
        return flat[:size].view(shape)


def _fresh(name: str, shape: tuple[int, ...], complex_: bool) -> None:
    """The scratch of a projection that autograd or functorch sees: it hands out ``None``, so
    every step allocates its own tensors."""
    return None


_Buffers = Callable[[str, tuple[int, ...], bool], Tensor | None]
"""``scratch(name, shape, complex_)``: a reused buffer (:class:`_Scratch`) or ``None``."""


class _Projection(torch.autograd.Function):
    """``A`` or ``A^T`` with the other as its backward, for fixed OTFs: the gradient of a
    projection is the transposed projection, computed in the spectral form instead of by
    differentiating through the padded FFTs (same result to rounding, a fraction of the work
    and no saved spectra). Being linear, its forward-mode derivative is the same projection
    of the tangent, and under ``vmap`` the batch is one more leading dimension."""

    @staticmethod
    def forward(tensor: Tensor, operator: FLFMOperator, forward: bool) -> Tensor:
        return operator._project(tensor) if forward else operator._back_project(tensor)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        _, ctx.operator, ctx.forward = inputs

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        operator = ctx.operator
        return (operator.adjoint if ctx.forward else operator.forward)(grad), None, None

    @staticmethod
    def jvp(ctx, tangent: Tensor, *_) -> Tensor:
        operator = ctx.operator
        return (operator.forward if ctx.forward else operator.adjoint)(tangent)

    @staticmethod
    def vmap(info, in_dims, tensor: Tensor, operator: FLFMOperator, forward: bool):
        if in_dims[0] is None:
            return _Projection.apply(tensor, operator, forward), None
        return _Projection.apply(tensor.movedim(in_dims[0], 0), operator, forward), 0


def _accumulate(
    otfs: tuple[Tensor, ...], spectrum: Tensor, views: Tensor | None, out: Tensor | None = None
) -> Tensor:
    """Add ``otfs[z] * spectrum[:, z]`` into ``views`` ``(B, V, F)`` in place, depth by depth,
    for the OTFs ``(V, F)`` of a chunk of depths and their slices' spectra ``(B, Zc, F)``;
    ``views`` ``None`` starts from the first product (written into ``out`` when given)."""
    slices = spectrum[:, :, None].unbind(1)
    if views is None:
        views = torch.mul(otfs[0], slices[0], out=out)
        otfs, slices = otfs[1:], slices[1:]
    for depth_otf, slice_ in zip(otfs, slices):
        views.addcmul_(depth_otf, slice_)
    return views


class _Contraction(torch.autograd.Function):
    """``views + sum_z otf[:, z] * spectrum[:, z]``: a chunk of depths' share of the projection
    with learned OTFs, ``(B, V, F)`` from the OTFs ``(V, Zc, F)``, the slices' spectra
    ``(B, Zc, F)`` and the running sum ``views`` ``(B, V, F)`` (``None`` for the first chunk).

    The forward accumulates depth by depth as the fixed operator does (the same result, bit
    for bit); the backward is two products over the whole chunk,
    ``dL/d otf = sum_b conj(spectrum) g`` and ``dL/d spectrum = sum_v conj(otf) g``.
    """

    @staticmethod
    def forward(otf: Tensor, spectrum: Tensor, views: Tensor | None) -> Tensor:
        return _accumulate(otf.unbind(1), spectrum, None if views is None else views.clone())

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        otf, spectrum, _ = inputs
        ctx.save_for_backward(otf, spectrum)

    @staticmethod
    def backward(ctx, grad: Tensor):
        otf, spectrum = ctx.saved_tensors
        grad_otf = grad_spectrum = None
        if ctx.needs_input_grad[0]:
            grad_otf = (grad[:, :, None] * spectrum[:, None].conj()).sum(0)
        if ctx.needs_input_grad[1]:
            grad_spectrum = (grad[:, :, None] * otf.conj()).sum(1)
        return grad_otf, grad_spectrum, grad if ctx.needs_input_grad[2] else None


def _patch_origins(
    centers: Tensor, size: tuple[int, int], sensor_shape: tuple[int, int]
) -> list[tuple[int, int]]:
    centers = torch.as_tensor(centers, dtype=torch.float64).detach().cpu()
    if centers.ndim != 2 or centers.shape[1] != 2:
        raise ValueError(f"centers must have shape (V, 2) (row, col), got {tuple(centers.shape)}")
    origins = (torch.round(centers) - torch.tensor([size[0] // 2, size[1] // 2])).long().tolist()
    for v, (r0, c0) in enumerate(origins):
        if r0 < 0 or c0 < 0 or r0 + size[0] > sensor_shape[0] or c0 + size[1] > sensor_shape[1]:
            raise ValueError(
                f"view {v}: a {size[0]} x {size[1]} patch centred at "
                f"{centers[v].tolist()} does not fit on the {sensor_shape[0]} x "
                f"{sensor_shape[1]} sensor"
            )
    return origins


def place_views(views: Tensor, centers: Tensor, sensor_shape: tuple[int, int]) -> Tensor:
    """See :meth:`FLFMOperator.sensor`."""
    origins = _patch_origins(centers, tuple(views.shape[-2:]), sensor_shape)
    if len(origins) != views.shape[-3]:
        raise ValueError(f"{views.shape[-3]} views but {len(origins)} centers")
    return place_patches(views, origins, sensor_shape)


def crop_views(image: Tensor, centers: Tensor, size: int | tuple[int, int]) -> Tensor:
    """See :meth:`FLFMOperator.views_from_sensor`."""
    size = (size, size) if isinstance(size, int) else tuple(size)
    return crop_patches(image, _patch_origins(centers, size, tuple(image.shape[-2:])), size)


def operator_memory(
    psf_shape: tuple[int, int, int, int],
    volume_shape: tuple[int, int, int],
    *,
    itemsize: int = 4,
    adjoint: bool = True,
    guard_px: int = 0,
) -> int:
    """Bytes of an :class:`~fgat.optics.operator.FLFMOperator` and one projection, upper bound.

    With ``guard_px = g > 0`` it is the :class:`~fgat.optics.acquisition.MeasuredOperator` of
    views ``volume_shape[1:]`` on the padded grid ``(Z, Y + 2g, X + 2g)``, and ``Y, X`` below
    are the padded sizes. With ``V, Z, h, w = psf_shape``, ``Y, X`` the volume's lateral size,
    the FFT grid ``fy x fx`` (:func:`~fgat.optics.operator.spectral_grid`),
    ``F = fy (fx // 2 + 1)`` complex bins and ``r = itemsize``: building the OTFs takes the
    zero-padded PSFs ``V Z fy fx r`` and the OTFs ``V Z F 2r``; the adjoint keeps their conjugate
    (another ``V Z F 2r``); a forward or adjoint projection holds the padded input and spectrum
    of the volume (``Z (fy fx r + F 2r)``) and of the views (``V (fy fx r + F 2r)``), counted
    twice for the inverse transforms.
    """

    n_views, n_depths, h, w = (int(n) for n in psf_shape)
    _, y, x = (int(n) + 2 * guard_px * (axis > 0) for axis, n in enumerate(volume_shape))
    fy, fx = spectral_grid((y, x), (h, w))
    real, spectrum = fy * fx * itemsize, fy * (fx // 2 + 1) * 2 * itemsize
    otf = n_views * n_depths * (real + spectrum * (2 if adjoint else 1))
    return otf + 2 * (n_depths + n_views) * (real + spectrum)
