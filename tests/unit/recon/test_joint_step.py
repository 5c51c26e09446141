"""The joint Gauss-Newton step of the Gaussians and the optics, against dense float64 solves."""

import numpy as np
import pytest
import torch
from torch.func import functional_call, jacfwd

from fgat.gaussians.densify import Densification
from fgat.recon import StaticReconstruction, StaticSettings, joint_step, phantom_scene
from fgat.recon.estimation import OpticsEstimation
from fgat.recon.joint_step import conjugate_gradient, joint_correction
from fgat.sim.simulation import SimulationConfig

SIMULATION = SimulationConfig(
    system="small",
    depths_um="-12:12:5",
    view_size=24,
    photons=None,
    phantom={"kind": "beads", "n_beads": 4, "sigma": 1.0, "min_spacing": 6, "margin": [1, 5, 5]},
    zernike={7: 0.08, 11: -0.05},
)


def fitted_engine(estimate: str, steps: int, n_gaussians: int = 12) -> StaticReconstruction:
    """A static fit of the small bead scene after ``steps`` steps (the optics never updated)."""
    engine = StaticReconstruction(
        phantom_scene(SIMULATION, psf="ideal"),
        StaticSettings(n_gaussians=n_gaussians, init_iterations=5, baseline_iterations=0),
        Densification(enabled=False),
        OpticsEstimation(estimate=estimate, start=10**6),
        total_steps=max(steps, 1),
    )
    for _ in range(steps):
        engine.step()
    return engine


def test_conjugate_gradient_solves_a_positive_definite_system():
    generator = torch.Generator().manual_seed(0)
    basis, _ = torch.linalg.qr(torch.randn(30, 30, generator=generator, dtype=torch.float64))
    scales = torch.logspace(0, 2, 30, dtype=torch.float64)
    matrix = basis @ torch.diag(torch.logspace(0, 3, 30, dtype=torch.float64)) @ basis.T  # cond 1e3
    matrix = scales[:, None] * matrix * scales[None, :]  # badly scaled: the diagonal helps
    rhs = torch.randn(30, generator=generator, dtype=torch.float64)
    solution, iterations = conjugate_gradient(
        lambda v: matrix @ v, rhs, matrix.diagonal(), 60, tolerance=1e-12
    )
    expected = torch.linalg.solve(matrix, rhs)
    assert iterations <= 60
    torch.testing.assert_close(solution, expected, rtol=1e-9, atol=1e-12)
    # the iteration count is honoured: one iteration is the preconditioned steepest descent step
    one, used = conjugate_gradient(lambda v: matrix @ v, rhs, matrix.diagonal(), 1)
    direction = rhs / matrix.diagonal()
    step = (rhs @ direction) / (direction @ matrix @ direction)
    assert used == 1
    torch.testing.assert_close(one, step * direction)


@pytest.mark.parametrize("estimate", ["zernike", "joint"])
@pytest.mark.slow
def test_joint_correction_is_the_dense_damped_gauss_newton_step(estimate, monkeypatch):
    """Dense float64 reference: the Jacobian of the masked views in every raw Gaussian parameter
    and every estimated optics parameter, the exact diagonal (floored as fgat floors it), the
    normal equations solved directly; the optics part of its solution is the correction (within
    2%: the damping's diagonal of the Gaussians is estimated from 8 probes)."""
    monkeypatch.setattr(joint_step, "CG_ITERATIONS", 1000)  # the solve converged (default: capped)
    engine = fitted_engine(estimate, steps=20)
    mask = torch.ones_like(engine.measurement)
    mask[:, ::5, ::3] = 0.0
    correction = joint_correction(
        engine.cloud,
        engine.jpgm,
        estimate,
        engine.measurement,
        engine.scene.operator,
        mask=mask,
    )

    gaussians = {n: p.detach().double() for n, p in engine.cloud.named_parameters()}
    names = joint_step.ESTIMATES[estimate]
    optics = {n: getattr(engine.jpgm, n).detach().double() for n in names}
    cloud, jpgm = engine.cloud.double(), engine.jpgm.double()

    with torch.no_grad():
        psf = jpgm()
    volume = cloud()
    data = (mask * engine.measurement).double().reshape(-1)

    def views(psf, volume):
        return (mask.double() * engine.scene.operator(psf).forward(volume)).reshape(-1)

    def in_gaussians(gaussians):
        return views(psf, functional_call(cloud, gaussians, ()))

    def in_optics(optics):
        return views(functional_call(jpgm, optics, (), strict=False), volume.detach())

    columns = [*jacfwd(in_gaussians)(gaussians).values(), *jacfwd(in_optics)(optics).values()]
    jacobian = torch.cat([j.reshape(j.shape[0], -1) for j in columns], 1)
    residual = views(psf, volume.detach()) - data
    gradient = jacobian.T @ residual
    diagonal = jacobian.square().sum(0)
    n_gaussians = sum(p.numel() for p in gaussians.values())
    floor = joint_step.DIAGONAL_FLOOR * diagonal[:n_gaussians].median()
    diagonal = diagonal.clamp(min=float(floor))
    normal = jacobian.T @ jacobian + joint_step.DAMPING * torch.diag(diagonal)
    step = torch.linalg.solve(normal, -gradient)[n_gaussians:]

    got = torch.cat([correction[n].double().reshape(-1) for n in names])
    assert list(correction) == list(names)
    assert float(step.norm()) > 0
    relative = float((got - step).norm() / step.norm())
    assert relative < 0.02, relative
    # and it is not the step with the volume held: the Gaussians' freedom changes it
    optics_block = jacobian[:, n_gaussians:]
    held = torch.linalg.solve(optics_block.T @ optics_block, -gradient[n_gaussians:])
    assert float((held - step).norm() / step.norm()) > 5 * relative
    assert np.isfinite(got.numpy()).all()


