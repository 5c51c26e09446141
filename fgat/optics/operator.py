"""The linear FLFM forward operator ``A`` and its adjoint ``A^T`` (Eqs. S3, S52, S53).

View ``v`` of ``A V`` is ``sum_z V_z * H_{v,z}``: a linear (zero-padded) convolution of each
depth slice with that view's PSF, cropped to the volume's lateral size with the PSF centre at
index ``(h // 2, w // 2)``; for odd PSF sizes this is ``scipy.signal.fftconvolve(mode="same")``
per depth. It is computed in the spectral form: one real FFT per depth slice, a contraction
with the cached OTFs over depth in the Fourier domain, one inverse FFT per view, so
``N_z + N_view`` FFTs per projection instead of ``N_z x N_view`` FFT pairs. The adjoint
mirrors it with conjugate OTFs (Eq. S53).
"""

from __future__ import annotations

import torch
from torch import Tensor

from fgat.optics.psf import fast_fft_size

CHUNK_BYTES = 2**23
"""Spectrum bytes per depth chunk on a CPU (8 MiB: a few slices at paper size stay in L3)."""


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
        fit in :data:`CHUNK_BYTES` of spectrum, so that each chunk's FFTs and its share of the
        contraction run in cache (the result does not depend on it, bit for bit).
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
        self.fft_shape = (fast_fft_size(y + h - 1), fast_fft_size(x + w - 1))
        self.otf = torch.fft.rfft2(psf_stack, s=self.fft_shape).flatten(2)  # (V, Z, F)
        self._conjugate_otf: Tensor | None = None
        if depth_chunk is None:
            plane_bytes = self.otf.shape[-1] * self.otf.element_size()
            depth_chunk = n_depths if self.device.type == "cuda" else CHUNK_BYTES // plane_bytes
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
        projection as its backward): only for reverse mode in ``tensor`` alone. With the OTFs
        learned (a JPGM update) or under a functorch transform (forward-mode Jacobians of the
        cross-information) it is differentiated through its FFTs instead."""
        wrapped = torch._C._functorch.is_functorch_wrapped_tensor
        return (
            torch.is_grad_enabled()
            and tensor.requires_grad
            and not self.otf.requires_grad
            and not wrapped(tensor)
            and not wrapped(self.otf)
        )

    def _depth_chunks(self) -> list[tuple[int, int]]:
        z = self.volume_shape[0]
        return [(k, min(z, k + self.depth_chunk)) for k in range(0, z, self.depth_chunk)]

    def _project(self, volume: Tensor) -> Tensor:
        """Forward projection, depth chunk by depth chunk: each chunk's slices are transformed
        while their share of the contraction still sits in cache, and added into the views'
        spectrum in place one depth at a time (each OTF read once; no ``(B, V, Z, F)`` product).
        Slices come from ``unbind``, whose backward stacks the per-depth gradients once."""
        z, y, x = self.volume_shape
        h, w = self.psf_shape
        batch = volume.shape[:-3]
        volume = volume.reshape(-1, z, y, x)
        otf = self.otf.unbind(1)
        views = None
        for begin, end in self._depth_chunks():
            spectrum = torch.fft.rfft2(volume[:, begin:end], s=self.fft_shape).flatten(2)
            for k, slice_ in enumerate(spectrum[:, :, None].unbind(1), start=begin):
                views = otf[k] * slice_ if views is None else views.addcmul_(otf[k], slice_)
        views = views.reshape(-1, self.n_views, self.fft_shape[0], self.fft_shape[1] // 2 + 1)
        views = torch.fft.irfft2(views, s=self.fft_shape)[
            ..., h // 2 : h // 2 + y, w // 2 : w // 2 + x
        ]
        return views.reshape(*batch, self.n_views, y, x)

    def _back_project(self, views: Tensor) -> Tensor:
        """Adjoint projection: one FFT per view, then depth chunk by depth chunk the contraction
        over views and that chunk's inverse FFTs (mirrors :meth:`_project`)."""
        z, y, x = self.volume_shape
        h, w = self.psf_shape
        batch = views.shape[:-3]
        fy, fx = self.fft_shape
        padded = torch.nn.functional.pad(
            views.reshape(-1, self.n_views, y, x),
            (w // 2, fx - x - w // 2, h // 2, fy - y - h // 2),
        )
        spectrum = torch.fft.rfft2(padded).flatten(2)  # (B, V, F)
        otf, slices = self.conjugate_otf, spectrum[:, :, None].unbind(1)
        volume = padded.new_empty(spectrum.shape[0], z, y, x)
        for begin, end in self._depth_chunks():
            chunk = otf[0, begin:end] * slices[0]
            for v in range(1, self.n_views):
                chunk.addcmul_(otf[v, begin:end], slices[v])
            chunk = chunk.reshape(-1, end - begin, fy, fx // 2 + 1)
            volume[:, begin:end] = torch.fft.irfft2(chunk, s=self.fft_shape)[..., :y, :x]
        return volume.reshape(*batch, z, y, x)

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


class _Projection(torch.autograd.Function):
    """``A`` or ``A^T`` with the other as its backward, for fixed OTFs: the gradient of a
    projection is the transposed projection, computed in the spectral form instead of by
    differentiating through the padded FFTs (same result to rounding, a fraction of the work
    and no saved spectra)."""

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
    h, w = views.shape[-2:]
    origins = _patch_origins(centers, (h, w), sensor_shape)
    if len(origins) != views.shape[-3]:
        raise ValueError(f"{views.shape[-3]} views but {len(origins)} centers")
    image = views.new_zeros((*views.shape[:-3], *sensor_shape))
    for v, (r0, c0) in enumerate(origins):
        image[..., r0 : r0 + h, c0 : c0 + w] += views[..., v, :, :]
    return image


def crop_views(image: Tensor, centers: Tensor, size: int | tuple[int, int]) -> Tensor:
    """See :meth:`FLFMOperator.views_from_sensor`."""
    size = (size, size) if isinstance(size, int) else tuple(size)
    origins = _patch_origins(centers, size, tuple(image.shape[-2:]))
    return torch.stack(
        [image[..., r0 : r0 + size[0], c0 : c0 + size[1]] for r0, c0 in origins], dim=-3
    )
