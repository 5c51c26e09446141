"""The joint Gauss-Newton step of the estimated optics, with the volume free to follow.

The static stage alternates: Adam steps of the Gaussians with the optics fixed, and JPGM events
with the volume fixed. Where a change of the optics can be traded against a change of the object
(coma against a lateral shift of the sample, spherical aberration against its depth), that
alternation crawls along the valley and stops short of the joint optimum, and the distance left
is many times the optics' standard error under the noise. The Gauss-Newton step of the data
misfit ``1/2 ||w (y(G, Theta) - d)||^2`` in the Gaussians ``G`` and the optics ``Theta`` together
measures that distance: its optics part is where the data still pull the optics once the volume
may follow (the volume-profiled step). :func:`joint_correction` computes it:

* the Gaussians' block of the Jacobian is applied matrix-free through one graph of the voxelizer
  and the forward model at the current PSF, recorded once: ``J^T u`` by reverse mode through it,
  ``J v`` by reverse mode through that reverse pass (linear in ``u``, its transpose is ``J``),
  which re-runs neither the voxelizer's bookkeeping nor functorch's forward mode;
* the optics' block ``J_Theta (N, P)`` is formed by forward mode
  (:func:`~fgat.optics.crossinfo.jpgm_jacobians`), since ``P`` is small;
* the normal equations ``(J^T J + lambda D) delta = -J^T r`` are solved by preconditioned
  conjugate gradients, ``D`` the diagonal of ``J^T J`` (for the Gaussians estimated from
  Rademacher probes, ``E[(J^T z)^2] = diag(J^T J)``, Hutchinson; floored at a fraction of its
  median so that Gaussians with no effect on the image do not take unbounded steps) and
  ``lambda`` a small Levenberg-Marquardt damping.

The step is a linearisation: applied whole it overshoots where the image is not linear in the
Gaussians' positions and scales, so fgat reports its optics part beside the estimate rather than
taking it (:func:`~fgat.recon.optics_report.identifiability`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch.func import functional_call

from fgat.optics.crossinfo import jpgm_jacobians
from fgat.optics.psf import JPGM
from fgat.recon.estimation import ESTIMATES

CG_ITERATIONS = 150  # most conjugate-gradient iterations of the joint solve
PROBES = 8  # Rademacher probes of the diagonal of the Gaussians' block
DAMPING = 1e-4  # Levenberg-Marquardt lambda, relative to the diagonal
DIAGONAL_FLOOR = 1e-3  # the diagonal's floor, relative to the Gaussians' median entry


def conjugate_gradient(
    matvec: Callable[[Tensor], Tensor],
    rhs: Tensor,
    preconditioner: Tensor,
    iterations: int,
    tolerance: float = 1e-4,
) -> tuple[Tensor, int]:
    """Solve ``M x = rhs`` for a symmetric positive (semi-)definite ``M`` by preconditioned
    conjugate gradients from ``x = 0``.

    Parameters
    ----------
    matvec : callable
        ``x -> M x`` on ``(P,)`` vectors.
    rhs : Tensor
        ``(P,)``.
    preconditioner : Tensor
        ``(P,)`` positive diagonal approximating ``M``.
    iterations : int
        Most iterations.
    tolerance : float
        Stop when ``||r|| <= tolerance ||rhs||``.

    Returns
    -------
    (Tensor, int)
        ``x`` and the iterations run.
    """
    x = torch.zeros_like(rhs)
    residual = rhs.clone()
    direction = residual / preconditioner
    rz = torch.dot(residual, direction)
    target = tolerance * rhs.norm()
    for k in range(iterations):
        if residual.norm() <= target:
            return x, k
        product = matvec(direction)
        curvature = torch.dot(direction, product)
        if not curvature > 0:
            return x, k
        step = rz / curvature
        x = x + step * direction
        residual = residual - step * product
        z = residual / preconditioner
        rz_next = torch.dot(residual, z)
        direction = z + (rz_next / rz) * direction
        rz = rz_next
    return x, iterations


def joint_correction(
    cloud: nn.Module,
    jpgm: JPGM,
    estimate: str,
    measurement: Tensor,
    operator: Callable[[Tensor], object],
    *,
    mask: Tensor | None = None,
    jacobians: tuple[Tensor, Tensor] | None = None,
    seed: int = 0,
) -> dict[str, Tensor]:
    """The optics part of the joint Gauss-Newton step of the Gaussians and the estimated optics
    (see the module's description); nothing is changed.

    Parameters
    ----------
    cloud : GaussianCloud
        The Gaussians; all their raw parameters are free in the step.
    jpgm : JPGM
        The optics at the point; the groups of ``estimate``
        (:data:`~fgat.recon.estimation.ESTIMATES`) are free in the step.
    estimate : {"shifts", "zernike", "joint"}
        The estimated optics groups.
    measurement : Tensor
        ``(V, Y, X)`` data in normalised units.
    operator : callable
        ``operator(psf_stack)`` with ``.forward(volume) -> (V, Y, X)``: the fit's forward model
        (with its gains, held fixed).
    mask : Tensor, optional
        Pixel mask broadcastable to ``(V, Y, X)`` (1 = used).
    jacobians : (Tensor, Tensor), optional
        The optics' Jacobians ``J_P (N, K)`` and ``J_G (N, 4V)`` at this point, unweighted, when
        already computed (e.g. by :func:`~fgat.optics.crossinfo.cross_information`, in any
        dtype); default computed here (:func:`~fgat.optics.crossinfo.jpgm_jacobians`).
    seed : int
        Seed of the probes.

    Returns
    -------
    dict
        Parameter name (``"zernike_coefficients"``, ``"intercepts"``, ``"slopes"``, those
        estimated) -> its step, shaped like the parameter (waves or pixels).
    """
    weight = torch.ones_like(measurement) if mask is None else mask.to(measurement)
    weight = weight.expand_as(measurement)
    gaussians = {name: p.detach() for name, p in cloud.named_parameters()}
    model = _GaussNewtonModel(
        cloud,
        jpgm,
        ESTIMATES[estimate],
        gaussians,
        weight,
        weight * measurement,
        operator,
        jacobians,
    )
    diagonal = model.diagonal(PROBES, torch.Generator(device="cpu").manual_seed(seed))
    gaussian_part = diagonal[: model.n_gaussians]
    floor = DIAGONAL_FLOOR * (gaussian_part.median() if len(gaussian_part) else diagonal.max())
    diagonal = diagonal.clamp(min=float(floor))
    step, _ = conjugate_gradient(
        lambda v: model.normal(v) + DAMPING * diagonal * v,
        -model.gradient,
        (1 + DAMPING) * diagonal,
        CG_ITERATIONS,
    )
    _, optics = model.split(step.detach())
    return optics


class _GaussNewtonModel:
    """The Gauss-Newton model of the weighted residual ``r = w (y - d)`` at a point: the
    Gaussians (given) and the optics (the JPGM's current parameters ``names``).

    Vectors ``(G + P,)`` hold the Gaussians' raw parameters (in ``gaussians``' order, flattened)
    then the optics' (in ``names`` order).
    """

    def __init__(
        self,
        cloud: nn.Module,
        jpgm: JPGM,
        names: tuple[str, ...],
        gaussians: dict[str, Tensor],
        weight: Tensor,
        data: Tensor,
        operator: Callable[[Tensor], object],
        jacobians: tuple[Tensor, Tensor] | None = None,
    ) -> None:
        with torch.no_grad():
            forward = operator(jpgm())
        self.gaussians = gaussians
        self._leaves = [p.detach().clone().requires_grad_() for p in gaussians.values()]
        with torch.enable_grad():
            # The PyTorch voxelizer: its backward is made of differentiable operations, which
            # the reverse pass through the reverse pass needs (the Triton kernels' is not).
            parameters = dict(zip(gaussians, self._leaves))
            volume = functional_call(cloud, parameters, (), {"backend": "torch"})
            self._prediction = (weight * forward.forward(volume)).reshape(-1)
            # J^T u for a probe u: linear in u, so reverse mode through it in u applies J.
            self._probe = torch.zeros_like(self._prediction, requires_grad=True)
            self._transposed = torch.autograd.grad(
                self._prediction, self._leaves, self._probe, create_graph=True, allow_unused=True
            )
        volume = volume.detach()
        pupil, geometry = jacobians or jpgm_jacobians(jpgm, volume, operator=operator)
        half = 2 * jpgm.n_views
        columns = {
            "zernike_coefficients": pupil,
            "intercepts": geometry[:, :half],
            "slopes": geometry[:, half:],
        }
        self.optics_jacobian = weight.reshape(-1, 1) * torch.cat([columns[n] for n in names], 1)
        self.optics_jacobian = self.optics_jacobian.to(self._prediction)
        self.optics_shapes = {n: getattr(jpgm, n).shape for n in names}
        self.n_gaussians = sum(p.numel() for p in gaussians.values())
        self.gradient = self.adjoint(self._prediction.detach() - data.reshape(-1))

    def split(self, vector: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """A vector as the Gaussians' and the optics' parameter dicts."""
        shapes = {**{n: p.shape for n, p in self.gaussians.items()}, **self.optics_shapes}
        parts = torch.split(vector, [s.numel() for s in shapes.values()])
        entries = {n: part.reshape(s) for (n, s), part in zip(shapes.items(), parts)}
        optics = {n: entries.pop(n) for n in self.optics_shapes}
        return entries, optics

    def apply(self, vector: Tensor) -> Tensor:
        """``J v`` ``(N,)``."""
        tangent, _ = self.split(vector)
        optics = vector[self.n_gaussians :]
        pairs = [
            (transposed, tangent[name])
            for name, transposed in zip(self.gaussians, self._transposed)
            if transposed is not None and transposed.requires_grad
        ]
        views = torch.zeros_like(self._prediction)
        if pairs:
            outputs, tangents = zip(*pairs)
            views = torch.autograd.grad(outputs, self._probe, tangents, retain_graph=True)[0]
        return views.detach() + self.optics_jacobian @ optics

    def adjoint(self, image: Tensor) -> Tensor:
        """``J^T u`` ``(G + P,)``."""
        cotangent = torch.autograd.grad(
            self._prediction, self._leaves, image, retain_graph=True, materialize_grads=True
        )
        flat = [c.detach().reshape(-1) for c in cotangent]
        return torch.cat([*flat, self.optics_jacobian.T @ image])

    def normal(self, vector: Tensor) -> Tensor:
        """``J^T J v``."""
        return self.adjoint(self.apply(vector))

    def diagonal(self, probes: int, generator: torch.Generator) -> Tensor:
        """``diag(J^T J)``: Hutchinson's estimate ``mean_z (J^T z)^2`` over Rademacher ``z`` for
        the Gaussians, exact for the optics' columns."""
        n = self.optics_jacobian.shape[0]
        estimate = self.gradient.new_zeros(self.n_gaussians)
        for _ in range(probes):
            z = torch.randint(0, 2, (n,), generator=generator).to(self.gradient) * 2 - 1
            estimate += self.adjoint(z)[: self.n_gaussians].square()
        return torch.cat([estimate / probes, self.optics_jacobian.square().sum(0)])
