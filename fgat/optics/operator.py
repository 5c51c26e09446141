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
    """

    def __init__(self, psf_stack: Tensor, volume_shape: tuple[int, int, int]) -> None:
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
        """``A V``: views ``(..., V, Y, X)`` of a volume ``(..., Z, Y, X)`` (Eq. S52)."""
        self._check(volume, self.volume_shape, "volume")
        z, y, x = self.volume_shape
        h, w = self.psf_shape
        batch = volume.shape[:-3]
        spectrum = torch.fft.rfft2(
            volume.to(self.dtype).reshape(-1, z, y, x), s=self.fft_shape
        ).flatten(2)
        # Sum over depth in the Fourier domain, accumulating in place one depth at a time:
        # reads each OTF once and never materialises a (B, V, Z, F) product. Slices come from
        # unbind, whose backward stacks the per-depth gradients once (an indexed slice would
        # allocate and zero a full-size gradient per depth).
        otf, slices = self.otf.unbind(1), spectrum[:, :, None].unbind(1)
        views = otf[0] * slices[0]
        for k in range(1, z):
            views.addcmul_(otf[k], slices[k])
        views = views.reshape(-1, self.n_views, self.fft_shape[0], self.fft_shape[1] // 2 + 1)
        views = torch.fft.irfft2(views, s=self.fft_shape)[
            ..., h // 2 : h // 2 + y, w // 2 : w // 2 + x
        ]
        return views.reshape(*batch, self.n_views, y, x)

    __call__ = forward

    def adjoint(self, views: Tensor) -> Tensor:
        """``A^T r``: volume ``(..., Z, Y, X)`` from views ``(..., V, Y, X)`` (Eq. S53)."""
        z, y, x = self.volume_shape
        h, w = self.psf_shape
        self._check(views, (self.n_views, y, x), "views")
        batch = views.shape[:-3]
        fy, fx = self.fft_shape
        padded = torch.nn.functional.pad(
            views.to(self.dtype).reshape(-1, self.n_views, y, x),
            (w // 2, fx - x - w // 2, h // 2, fy - y - h // 2),
        )
        spectrum = torch.fft.rfft2(padded).flatten(2)  # (B, V, F)
        otf, slices = self.conjugate_otf.unbind(0), spectrum[:, :, None].unbind(1)
        volume = otf[0] * slices[0]
        for v in range(1, self.n_views):
            volume.addcmul_(otf[v], slices[v])
        volume = torch.fft.irfft2(volume.reshape(-1, z, fy, fx // 2 + 1), s=self.fft_shape)[
            ..., :y, :x
        ]
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
