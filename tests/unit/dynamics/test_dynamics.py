"""HexPlane features, deformation MLP, anchoring and the plane regularisers (Notes S3.3-S3.5.3)."""

import copy

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fgat._core.devices import DispatchCount
from fgat.dynamics import (
    DeformationField,
    HexPlane,
    apply_deformation,
    plane_l1_to_one,
    plane_regularisers,
    plane_tv,
    temporal_smoothness,
)
from fgat.dynamics.deformation import HEADS, normalized_positions
from fgat.dynamics.hexplane import AXES, PLANES
from fgat.gaussians.rotation import (
    normalize_quaternion,
    quaternion_multiply,
    quaternion_to_rotation,
)


def small_field(seed=0):
    torch.manual_seed(seed)
    return DeformationField(
        HexPlane(
            channels=4, spatial_resolution=(4, 5, 6), temporal_resolution=3, levels=2, seed=seed
        ),
        width=16,
        depth=2,
        reference_time=-0.5,
    )


def test_hexplane_feature_shape_and_time_independence_at_initialisation():
    hexplane = HexPlane(channels=4, spatial_resolution=(4, 5, 6), temporal_resolution=3, levels=3)
    positions = torch.rand(10, 3) * 2 - 1
    features = hexplane(positions, 0.3)
    assert features.shape == (10, 12) and hexplane.feature_dim == 12
    torch.testing.assert_close(
        hexplane(positions, -0.9), features, rtol=1e-6, atol=0
    )  # temporal planes = 1
    assert hexplane.plane(2, ("x", "y")).shape == (
        1,
        4,
        6 * 4,
        5 * 4,
    )  # (1, C, R_x, R_y) at level 2
    assert hexplane.plane(0, ("z", "t")).shape == (1, 4, 4, 3)


def test_hexplane_feature_is_the_product_of_bilinear_samples():
    hexplane = HexPlane(channels=1, spatial_resolution=(2, 2, 2), temporal_resolution=2, levels=1)
    with torch.no_grad():
        for pair, value in ((("x", "y"), 2.0), (("x", "z"), 3.0), (("y", "z"), 5.0)):
            hexplane.plane(0, pair).fill_(value)
        hexplane.plane(0, ("x", "t")).copy_(
            torch.tensor([[0.0, 1.0], [0.0, 1.0]])
        )  # rows x, columns t
    # t = -1 -> 0, t = +1 -> 1, linear in between; the other planes are constant
    times = torch.tensor([-1.0, 0.0, 0.5])
    features = hexplane(torch.zeros(3, 3), times)
    torch.testing.assert_close(features[:, 0], 30.0 * (times + 1) / 2)


def plane_by_plane(hexplane, positions, times):
    """Eq. S18 in float64, one plane at a time: each plane's bilinear samples (its own
    ``grid_sample``), multiplied over the six planes and concatenated over the levels."""
    coordinates = torch.cat(
        [
            positions.double(),
            torch.as_tensor(times, dtype=torch.float64).expand(len(positions))[:, None],
        ],
        dim=1,
    )
    features = []
    for level in range(hexplane.levels):
        product = torch.ones(len(positions), hexplane.channels, dtype=torch.float64)
        for a, b in PLANES:
            grid = coordinates[:, [AXES[b], AXES[a]]].reshape(1, -1, 1, 2)
            plane = hexplane.plane(level, (a, b)).detach().double()
            sample = F.grid_sample(
                plane, grid, mode="bilinear", padding_mode="border", align_corners=True
            )
            product = product * sample[0, :, :, 0].T
        features.append(product)
    return torch.cat(features, dim=1)


