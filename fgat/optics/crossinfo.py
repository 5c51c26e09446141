"""Local cross-information between the Zernike and lenslet-shift parameters of JPGM (Note S4).

With the volume held fixed (Eq. S37), the predicted views ``y`` are a differentiable map of the
pupil parameters ``Theta_P`` (the Zernike coefficients ``c_j``, waves) and the geometry
parameters ``Theta_G`` (the intercepts ``b_v`` and slopes ``s_v``, pixels). Their Jacobians
``J_P`` and ``J_G`` (Eq. S38), computed here by forward-mode automatic differentiation, give
the Gauss-Newton Hessian in block form (Eq. S42)::

    H = [[A, C], [C^T, D]],  A = J_P^T W J_P + Lambda_P,  C = J_P^T W J_G,
                             D = J_G^T W J_G + Lambda_G

whose off-diagonal block ``C`` is the cross-information (Eq. S43), and from it the modal
profiles ``eta^b``, ``eta^s`` (Eq. S48), the Schur complements ``S_P``, ``S_G`` (Eqs. S49-S50),
the leakage map ``-A^-1 C dTheta_G`` (Eq. S51) and the standard errors of a joint fit.

``W`` is the local image-space metric of the loss (Note S4.3): the identity for the pixel L2
loss, or the local quadratic weights of the L1 and Fourier losses about the current residual
(:func:`l1_metric`, :func:`fourier_metric`), combined with :func:`combined_metric`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import torch
from torch import Tensor
from torch.func import functional_call, jvp, vmap

from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM

GEOMETRY = ("intercepts", "slopes")
"""The geometry parameters of ``Theta_G`` in their column order (each ``(V, 2)``, row-major)."""
BLOCKS = ("pupil", "geometry")
"""The Jacobian blocks: the Zernike coefficients' (``J_P``) and the lenslet shifts' (``J_G``)."""

Metric = Callable[[Tensor], Tensor]
"""``W^(1/2)`` applied to Jacobian columns: ``(P, N) -> (P, M)`` (real or complex)."""


def l1_metric(residual: Tensor, floor: float | None = None) -> Metric:
    """The local quadratic weights of the pixel L1 loss ``sum |r|`` about ``residual`` ``r``.

    Near ``r_0``, ``|r| ~ |r_0| / 2 + r^2 / (2 |r_0|)``, so ``W = diag(1 / |r_0|)`` (the
    iteratively-reweighted least-squares weights), with ``|r_0|`` floored at ``floor`` (default
    1e-3 of the largest ``|r_0|``) so that fitted pixels do not dominate.

    Parameters
    ----------
    residual : Tensor
        ``(N,)`` or ``(V, Y, X)`` prediction minus data at the analysed point.
    floor : float, optional
        Smallest ``|r_0|`` used.
    """
    magnitude = residual.detach().reshape(-1).abs()
    floor = float(magnitude.max()) * 1e-3 if floor is None else floor
    root = magnitude.clamp_min(max(floor, torch.finfo(magnitude.dtype).tiny)).rsqrt()
    return lambda columns: columns * root


def fourier_metric(residual: Tensor, floor: float | None = None) -> Metric:
    """The local quadratic weights of the Fourier loss ``sum |F r|`` (Eq. S24) about
    ``residual``: ``W = F^H diag(1 / |F r_0|) F`` with the per-view unnormalised 2D DFT ``F``
    and ``|F r_0|`` floored at ``floor`` (default 1e-3 of its largest value).

    Parameters
    ----------
    residual : Tensor
        ``(V, Y, X)`` prediction minus data at the analysed point.
    floor : float, optional
        Smallest ``|F r_0|`` used.
    """
    if residual.ndim != 3:
        raise ValueError(
            f"fourier_metric: residual (V, Y, X) expected, got {tuple(residual.shape)}"
        )
    shape = tuple(residual.shape)
    magnitude = torch.fft.fft2(residual.detach()).abs()
    floor = float(magnitude.max()) * 1e-3 if floor is None else floor
    root = magnitude.clamp_min(max(floor, torch.finfo(magnitude.dtype).tiny)).rsqrt()

    def apply(columns: Tensor) -> Tensor:
        spectra = torch.fft.fft2(columns.reshape(columns.shape[0], *shape)) * root
        return spectra.reshape(columns.shape[0], -1)

    return apply


def combined_metric(terms: Sequence[tuple[float, Metric | None]]) -> Metric:
    """The metric of a weighted sum of losses, ``W = sum_k lambda_k W_k`` (``None``: the L2
    identity), as stacked rows ``sqrt(lambda_k) W_k^(1/2) J``."""
    for weight, _ in terms:
        if not weight >= 0:
            raise ValueError(f"combined_metric: weights must be >= 0, got {weight}")

    def apply(columns: Tensor) -> Tensor:
        parts = [
            (columns if metric is None else metric(columns)) * weight**0.5
            for weight, metric in terms
            if weight > 0
        ]
        if any(part.is_complex() for part in parts):
            parts = [part.to(torch.promote_types(part.dtype, torch.complex64)) for part in parts]
        return torch.cat(parts, dim=1)

    return apply


def _gram(left: Tensor, right: Tensor) -> Tensor:
    """``Re(left^H right)`` of weighted Jacobian columns ``(P, M)``, ``(Q, M)`` -> ``(P, Q)``."""
    if left.is_complex() or right.is_complex():
        return (left.conj() @ right.transpose(0, 1)).real
    return left @ right.transpose(0, 1)


def _cholesky(matrix: Tensor, name: str) -> Tensor:
    factor, info = torch.linalg.cholesky_ex(matrix)
    if int(info) != 0:
        raise ValueError(
            f"cross_information: the block {name} is singular or not positive definite (its "
            f"leading minor of order {int(info)} is not positive): the image does not determine "
            "those parameters at this point (an empty or flat volume, a view without light, or "
            "parameters with no effect); add a regulariser (lambda_pupil / lambda_geometry)"
        )
    return factor


@dataclass(frozen=True, eq=False)
class CrossInformation:
    """The local Gauss-Newton geometry of JPGM at one point (Note S4).

    Attributes
    ----------
    jacobian_pupil : Tensor
        ``(N, K)`` ``J_P``: image change per wave of each Zernike coefficient, columns in
        ``zernike_indices`` order.
    jacobian_geometry : Tensor
        ``(N, 4V)`` ``J_G``: image change per pixel of ``intercepts.flatten()`` then
        ``slopes.flatten()`` (each ``(V, 2)`` (row, col), row-major).
    A, C, D : Tensor
        ``(K, K)``, ``(K, 4V)``, ``(4V, 4V)`` blocks of the Hessian (Eq. S42).
    zernike_indices : tuple of int
        Noll index of each pupil column.
    n_views : int
        ``V``.
    """

    jacobian_pupil: Tensor
    jacobian_geometry: Tensor
    A: Tensor
    C: Tensor
    D: Tensor
    zernike_indices: tuple[int, ...]
    n_views: int

    @property
    def C_b(self) -> Tensor:
        """``(K, 2V)`` cross-information with the intercepts (Eq. S47)."""
        return self.C[:, : 2 * self.n_views]

    @property
    def C_s(self) -> Tensor:
        """``(K, 2V)`` cross-information with the slopes (Eq. S47)."""
        return self.C[:, 2 * self.n_views :]

    @property
    def eta_b(self) -> Tensor:
        """``(K,)`` modal profile ``||C_b[j, :]|| / ||C_b||_F`` (Eq. S48); its squares sum to 1."""
        return _profile(self.C_b)

    @property
    def eta_s(self) -> Tensor:
        """``(K,)`` modal profile ``||C_s[j, :]|| / ||C_s||_F`` (Eq. S48)."""
        return _profile(self.C_s)

    @property
    def hessian(self) -> Tensor:
        """``(K + 4V, K + 4V)`` the whole block Hessian ``[[A, C], [C^T, D]]``."""
        return torch.cat(
            [torch.cat([self.A, self.C], dim=1), torch.cat([self.C.T, self.D], dim=1)], dim=0
        )

    @property
    def schur_pupil(self) -> Tensor:
        """``(K, K)`` ``S_P = A - C D^-1 C^T`` (Eq. S49): the Zernike curvature of a joint fit."""
        solved = torch.cholesky_solve(self.C.T, _cholesky(self.D, "D (shifts)"))
        return _symmetric(self.A - self.C @ solved)

    @property
    def schur_geometry(self) -> Tensor:
        """``(4V, 4V)`` ``S_G = D - C^T A^-1 C`` (Eq. S50): the shift curvature of a joint fit."""
        solved = torch.cholesky_solve(self.C, _cholesky(self.A, "A (Zernike)"))
        return _symmetric(self.D - self.C.T @ solved)

    def leakage(self, delta_geometry: Tensor) -> Tensor:
        """``(K,)`` first-order Zernike change ``-A^-1 C dTheta_G`` (Eq. S51) that compensates a
        geometry perturbation ``delta_geometry`` (``(4V,)``, or ``(2, V, 2)`` intercepts and
        slopes), in waves."""
        delta = delta_geometry.to(self.C).reshape(-1)
        if delta.numel() != self.C.shape[1]:
            raise ValueError(
                f"leakage: delta_geometry must have {self.C.shape[1]} entries (intercepts then "
                f"slopes, {self.n_views} views x 2), got {delta_geometry.numel()}"
            )
        solved = torch.cholesky_solve((self.C @ delta)[:, None], _cholesky(self.A, "A (Zernike)"))
        return -solved[:, 0]

    def standard_errors(self, noise_sigma: float, estimate: str = "joint") -> dict[str, Tensor]:
        """Gauss-Newton standard errors of the estimated parameters under white noise.

        For the L2 loss with pixel noise of standard deviation ``noise_sigma`` the covariance of
        a fit is ``sigma^2 H^-1``; its pupil block is ``sigma^2 S_P^-1`` in a joint fit and
        ``sigma^2 A^-1`` when only the Zernike terms are estimated (and likewise ``S_G`` or
        ``D`` for the shifts): the cross-information costs the joint fit precision.

        Parameters
        ----------
        noise_sigma : float
            Pixel noise standard deviation, in the units of the predicted views.
        estimate : {"joint", "zernike", "shifts"}
            The parameter groups the fit estimated.

        Returns
        -------
        dict
            ``"zernike"`` ``(K,)`` waves and/or ``"intercepts"``, ``"slopes"`` ``(V, 2)``
            pixels, for the estimated groups.
        """
        _check_estimate(estimate)
        if not noise_sigma >= 0:
            raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma}")
        errors = {}
        if estimate in ("joint", "zernike"):
            curvature = self.schur_pupil if estimate == "joint" else self.A
            errors["zernike"] = noise_sigma * _inverse_diagonal(curvature, "the Zernike block")
        if estimate in ("joint", "shifts"):
            curvature = self.schur_geometry if estimate == "joint" else self.D
            diagonal = noise_sigma * _inverse_diagonal(curvature, "the shift block")
            errors.update(self._geometry_groups(diagonal))
        return errors

    def sandwich_errors(
        self, residual: Tensor, estimate: str = "joint", weights: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Standard errors that hold whatever the pixels' noise variances (White, Econometrica
        48, 817 (1980)): the covariance ``H^-1 (J^T W diag(r^2) W J) H^-1`` of the estimated
        groups' columns ``J``, their Hessian block ``H`` (``A``, ``D`` or the whole Hessian for a
        joint fit) and the residual ``r`` standing in for each pixel's noise.

        Photon noise is largest on the bright pixels that carry the information about the
        optics, so these exceed :meth:`standard_errors` under one ``sigma`` for all pixels.

        Parameters
        ----------
        residual : Tensor
            ``(N,)`` (or any shape with ``N`` entries) prediction minus data, rows as the
            Jacobians'.
        estimate : {"joint", "zernike", "shifts"}
            The parameter groups the fit estimated.
        weights : Tensor, optional
            ``(N,)`` the diagonal metric the blocks were formed with (default the identity); a
            Fourier or L1 metric is not diagonal and is refused.

        Returns
        -------
        dict
            As :meth:`standard_errors`.
        """
        _check_estimate(estimate)
        residual = residual.reshape(-1).to(self.A)
        if residual.numel() != self.jacobian_pupil.shape[0]:
            raise ValueError(
                f"residual must have {self.jacobian_pupil.shape[0]} entries (the Jacobians' "
                f"rows), got {residual.numel()}"
            )
        if weights is not None:
            residual = residual * weights.reshape(-1).to(residual)
        blocks, curvature, name = {
            "zernike": ((self.jacobian_pupil,), self.A, "A (Zernike)"),
            "shifts": ((self.jacobian_geometry,), self.D, "D (shifts)"),
            "joint": (
                (self.jacobian_pupil, self.jacobian_geometry),
                self.hessian,
                "H (Zernike and shifts)",
            ),
        }[estimate]
        variance = residual.square()
        meat = torch.cat(
            [torch.cat([_row_gram(p, q, variance) for q in blocks], 1) for p in blocks], 0
        )
        factor = _cholesky(curvature, name)
        bread = torch.cholesky_solve(meat, factor)
        covariance = torch.cholesky_solve(bread.T.contiguous(), factor)
        diagonal = covariance.diagonal().clamp_min(0).sqrt()
        k = self.A.shape[0]
        errors = {} if estimate == "shifts" else {"zernike": diagonal[:k]}
        if estimate != "zernike":
            errors.update(self._geometry_groups(diagonal[-4 * self.n_views :]))
        return errors

    def _geometry_groups(self, values: Tensor) -> dict[str, Tensor]:
        """``(4V,)`` values as ``{"intercepts": (V, 2), "slopes": (V, 2)}``."""
        return {
            name: values[2 * self.n_views * k : 2 * self.n_views * (k + 1)].reshape(self.n_views, 2)
            for k, name in enumerate(GEOMETRY)
        }


