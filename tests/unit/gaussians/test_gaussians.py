import math

import numpy as np
import pytest
import torch

from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.densify import (
    Densification,
    DensificationStrategy,
    append_gaussians,
    select_gaussians,
)
from fgat.gaussians.rotation import covariance, quaternion_multiply, quaternion_to_rotation
from fgat.gaussians.voxelize import _bucket, _window_groups, voxelize, voxelize_dense

SHAPE, VOXEL, ORIGIN = (12, 20, 18), (1.5, 0.975, 0.975), (-9.0, -9.75, -8.775)


def random_gaussians(n, seed=0, dtype=torch.float64, spread=1.3):
    g = torch.Generator().manual_seed(seed)
    extent = torch.tensor(SHAPE, dtype=dtype) * torch.tensor(VOXEL, dtype=dtype)
    means = (
        torch.tensor(ORIGIN, dtype=dtype)
        + (torch.rand(n, 3, generator=g, dtype=dtype) * 1.4 - 0.2) * extent
    )
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 2.0 + 0.4
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    intensities = torch.rand(n, generator=g, dtype=dtype) + 0.1
    return means, scales, quats, intensities


def brute_force(means, scales, quats, intensities):
    """No cut-off at all: every Gaussian everywhere, float64."""
    axes = [o + (np.arange(n) + 0.5) * s for n, s, o in zip(SHAPE, VOXEL, ORIGIN)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    cov = covariance(scales, quats).numpy()
    total = np.zeros(len(points))
    for m, c, i in zip(means.numpy(), cov, intensities.numpy()):
        d = points - m
        total += i * np.exp(-0.5 * np.einsum("pi,ij,pj->p", d, np.linalg.inv(c), d))
    return total.reshape(SHAPE)


def test_matches_the_dense_rule_and_brute_force():
    gaussians = random_gaussians(60)
    ours = voxelize(*gaussians, SHAPE, VOXEL, ORIGIN)
    dense = voxelize_dense(*gaussians, SHAPE, VOXEL, ORIGIN)
    torch.testing.assert_close(ours, dense, rtol=1e-10, atol=1e-12)
    reference = brute_force(*gaussians)
    assert np.linalg.norm(ours.numpy() - reference) / np.linalg.norm(reference) < 2e-2


def test_float32_and_chunking():
    gaussians = random_gaussians(80, seed=1)
    reference = voxelize_dense(*gaussians, SHAPE, VOXEL, ORIGIN)
    small_chunks = voxelize(*(t.float() for t in gaussians), SHAPE, VOXEL, ORIGIN, max_elements=500)
    assert float((small_chunks.double() - reference).norm() / reference.norm()) < 1e-5


def test_culled_gaussians_change_nothing():
    gaussians = random_gaussians(20, seed=2)
    far = [torch.cat([t, t[:5]]) for t in gaussians]
    far[0][-5:] += 1000.0  # five copies far outside the grid
    torch.testing.assert_close(
        voxelize(*far, SHAPE, VOXEL, ORIGIN), voxelize(*gaussians, SHAPE, VOXEL, ORIGIN)
    )


def test_gradients_match_finite_differences_and_the_dense_reference():
    means, scales, quats, intensities = (
        t[:4].clone().requires_grad_(True) for t in random_gaussians(40, seed=3)
    )
    shape = (6, 9, 8)
    assert torch.autograd.gradcheck(
        lambda *a: voxelize(*a, shape, VOXEL, ORIGIN),
        (means, scales, quats, intensities),
        fast_mode=True,
    )
    weights = torch.rand(SHAPE, dtype=torch.float64)
    grads = torch.autograd.grad(
        (voxelize(means, scales, quats, intensities, SHAPE, VOXEL, ORIGIN) * weights).sum(),
        (means, scales, quats, intensities),
    )
    dense = torch.autograd.grad(
        (voxelize_dense(means, scales, quats, intensities, SHAPE, VOXEL, ORIGIN) * weights).sum(),
        (means, scales, quats, intensities),
    )
    for ours, reference in zip(grads, dense):
        torch.testing.assert_close(ours, reference, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("count", [0, 1, 500])
def test_window_groups_equal_a_row_unique(count):
    # The 1-D key keeps torch.unique(dim=0)'s groups, their order and each Gaussian's group,
    # so the accumulation order (and the volume) is unchanged bit for bit.
    generator = torch.Generator().manual_seed(count)
    half_width = _bucket(torch.randint(1, 200, (count, 3), generator=generator))
    half_width[:, 1:] = half_width[:, 1:].amax(dim=1, keepdim=True)
    groups, inverse = torch.unique(half_width, dim=0, return_inverse=True)
    fast_groups, fast_inverse = _window_groups(half_width)
    assert torch.equal(fast_groups, groups) and torch.equal(fast_inverse, inverse)


def test_empty_and_bad_inputs():
    empty = torch.zeros(0, 3)
    assert voxelize(
        empty, empty, torch.zeros(0, 4), torch.zeros(0), (2, 3, 4), VOXEL, ORIGIN
    ).shape == (2, 3, 4)
    with pytest.raises(ValueError, match="quats must have shape"):
        voxelize(
            torch.zeros(2, 3),
            torch.ones(2, 3),
            torch.zeros(3, 4),
            torch.ones(2),
            (2, 3, 4),
            VOXEL,
            ORIGIN,
        )


def test_rotations():
    q = torch.randn(50, 4, dtype=torch.float64)
    r = quaternion_to_rotation(q)
    torch.testing.assert_close(
        r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3)
    )
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(50, dtype=torch.float64))
    quarter_turn_about_z = torch.tensor(
        [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=torch.float64
    )
    x_unit = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # (z, y, x)
    torch.testing.assert_close(
        quaternion_to_rotation(quarter_turn_about_z) @ x_unit,
        torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
    )
    p, s = torch.randn(10, 4, dtype=torch.float64), torch.randn(10, 4, dtype=torch.float64)
    torch.testing.assert_close(
        quaternion_to_rotation(quaternion_multiply(p, s)),
        quaternion_to_rotation(p) @ quaternion_to_rotation(s),
    )


def test_activation_ranges():
    cloud = GaussianCloud(SHAPE, VOXEL, 10)
    with torch.no_grad():
        cloud.raw_scales.copy_(torch.linspace(-1e3, 1e3, 30).reshape(10, 3))
        cloud.raw_intensities.fill_(-50.0)
        cloud.raw_quats.mul_(1e3)
    unit = VOXEL[2]
    assert cloud.scales.min() >= 0.8 * unit - 1e-6 and cloud.scales.max() <= 20 * unit + 1e-6
    torch.testing.assert_close(cloud.quaternions.norm(dim=1), torch.ones(10))
    assert (cloud.intensities >= 0).all()


def test_cloud_init_save_load(tmp_path):
    volume = np.zeros(SHAPE, np.float32)
    volume[6, 10, 9] = 1.0
    cloud = GaussianCloud(SHAPE, VOXEL).from_volume(volume, 8)
    target = cloud.voxel_centers(torch.tensor([[6, 10, 9]]))
    assert (cloud.means - target).abs().max() <= 0.5 * max(VOXEL) + 1e-6
    torch.testing.assert_close(cloud.scales, torch.full((8, 3), VOXEL[2]), rtol=1e-4, atol=1e-5)
    cloud.save(tmp_path / "g.pt")
    loaded = GaussianCloud.load(tmp_path / "g.pt")
    torch.testing.assert_close(loaded(), cloud())
    other = GaussianCloud(SHAPE, VOXEL, 3)
    other.load_state_dict(cloud.state_dict())  # a different count resizes
    assert other.count == 8


def test_densify_keeps_adam_state_aligned():
    cloud = GaussianCloud(SHAPE, VOXEL, 6, seed=4)
    optimizer = torch.optim.Adam(
        [
            {"params": [getattr(cloud, n)], "lr": 0.01}
            for n in ("means", "raw_scales", "raw_quats", "raw_intensities")
        ]
    )
    cloud().square().sum().backward()
    optimizer.step()
    before = {id(p): optimizer.state[p]["exp_avg"].clone() for p in cloud.parameters()}
    means_moment = before[id(cloud.means)]
    keep = torch.tensor([True, False, True, True, False, True])
    select_gaussians(cloud, optimizer, keep)
    append_gaussians(
        cloud,
        optimizer,
        {
            n: getattr(cloud, n).detach()[:2]
            for n in ("means", "raw_scales", "raw_quats", "raw_intensities")
        },
    )
    assert cloud.count == 6
    for parameter in cloud.parameters():
        assert optimizer.state[parameter]["exp_avg"].shape == parameter.shape
    assert all(
        any(p is q for q in cloud.parameters()) for g in optimizer.param_groups for p in g["params"]
    )
    torch.testing.assert_close(optimizer.state[cloud.means]["exp_avg"][:4], means_moment[keep])
    assert optimizer.state[cloud.means]["exp_avg"][4:].abs().max() == 0
    cloud().sum().backward()
    optimizer.step()  # the optimizer still works on the new tensors


def test_strategy_clones_splits_and_prunes():
    cloud = GaussianCloud(SHAPE, VOXEL, 4, seed=5)
    with torch.no_grad():
        cloud.raw_scales[1] = 5.0  # large: split
        cloud.raw_intensities[3] = -20.0  # vanishing: pruned
    strategy = DensificationStrategy(
        Densification(
            start=1, interval=1, stop=10, grad_threshold=0.0, split_scale=2.0, min_gaussians=1
        )
    )
    cloud.means.grad = torch.ones(4, 3)
    strategy.update_statistics(cloud)
    assert strategy.step(cloud, None, step=0) is None  # not due
    changes = strategy.step(cloud, None, step=1)
    assert changes == {"cloned": 3, "split": 1, "pruned": 2, "count": 6}
    disabled = DensificationStrategy(Densification(enabled=False))
    disabled.update_statistics(cloud)
    assert disabled.step(cloud, None, 1) is None


def test_densification_stops_once_the_count_settles():
    """Two events in a row changing at most 1% of the Gaussians stop densification for good;
    a busy event in between starts the count again; the state survives a state_dict."""
    cloud = GaussianCloud(SHAPE, VOXEL, 200, seed=6)
    settings = Densification(
        start=1, interval=1, stop=100, grad_threshold=1.0, stable_fraction=0.01, stable_events=2
    )
    strategy = DensificationStrategy(settings)

    def event(step, gradient=0.0):
        cloud.means.grad = torch.full((cloud.count, 3), gradient)
        cloud.means.grad[0] = 10.0  # one candidate: 1 of 200 changed, within 1%
        strategy.update_statistics(cloud)
        return strategy.step(cloud, None, step)

    assert "stopped_at_step" not in event(1)
    busy = event(2, gradient=10.0)  # every Gaussian cloned or split
    assert busy["cloned"] + busy["split"] > 2 and strategy.quiet_events == 0
    assert "stopped_at_step" not in event(3)
    settled = event(4)
    assert settled["stopped_at_step"] == 4 and strategy.stopped_at == 4
    count = cloud.count
    assert event(5, gradient=10.0) is None and cloud.count == count
    resumed = DensificationStrategy(settings)
    resumed.load_state_dict(strategy.state_dict())
    assert not resumed.active and resumed.stopped_at == 4
    never = DensificationStrategy(Densification(start=1, interval=1, grad_threshold=1.0))
    for step in (1, 2, 3):
        cloud.means.grad = torch.zeros(cloud.count, 3)
        never.update_statistics(cloud)
        assert "stopped_at_step" not in never.step(cloud, None, step)
    with pytest.raises(ValueError, match=r"densification.stable_fraction must be a fraction"):
        Densification(stable_fraction=1.0)


def test_voxelizing_first_under_inference_mode_then_differentiating():
    """The voxelizer's constants are made once per device and type; those first made during a
    validation (inference mode) must still serve a training step's backward."""
    from fgat._core.devices import constant

    constant.cache_clear()  # as in a fresh process
    gaussians = [t.float() for t in random_gaussians(6, seed=9)]
    with torch.inference_mode():
        first = voxelize(*gaussians, SHAPE, VOXEL, ORIGIN)
    leaves = [t.clone().requires_grad_(True) for t in gaussians]
    again = voxelize(*leaves, SHAPE, VOXEL, ORIGIN)
    torch.testing.assert_close(again.detach(), first, rtol=0, atol=0)
    again.sum().backward()
    assert all(torch.isfinite(leaf.grad).all() for leaf in leaves)