@pytest.mark.parametrize(
    "spatial, temporal", [((4, 5, 6), 3), ((8, 8, 8), 8)], ids=["mixed", "one-shape"]
)
def test_features_at_several_times_against_a_float64_plane_by_plane_reference(spatial, temporal):
    hexplane = HexPlane(channels=3, spatial_resolution=spatial, temporal_resolution=temporal)
    generator = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for plane in hexplane.planes:
            plane.uniform_(0.2, 1.5, generator=generator)
    positions = torch.rand(50, 3, generator=generator) * 2.2 - 1.1  # some beyond the border
    times = (0.3, torch.rand(50, generator=generator) * 2 - 1, torch.tensor(-1.0))
    features = hexplane.at_times(positions, times)
    for t, feature in zip(times, features):
        reference = plane_by_plane(hexplane, positions, t)
        torch.testing.assert_close(feature.double(), reference, rtol=1e-5, atol=0)
        assert torch.equal(feature, hexplane(positions, t))  # shared samples change nothing
    with DispatchCount() as one:
        hexplane(positions, 0.3)
    with DispatchCount() as two:
        hexplane.at_times(positions, times[:2])
    # the spatial planes are sampled once: at least their concatenation, grid_sample and two
    # products fewer per level than two separate calls
    assert two.total <= 2 * one.total - 4 * hexplane.levels


def test_deformation_field_gradients_against_two_float64_passes():
    """The shared spatial samples leave the gradients those of ``raw(t) - raw(t_ref)`` made as
    two separate passes, computed in float64."""
    field = small_field(3)
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.add_(0.3 * torch.randn_like(parameter))
    positions, times = torch.rand(30, 3) * 2 - 1, torch.rand(30) * 2 - 1
    weights = {name: torch.randn(30, n, dtype=torch.float64) for name, n in HEADS.items()}

    def loss(delta):
        return sum(
            (delta[name].reshape(30, -1) * weights[name].to(delta[name])).sum() for name in HEADS
        )

    def two_passes(model):
        now, reference = (
            model.raw(positions.double(), times.double()),
            model.raw(positions.double(), model.reference_time),
        )
        delta = {name: now[name] - reference[name] for name in HEADS}
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        delta["quats"] = normalize_quaternion(identity + delta["quats"])
        return delta

    reference = copy.deepcopy(field).double()
    loss(two_passes(reference)).backward()
    loss(field(positions, times)).backward()
    # float32 rounds each parameter's gradient relative to the whole backward pass's terms,
    # which for a small gradient (t and t_ref cancelling) can be far larger than itself.
    scale = max(float(p.grad.abs().max()) for p in reference.parameters())
    for got, want in zip(field.parameters(), reference.parameters()):
        torch.testing.assert_close(got.grad.double(), want.grad, rtol=1e-4, atol=1e-5 * scale)


def test_anchoring_is_exact_whatever_the_weights():
    field = small_field()
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.add_(torch.randn_like(parameter))  # far from the initialisation
    positions = torch.rand(20, 3) * 2 - 1
    delta = field(positions, field.reference_time)
    for name in ("means", "scales", "intensities"):
        assert torch.equal(delta[name], torch.zeros_like(delta[name])), name
    assert torch.equal(delta["quats"], torch.tensor([1.0, 0, 0, 0]).expand(20, 4))
    means, scales = torch.randn(20, 3), torch.rand(20, 3) + 0.5
    quats, intensities = normalize_quaternion(torch.randn(20, 4)), torch.rand(20)
    deformed = apply_deformation(means, scales, quats, intensities, delta)
    for before, after in zip((means, scales, quats, intensities), deformed):
        assert torch.equal(before, after)  # G_{t_ref} == G_0 exactly
    moved = field(positions, 0.7)
    assert moved["means"].abs().max() > 0 and torch.allclose(
        moved["quats"].norm(dim=1), torch.ones(20)
    )


def test_deformation_gradients_reach_hexplane_and_mlp():
    field = small_field(1)
    positions, times = torch.rand(8, 3) * 2 - 1, torch.rand(8) * 2 - 1
    delta = field(positions, times)
    sum(value.sum() for value in delta.values()).backward()
    # at initialisation the field is static: only the spatio-temporal planes can start it moving
    assert all(float(p.grad.abs().sum()) == 0 for p in field.heads.parameters())
    assert all(float(p.grad.abs().sum()) > 0 for p in field.hexplane.spatiotemporal_planes())
    field.zero_grad()
    with torch.no_grad():
        for plane in field.hexplane.spatiotemporal_planes():
            plane.add_(
                torch.randn_like(plane)
            )  # enough to change ReLU patterns between t and t_ref
    delta = field(positions, times)
    sum(value.sum() for value in delta.values()).backward()
    for name, parameter in field.named_parameters():
        if not name.endswith(
            "bias"
        ):  # trunk biases cancel between t and t_ref while ReLU patterns agree
            assert float(parameter.grad.abs().sum()) > 0, name