def estimated_blocks(estimate: str) -> tuple[str, ...]:
    """The Jacobian blocks (:data:`BLOCKS`) whose standard errors a fit that estimated
    ``estimate`` ({"joint", "zernike", "shifts"}) reports: its own groups'."""
    _check_estimate(estimate)
    return {"zernike": ("pupil",), "shifts": ("geometry",), "joint": BLOCKS}[estimate]


def _check_estimate(estimate: str) -> None:
    if estimate not in ("joint", "zernike", "shifts"):
        raise ValueError(f"estimate must be 'joint', 'zernike' or 'shifts', got {estimate!r}")


def _profile(block: Tensor) -> Tensor:
    total = torch.linalg.matrix_norm(block)
    return torch.linalg.vector_norm(block, dim=1) / total.clamp_min(torch.finfo(block.dtype).tiny)


def _symmetric(matrix: Tensor) -> Tensor:
    return 0.5 * (matrix + matrix.T)


def _inverse_diagonal(matrix: Tensor, name: str) -> Tensor:
    """``sqrt(diag(M^-1))`` of a symmetric positive-definite ``M``, by its Cholesky factor."""
    factor = _cholesky(matrix, name)
    identity = torch.eye(matrix.shape[0], dtype=matrix.dtype, device=matrix.device)
    inverse_factor = torch.linalg.solve_triangular(factor, identity, upper=False)
    return inverse_factor.square().sum(dim=0).sqrt()