@pytest.mark.slow
def test_gauss_newton_model_applies_the_jacobian_and_its_transpose():
    """``J v`` (reverse mode through the recorded reverse pass) and ``J^T u`` of the Gaussians'
    block against the dense float64 Jacobian by forward mode, with a mask that zeroes pixels."""
    engine = fitted_engine("zernike", steps=5)
    cloud, jpgm = engine.cloud.double(), engine.jpgm.double()
    weight = torch.ones_like(engine.measurement, dtype=torch.float64)
    weight[:, ::4, ::3] = 0.0
    gaussians = {n: p.detach() for n, p in cloud.named_parameters()}
    model = joint_step._GaussNewtonModel(
        cloud,
        jpgm,
        ("zernike_coefficients",),
        gaussians,
        weight,
        weight * engine.measurement.double(),
        engine.scene.operator,
    )
    with torch.no_grad():
        operator = engine.scene.operator(jpgm())

    def views(parameters):
        return (weight * operator.forward(functional_call(cloud, parameters, ()))).reshape(-1)

    dense = torch.cat([j.reshape(j.shape[0], -1) for j in jacfwd(views)(gaussians).values()], 1)
    generator = torch.Generator().manual_seed(3)
    vector = torch.randn(model.n_gaussians + 17, generator=generator, dtype=torch.float64)
    image = torch.randn(dense.shape[0], generator=generator, dtype=torch.float64)
    optics = model.optics_jacobian
    expected = dense @ vector[: model.n_gaussians] + optics @ vector[model.n_gaussians :]
    torch.testing.assert_close(model.apply(vector), expected, rtol=1e-10, atol=1e-12)
    transposed = torch.cat([dense.T @ image, optics.T @ image])
    torch.testing.assert_close(model.adjoint(image), transposed, rtol=1e-10, atol=1e-12)
    assert float(dense.abs().max()) > 0 and float(dense[weight.reshape(-1) == 0].abs().max()) == 0


@pytest.mark.slow
def test_joint_correction_renders_with_the_differentiable_voxelizer(monkeypatch):
    """``J v`` is a reverse pass through the voxelizer's backward, which the Triton kernels do
    not record: the step must ask for the PyTorch path whatever the device picks."""
    import importlib

    voxelize_module = importlib.import_module("fgat.gaussians.voxelize")
    asked = []
    use_triton = voxelize_module._use_triton
    monkeypatch.setattr(
        voxelize_module, "_use_triton", lambda backend, means: asked.append(backend) or False
    )
    engine = fitted_engine("zernike", steps=0, n_gaussians=8)
    asked.clear()
    joint_correction(
        engine.cloud, engine.jpgm, "zernike", engine.measurement, engine.scene.operator
    )
    assert asked and set(asked) == {"torch"}
    assert use_triton("torch", torch.zeros(1, 3)) is False