def test_apply_deformation_composes_rotations_and_guards_attributes():
    p, q = normalize_quaternion(torch.randn(5, 4)), normalize_quaternion(torch.randn(5, 4))
    delta = {
        "means": torch.ones(5, 3),
        "scales": -10 * torch.ones(5, 3),
        "quats": p,
        "intensities": -torch.ones(5),
    }
    means, scales, quats, intensities = apply_deformation(
        torch.zeros(5, 3), torch.ones(5, 3), q, torch.ones(5) * 0.5, delta
    )
    torch.testing.assert_close(
        quaternion_to_rotation(quats), quaternion_to_rotation(p) @ quaternion_to_rotation(q)
    )
    torch.testing.assert_close(quats, quaternion_multiply(p, q))
    assert torch.equal(means, torch.ones(5, 3)) and scales.min() > 0 and intensities.min() == 0


def test_regularisers_over_planes_of_several_shapes_equal_a_float64_loop():
    """Planes are stacked by shape inside the regularisers; the sums equal a NumPy loop over
    the planes one by one, and so do the gradients' per-plane totals."""
    g = torch.Generator().manual_seed(4)
    shapes = [(1, 3, 5, 7), (1, 3, 5, 7), (1, 3, 6, 4), (1, 3, 5, 7), (1, 3, 6, 4), (1, 3, 2, 9)]
    planes = [torch.rand(s, generator=g, dtype=torch.float64, requires_grad=True) for s in shapes]
    arrays = [p.detach().numpy()[0] for p in planes]
    expected = {
        plane_tv: sum(
            (np.diff(a, axis=-2) ** 2).sum() / a.size + (np.diff(a, axis=-1) ** 2).sum() / a.size
            for a in arrays
        ),
        temporal_smoothness: sum((np.diff(a, 2, axis=-1) ** 2).sum() / a.size for a in arrays),
        plane_l1_to_one: sum(np.abs(1 - a).sum() / a.size for a in arrays),
    }
    for regulariser, value in expected.items():
        total = regulariser(planes)
        assert float(total) == pytest.approx(value, rel=1e-12), regulariser.__name__
        grads = torch.autograd.grad(total, planes)
        one_by_one = [torch.autograd.grad(regulariser([p]), p)[0] for p in planes]
        for ours, reference in zip(grads, one_by_one):
            torch.testing.assert_close(ours, reference, rtol=1e-12, atol=1e-15)