def jpgm_jacobians(
    jpgm: JPGM,
    volume: Tensor,
    *,
    operator: Callable[[Tensor], object] | None = None,
    views: Sequence[int] | None = None,
    chunk_size: int | None = 8,
    blocks: Sequence[str] = BLOCKS,
    depth_chunk: int | None = None,
) -> tuple[Tensor, Tensor]:
    """``J_P (N, K)`` and ``J_G (N, 4V)`` of the predicted views with the volume held fixed.

    Forward-mode automatic differentiation (one Jacobian-vector product per column, ``chunk_size``
    columns at a time), in the JPGM's dtype. The two blocks are differentiated apart: the
    geometry moves only the crops (Eqs. S11-S12), so its ``4V`` columns carry no tangent through
    the pupil fields and their propagation, which only the ``K`` Zernike columns need. The views
    are a sum over planes (Eq. S52) and each plane's PSF is normalised on its own (Eq. S9), so
    with ``depth_chunk`` the Jacobian is accumulated over slices of that many planes, each pass
    holding one slice's PSFs, OTFs and tangents instead of the whole stack's.

    Parameters
    ----------
    jpgm : JPGM
        The generator at the analysed point (its parameters are not changed).
    volume : Tensor
        ``(Z, Y', X')`` the object, on the operator's grid.
    operator : callable, optional
        ``operator(psf_stack)`` with a ``forward(volume) -> (V, Y, X)`` (e.g. a
        :class:`~fgat.optics.acquisition.MeasuredOperator` with gains and a guard band, which
        takes its depths from the stack); default :class:`~fgat.optics.operator.FLFMOperator`
        on the stack's depths and ``volume``'s lateral shape. With ``depth_chunk`` it is given
        stacks of that many planes and their slices of ``volume``.
    views : sequence of int, optional
        The views whose pixels are the rows (default all).
    chunk_size : int or None
        Columns per batched pass (memory grows with it); ``None``: all at once.
    blocks : sequence of {"pupil", "geometry"}
        The blocks computed (default both); one left out is returned empty, ``(N, 0)`` (a fit
        that estimated only the Zernike terms, or only the shifts, needs only its own).
    depth_chunk : int, optional
        Planes per pass (default all): memory falls with it, the result is the same up to
        rounding.

    Returns
    -------
    (Tensor, Tensor)
        ``J_P`` and ``J_G``; rows ordered as the predicted ``(V, Y, X)`` flattened.
    """
    if not blocks or not set(blocks) <= set(BLOCKS):
        raise ValueError(f"blocks must be one or both of {BLOCKS}, got {tuple(blocks)!r}")
    if depth_chunk is None:
        slices = [slice(None)]
    elif int(depth_chunk) < 1:
        raise ValueError(f"depth_chunk must be a positive number of planes, got {depth_chunk!r}")
    else:
        step, n_depths = int(depth_chunk), jpgm.n_depths
        slices = [slice(k, min(k + step, n_depths)) for k in range(0, n_depths, step)]
    dtype = jpgm.zernike_coefficients.dtype
    volume = volume.detach().to(device=jpgm.xi.device, dtype=dtype)
    operator = operator or partial(_plane_operator, lateral_shape=tuple(volume.shape[1:]))
    point = {name: getattr(jpgm, name).detach() for name in ("zernike_coefficients", *GEOMETRY)}
    selected = None if views is None else torch.as_tensor(list(views), device=volume.device)

    def columns(names: tuple[str, ...]) -> Tensor:
        """``(N, P)``: the derivatives in the parameters ``names``, the others held."""
        sizes = [point[name].numel() for name in names]

        def predict(theta: Tensor, depths: slice) -> Tensor:
            parts = dict(zip(names, torch.split(theta, sizes)))
            parameters = {
                n: parts[n].reshape(p.shape) if n in parts else p for n, p in point.items()
            }
            planes = {} if len(slices) == 1 else {"depths": depths}
            psf = functional_call(jpgm, parameters, (), planes)
            prediction = operator(psf).forward(volume[depths])
            if selected is not None:
                prediction = prediction.index_select(-3, selected)
            return prediction.reshape(-1)

        theta = torch.cat([point[name].reshape(-1) for name in names])
        basis = torch.eye(theta.numel(), dtype=dtype, device=theta.device)
        total = None
        for depths in slices:
            column = vmap(
                lambda tangent: jvp(partial(predict, depths=depths), (theta,), (tangent,))[1],
                chunk_size=chunk_size,
            )
            part = column(basis)
            total = part if total is None else total.add_(part)
        return total.T.contiguous()

    computed = {
        block: columns(names)
        for block, names in zip(BLOCKS, (("zernike_coefficients",), GEOMETRY))
        if block in blocks
    }
    rows = next(iter(computed.values())).shape[0]
    empty = volume.new_zeros(rows, 0)
    return computed.get("pupil", empty), computed.get("geometry", empty)


def bead_cross_information(
    jpgm: JPGM,
    *,
    sigma_px: float = 1.0,
    depth_chunk: int = 8,
    chunk_size: int | None = 8,
) -> Tensor:
    """``(K, 4V)`` cross-information ``C`` (Eq. S43, ``W = I``) of one isolated Gaussian bead on
    each plane, summed over the planes: the expected ``C`` per bead of a sparse bead scene.

    A scene of beads far enough apart that their images do not overlap, each inside the field,
    has ``C = sum_k a_k^2 sum_v <d_j h_v(z_k) * g, d_theta h_v(z_k) * g>`` over its beads ``k``
    (depth ``z_k``, amplitude ``a_k``), with ``h_v(z)`` the PSF crop of view ``v`` (Eq. S12) and
    ``g`` the bead's lateral Gaussian: the lateral positions drop out, and beads spread evenly in
    depth make ``C`` proportional to this sum over the planes. It needs the PSF stack's
    Jacobian only (no volume, no operator), so the profiles of Eq. S48 at a scale whose full
    Jacobian does not fit can be computed from it.

    Parameters
    ----------
    jpgm : JPGM
        The generator at the analysed point.
    sigma_px : float
        Bead standard deviation, camera pixels (0: points).
    depth_chunk : int
        Planes per pass (memory grows with it).
    chunk_size : int or None
        Jacobian columns per batched pass, as :func:`jpgm_jacobians`.

    Returns
    -------
    Tensor
        ``C`` in the column order of :class:`CrossInformation` (intercepts then slopes).
    """
    if int(depth_chunk) < 1 or not sigma_px >= 0:
        raise ValueError(
            f"depth_chunk must be >= 1 and sigma_px >= 0, got {depth_chunk!r}, {sigma_px!r}"
        )
    dtype, device = jpgm.zernike_coefficients.dtype, jpgm.xi.device
    point = {name: getattr(jpgm, name).detach() for name in ("zernike_coefficients", *GEOMETRY)}
    blur = _gaussian_kernel(sigma_px, dtype, device)

    def columns(names: tuple[str, ...], depths: slice) -> Tensor:
        """``(P, pixels)``: the blurred PSF crops' derivatives in the parameters ``names``."""
        sizes = [point[name].numel() for name in names]

        def crops(theta: Tensor) -> Tensor:
            parameters = {**point, **dict(zip(names, torch.split(theta, sizes)))}
            parameters = {n: p.reshape(point[n].shape) for n, p in parameters.items()}
            stack = functional_call(jpgm, parameters, (), {"depths": depths})
            return _blur(stack, blur).reshape(-1)

        theta = torch.cat([point[name].reshape(-1) for name in names])
        basis = torch.eye(theta.numel(), dtype=dtype, device=device)
        tangent = vmap(lambda t: jvp(crops, (theta,), (t,))[1], chunk_size=chunk_size)
        return tangent(basis)

    total = torch.zeros(len(jpgm.zernike_indices), 4 * jpgm.n_views, dtype=dtype, device=device)
    for begin in range(0, jpgm.n_depths, int(depth_chunk)):
        depths = slice(begin, min(begin + int(depth_chunk), jpgm.n_depths))
        pupil = columns(("zernike_coefficients",), depths)
        total += pupil @ columns(GEOMETRY, depths).T
    return total