def test_regularisers_together_equal_a_float64_loop_over_mixed_memberships():
    """plane_regularisers stacks each shape once for all three terms: spatial and
    spatio-temporal planes of one shape share a stack, a plane may enter Eq. S30 only, Eqs.
    S31-S32 only, or both, and time planes of 2 samples have no second difference. Values equal
    a NumPy loop plane by plane; gradients those of the equations written with slices."""
    g = torch.Generator().manual_seed(7)
    shapes = [(1, 2, 4, 5), (1, 2, 4, 5), (1, 2, 4, 5), (1, 2, 3, 2), (1, 2, 6, 5), (2, 3)]
    planes = [torch.rand(s, generator=g, dtype=torch.float64, requires_grad=True) for s in shapes]
    tv_planes = [planes[0], planes[1], planes[3], planes[5]]
    temporal = [planes[1], planes[2], planes[3], planes[4]]  # planes[2], [4]: Eqs. S31-S32 only
    arrays = {id(p): p.detach().numpy() for p in planes}

    def reference(term, members):
        return sum(term(arrays[id(p)]) / arrays[id(p)].size for p in members)

    expected = {
        "tv": reference(
            lambda a: (np.diff(a, axis=-2) ** 2).sum() + (np.diff(a, axis=-1) ** 2).sum(),
            tv_planes,
        ),
        "sm": reference(lambda a: (np.diff(a, 2, axis=-1) ** 2).sum(), temporal),
        "l1": reference(lambda a: np.abs(1 - a).sum(), temporal),
    }
    terms = plane_regularisers(tv_planes, temporal)
    assert {k: float(v) for k, v in terms.items()} == pytest.approx(expected, rel=1e-12)
    weights = {"tv": 0.3, "sm": 0.5, "l1": 0.7}
    grads = torch.autograd.grad(sum(weights[k] * v for k, v in terms.items()), planes)
    sliced = (
        sum(  # the equations written with slices, plane by plane
            0.3 * ((p[..., 1:, :] - p[..., :-1, :]).square().sum() / p.numel())
            + 0.3 * ((p[..., 1:] - p[..., :-1]).square().sum() / p.numel())
            for p in tv_planes
        )
        + sum(
            0.5 * (p[..., 2:] - 2 * p[..., 1:-1] + p[..., :-2]).square().sum() / p.numel()
            + 0.7 * (1 - p).abs().sum() / p.numel()
            for p in temporal
        )
    )
    for ours, reference_grad in zip(grads, torch.autograd.grad(sliced, planes)):
        torch.testing.assert_close(ours, reference_grad, rtol=1e-12, atol=1e-15)
    only_sm = plane_regularisers(tv_planes, temporal, terms=("sm",))
    assert set(only_sm) == {"sm"} and float(only_sm["sm"]) == pytest.approx(expected["sm"])
    assert float(plane_regularisers([], [], terms=("tv",))["tv"]) == 0
    with pytest.raises(ValueError, match=r"unknown plane regularisers \['tvv'\]"):
        plane_regularisers(planes, terms=("tvv",))


def test_regularisers_against_hand_computed_values():
    plane = torch.tensor([[[[0.0, 1.0, 4.0], [2.0, 2.0, 2.0]]]])  # (1, 1, 2, 3)
    # first differences: along rows (2-0, 2-1, 2-4) -> 4 + 1 + 4; along columns (1, 3, 0, 0) -> 10
    assert float(plane_tv([plane])) == pytest.approx((9 + 10) / 6)
    # second differences along the last axis: (4 - 2 + 0) = 2 and 0 -> 4 / 6
    assert float(temporal_smoothness([plane])) == pytest.approx(4 / 6)
    # |1 - P|: 1 + 0 + 3 + 1 + 1 + 1 = 7 -> 7 / 6
    assert float(plane_l1_to_one([plane])) == pytest.approx(7 / 6)
    ones = torch.ones(1, 2, 3, 4)
    assert float(plane_l1_to_one([ones])) == 0 and float(temporal_smoothness([ones])) == 0
    assert float(plane_tv([plane, plane])) == pytest.approx(2 * 19 / 6)  # sums over planes
    hexplane = HexPlane(channels=2, spatial_resolution=(3, 3, 3), temporal_resolution=4, levels=2)
    assert (
        float(plane_l1_to_one(hexplane.spatiotemporal_planes()).detach()) == 0
    )  # identity at initialisation


def test_normalized_positions_and_errors():
    means = torch.tensor([[0.0, 0.0, 0.0], [10.0, 20.0, 30.0], [5.0, 10.0, 15.0]])
    torch.testing.assert_close(
        normalized_positions(means, (0, 0, 0), (10, 20, 30)),
        torch.tensor([[-1.0, -1, -1], [1, 1, 1], [0, 0, 0]]),
    )
    with pytest.raises(ValueError, match="every resolution >= 2"):
        HexPlane(temporal_resolution=1)
    with pytest.raises(ValueError, match=r"positions must have shape \(N, 3\)"):
        HexPlane(channels=1, spatial_resolution=(2, 2, 2), temporal_resolution=2)(
            torch.zeros(4, 2), 0.0
        )