def modal_profiles(cross: Tensor) -> tuple[Tensor, Tensor]:
    """``(eta^b, eta^s)`` (Eq. S48), each ``(K,)``, of a cross-information block ``C``
    ``(K, 4V)`` (intercept columns, then slope columns)."""
    half = cross.shape[1] // 2
    return _profile(cross[:, :half]), _profile(cross[:, half:])


def _gaussian_kernel(sigma: float, dtype: torch.dtype, device) -> Tensor | None:
    """Normalised 1D Gaussian of standard deviation ``sigma`` pixels over +-4 sigma (``None``
    for ``sigma = 0``)."""
    if sigma == 0:
        return None
    half = max(1, math.ceil(4 * sigma))
    offsets = torch.arange(-half, half + 1, dtype=dtype, device=device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    return kernel / kernel.sum()


def _blur(stack: Tensor, kernel: Tensor | None) -> Tensor:
    """The full linear convolution ``(..., H + n - 1, W + n - 1)`` of ``stack`` ``(..., H, W)``
    with the separable, symmetric ``kernel`` ``(n,)``: each crop's whole bead image."""
    if kernel is None:
        return stack
    images = stack.reshape(-1, 1, *stack.shape[-2:])
    pad = kernel.numel() - 1
    images = torch.nn.functional.conv2d(images, kernel.view(1, 1, -1, 1), padding=(pad, 0))
    images = torch.nn.functional.conv2d(images, kernel.view(1, 1, 1, -1), padding=(0, pad))
    return images.reshape(*stack.shape[:-2], *images.shape[-2:])


def _plane_operator(psf_stack: Tensor, lateral_shape: tuple[int, int]) -> FLFMOperator:
    """The :class:`~fgat.optics.operator.FLFMOperator` of a stack's planes on ``(Y, X)``."""
    return FLFMOperator(psf_stack, (psf_stack.shape[1], *lateral_shape))


def cross_information(
    jpgm: JPGM,
    volume: Tensor,
    *,
    weights: Tensor | Metric | None = None,
    views: Sequence[int] | None = None,
    operator: Callable[[Tensor], object] | None = None,
    lambda_pupil: Tensor | float | None = None,
    lambda_geometry: Tensor | float | None = None,
    chunk_size: int | None = 8,
    blocks: Sequence[str] = BLOCKS,
    depth_chunk: int | None = None,
) -> CrossInformation:
    """The cross-information of JPGM's pupil and geometry parameters at one point (Note S4).

    Parameters
    ----------
    jpgm : JPGM
        The generator at the analysed point; float64 for the tables.
    volume : Tensor
        ``(Z, Y, X)`` the object, held fixed (Eq. S37).
    weights : Tensor or callable, optional
        The image metric ``W``: ``None`` the identity (pixel L2); an ``(N,)`` tensor of diagonal
        weights (1 / variance, a pixel mask); or a metric from :func:`l1_metric`,
        :func:`fourier_metric` or :func:`combined_metric`.
    views : sequence of int, optional
        Only these views' pixels (default all).
    operator : callable, optional
        As :func:`jpgm_jacobians`.
    lambda_pupil, lambda_geometry : Tensor or float, optional
        Diagonal regularisers ``Lambda_P`` ``(K,)`` and ``Lambda_G`` ``(4V,)`` (or scalars).
    chunk_size : int or None
        As :func:`jpgm_jacobians`.
    blocks : sequence of {"pupil", "geometry"}
        As :func:`jpgm_jacobians`: with one block only, the other's Jacobian and Hessian blocks
        are empty, so only the standard errors of a fit that estimated that group alone are
        defined.
    depth_chunk : int, optional
        As :func:`jpgm_jacobians`.

    Returns
    -------
    CrossInformation
        With diagonal weights (or none) the blocks are summed over row blocks of the
        Jacobians, so no weighted copy of them is held.
    """
    pupil, geometry = jpgm_jacobians(
        jpgm,
        volume,
        operator=operator,
        views=views,
        chunk_size=chunk_size,
        blocks=blocks,
        depth_chunk=depth_chunk,
    )
    if weights is None or not callable(weights):
        diagonal = _diagonal_weights(weights, pupil)
        a = _row_gram(pupil, pupil, diagonal)
        c = _row_gram(pupil, geometry, diagonal)
        d = _row_gram(geometry, geometry, diagonal)
    else:
        weighted_p, weighted_g = weights(pupil.T), weights(geometry.T)
        a, c, d = (
            _gram(weighted_p, weighted_p),
            _gram(weighted_p, weighted_g),
            _gram(weighted_g, weighted_g),
        )
    a = a + _diagonal(lambda_pupil, pupil.shape[1], pupil)
    d = d + _diagonal(lambda_geometry, geometry.shape[1], pupil)
    return CrossInformation(
        pupil,
        geometry,
        _symmetric(a),
        c,
        _symmetric(d),
        jpgm.zernike_indices,
        jpgm.intercepts.shape[0],
    )


def _diagonal_weights(weights: Tensor | None, like: Tensor) -> Tensor | None:
    """The diagonal metric ``(N,)`` of Jacobian rows ``like`` ``(N, P)`` (``None``: identity)."""
    if weights is None:
        return None
    diagonal = torch.as_tensor(weights).to(like).reshape(-1)
    if diagonal.numel() != like.shape[0] or not bool((diagonal >= 0).all()):
        raise ValueError(
            f"cross_information: weights must be {like.shape[0]} non-negative numbers (one per "
            f"predicted pixel), got {diagonal.numel()}"
        )
    return diagonal


ROW_BLOCK = 2**16
"""Jacobian rows per block of :func:`_row_gram` (bounds its temporary to ``ROW_BLOCK P``)."""


def _row_gram(left: Tensor, right: Tensor, weights: Tensor | None = None) -> Tensor:
    """``left^T diag(weights) right`` of ``(N, P)`` and ``(N, Q)`` -> ``(P, Q)``, summed over
    blocks of :data:`ROW_BLOCK` rows (only one block's weighted copy is held)."""
    total = left.new_zeros(left.shape[1], right.shape[1])
    for begin in range(0, left.shape[0], ROW_BLOCK):
        rows = slice(begin, begin + ROW_BLOCK)
        block = right[rows] if weights is None else right[rows] * weights[rows, None]
        total += left[rows].T @ block
    return total


def _diagonal(values: Tensor | float | None, size: int, like: Tensor) -> Tensor:
    if values is None:
        return torch.zeros(size, size, dtype=like.dtype, device=like.device)
    values = torch.as_tensor(values, dtype=like.dtype, device=like.device).expand(size)
    if not bool((values >= 0).all()):
        raise ValueError("cross_information: the regularisers must be >= 0")
    return torch.diag(values)
