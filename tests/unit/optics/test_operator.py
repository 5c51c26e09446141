import numpy as np
import pytest
import scipy.signal
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.func import jacfwd, jvp, vmap

from fgat._core.devices import DispatchCount
from fgat.optics.operator import FLFMOperator, crop_views, place_views, spectral_grid
from fgat.optics.psf import fast_fft_size


def reference_forward(volume, psf):
    """Per view: sum over depth of the full linear convolution (scipy, float64) cropped at the
    PSF centre ``(h // 2, w // 2)``: ``fftconvolve(mode="same")`` for odd PSF sizes."""
    (y, x), (h, w) = volume.shape[1:], psf.shape[2:]
    return np.stack(
        [
            sum(
                scipy.signal.fftconvolve(volume[z], psf[v, z], mode="full")
                for z in range(volume.shape[0])
            )[h // 2 : h // 2 + y, w // 2 : w // 2 + x]
            for v in range(psf.shape[0])
        ]
    )


shapes = st.tuples(
    st.integers(1, 3),
    st.integers(1, 4),
    st.integers(3, 14),
    st.integers(3, 14),
    st.integers(0, 9),
    st.integers(0, 9),
)


def random_case(case, dtype, seed, odd=True):
    views, depths, y, x, hh, hw = case
    h, w = (2 * hh + 1, 2 * hw + 1) if odd else (2 * hh + 2, 2 * hw + 2)
    generator = torch.Generator().manual_seed(seed)
    psf = torch.rand(views, depths, h, w, generator=generator, dtype=torch.float64)
    volume = torch.rand(depths, y, x, generator=generator, dtype=torch.float64)
    return psf.to(dtype), volume.to(dtype)


@settings(max_examples=40, deadline=None)
@given(case=shapes, seed=st.integers(0, 2**31 - 1))
def test_forward_matches_scipy_fftconvolve_float64(case, seed):
    psf, volume = random_case(case, torch.float64, seed, odd=seed % 3 > 0)
    ours = FLFMOperator(psf, tuple(volume.shape)).forward(volume).numpy()
    reference = reference_forward(volume.numpy(), psf.numpy())
    np.testing.assert_allclose(ours, reference, rtol=1e-10, atol=1e-10 * np.abs(reference).max())


@settings(max_examples=20, deadline=None)
@given(case=shapes, seed=st.integers(0, 2**31 - 1))
def test_forward_float32_close_to_float64_reference(case, seed):
    psf, volume = random_case(case, torch.float32, seed)
    ours = FLFMOperator(psf, tuple(volume.shape)).forward(volume).double().numpy()
    reference = reference_forward(volume.double().numpy(), psf.double().numpy())
    assert np.abs(ours - reference).max() <= 1e-5 * np.abs(reference).max()


@pytest.mark.parametrize("n, p", [(300, 161), (12, 5), (9, 6), (3, 19), (64, 65)])
def test_spectral_grid_is_exact_and_the_bound_tight(n, p):
    """Circular convolution on ``N = max(n + p // 2, p)`` points gives the cropped linear
    convolution exactly (float64 DFTs), ``N - 1`` does not when ``n + p // 2 > p``; the operator
    takes the fast size of that bound."""
    rng = np.random.default_rng(n * 1000 + p)
    signal, kernel = rng.random(n), rng.random(p)
    crop = np.arange(p // 2, p // 2 + n)
    linear = np.convolve(signal, kernel)[crop]

    def circular(size):
        folded = np.bincount(np.arange(p) % size, kernel, minlength=size)
        return np.fft.irfft(np.fft.rfft(signal, size) * np.fft.rfft(folded), size)[crop % size]

    bound = max(n + p // 2, p)
    np.testing.assert_allclose(circular(bound), linear, rtol=1e-12, atol=1e-12)
    if bound > p:
        assert np.abs(circular(bound - 1) - linear).max() > 1e-3
    assert spectral_grid((n, 7), (p, 3)) == (fast_fft_size(bound), fast_fft_size(max(7 + 1, 3)))
    assert spectral_grid((300, 300), (161, 161)) == (384, 384)


def test_even_psf_center_convention():
    # PSF centre at (h // 2, w // 2): a delta there is the identity.
    psf = torch.zeros(1, 1, 4, 6, dtype=torch.float64)
    psf[0, 0, 2, 3] = 1.0
    volume = torch.rand(1, 7, 9, dtype=torch.float64)
    out = FLFMOperator(psf, (1, 7, 9)).forward(volume)
    torch.testing.assert_close(out[0], volume[0])


def _flfm(case, dtype, seed):
    psf, volume = random_case(case, dtype, seed, odd=seed % 2 == 0)
    operator = FLFMOperator(psf, tuple(volume.shape), depth_chunk=1 + seed % volume.shape[0])
    return (
        operator.forward,
        operator.adjoint,
        tuple(volume.shape),
        (psf.shape[0], *volume.shape[1:]),
    )


def _sensor(case, dtype, seed):
    views, _, y, x, _, _ = case
    centers = torch.tensor(
        [[y // 2 + 1 + v * (y + 2), x // 2 + 3] for v in range(views)], dtype=torch.float64
    )
    sensor_shape = (views * (y + 2) + 2, x + 6)
    return (
        lambda v: place_views(v, centers, sensor_shape),
        lambda s: crop_views(s, centers, (y, x)),
        (views, y, x),
        sensor_shape,
    )


# deepinv-style registry: every linear operator of the optics layer with its exact adjoint.
LINEAR_OPERATORS = {"flfm": _flfm, "sensor": _sensor}


@pytest.mark.parametrize("name", LINEAR_OPERATORS)
@pytest.mark.parametrize(
    "dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)], ids=["float64", "float32"]
)
@settings(max_examples=25, deadline=None)
@given(case=shapes, seed=st.integers(0, 2**31 - 1), batch=st.sampled_from([(), (2,)]))
def test_adjoint_identity(name, dtype, tol, case, seed, batch):
    forward, adjoint, in_shape, out_shape = LINEAR_OPERATORS[name](case, dtype, seed)
    generator = torch.Generator().manual_seed(seed + 1)
    x = torch.rand(*batch, *in_shape, generator=generator, dtype=torch.float64).to(dtype)
    y = torch.rand(*batch, *out_shape, generator=generator, dtype=torch.float64).to(dtype)
    ax, aty = forward(x), adjoint(y)
    assert ax.shape == (*batch, *out_shape) and aty.shape == (*batch, *in_shape)
    lhs = float((ax.double() * y.double()).sum())
    rhs = float((x.double() * aty.double()).sum())
    assert abs(lhs - rhs) <= tol * max(abs(lhs), abs(rhs))


def test_batched_equals_looped():
    """Every item of a batch is the scipy float64 reference of that volume alone."""
    psf, volume = random_case((2, 3, 8, 9, 1, 2), torch.float64, 3)
    operator = FLFMOperator(psf, (3, 8, 9))
    items = [volume, 2 * volume + 1]
    out = operator.forward(torch.stack(items).reshape(1, 2, 3, 8, 9))
    assert out.shape == (1, 2, 2, 8, 9)
    for k, item in enumerate(items):
        reference = reference_forward(item.numpy(), psf.numpy())
        np.testing.assert_allclose(out[0, k].numpy(), reference, rtol=1e-10, atol=1e-12)


def test_gradients_volume_and_psf():
    psf, volume = random_case((2, 2, 5, 4, 1, 1), torch.float64, 5)
    psf.requires_grad_(True)
    volume.requires_grad_(True)
    views = torch.rand(2, 5, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda p, v: FLFMOperator(p, (2, 5, 4)).forward(v), (psf, volume)
    )
    assert torch.autograd.gradcheck(
        lambda p, r: FLFMOperator(p, (2, 5, 4)).adjoint(r), (psf, views)
    )


@pytest.mark.slow
def test_learned_psf_projection_in_chunks():
    """With the PSF learned, each depth chunk is one product and sum: on a CPU the views equal
    the fixed operator's bit for bit (the same sums in the same order), and the PSF gradient
    passes the finite-difference check, in chunks or whole."""
    psf32, volume32 = random_case((3, 7, 12, 10, 2, 1), torch.float32, 4)
    fixed = FLFMOperator(psf32, (7, 12, 10), depth_chunk=3).forward(volume32)
    for chunk in (1, 3, 7):
        learned = FLFMOperator(psf32.clone().requires_grad_(True), (7, 12, 10), depth_chunk=chunk)
        assert torch.equal(learned.forward(volume32).detach(), fixed)
    psf, volume = random_case((2, 5, 6, 5, 1, 2), torch.float64, 9)
    learned = psf.clone().requires_grad_(True)
    for chunk in (1, 2, 5):
        assert torch.autograd.gradcheck(
            lambda p, chunk=chunk: FLFMOperator(p, (5, 6, 5), depth_chunk=chunk).forward(volume),
            (learned,),
        )


def test_learned_psf_backward_does_not_grow_with_depth():
    """The backward of a learned-PSF projection dispatches as many operations for 16 depths in
    a chunk as for 2 (no per-depth nodes: on a GPU each costs host time)."""

    def backward_operations(depths: int) -> int:
        psf, volume = random_case((3, depths, 8, 8, 2, 2), torch.float32, 1)
        psf.requires_grad_(True)
        loss = FLFMOperator(psf, (depths, 8, 8), depth_chunk=depths).forward(volume).sum()
        with DispatchCount() as count:
            loss.backward()
        return count.total

    assert backward_operations(2) == backward_operations(16)


def test_depth_chunks_change_nothing_bit_for_bit():
    psf, volume = random_case((3, 7, 12, 10, 2, 1), torch.float32, 11)
    batch = torch.stack([volume, volume.flip(-1)])
    whole = FLFMOperator(psf, (7, 12, 10), depth_chunk=7)
    views = whole.forward(batch)
    for chunk in (1, 2, 3, 5):
        chunked = FLFMOperator(psf, (7, 12, 10), depth_chunk=chunk)
        assert torch.equal(chunked.forward(batch), views)
        assert torch.equal(chunked.adjoint(views), whole.adjoint(views))


def test_a_view_whose_spectrum_plane_outgrows_the_chunk_budget_gets_one_plane_chunks():
    """On a 2048^2 view one float32 spectrum plane exceeds the CPU's chunk budget: the default
    chunk is one plane, and a point projects to its PSF centred on it (scipy's "same" rule)."""
    psf = torch.rand(1, 2, 5, 5, generator=torch.Generator().manual_seed(3))
    operator = FLFMOperator(psf, (2, 2048, 2048))
    assert operator.depth_chunk == 1
    volume = torch.zeros(2, 2048, 2048)
    volume[1, 1000, 1500] = 1.0
    views = operator.forward(volume)
    torch.testing.assert_close(views[0, 998:1003, 1498:1503], psf[0, 1], atol=1e-6, rtol=1e-5)
    assert float(views.abs().sum()) == pytest.approx(float(psf[0, 1].sum()), rel=1e-4)


def test_reused_buffers_change_nothing_bit_for_bit():
    """Projections outside autograd reuse the operator's padded planes and spectra; they equal
    the allocating path (the one a graph records) bit for bit, whatever the batch sizes, depth
    chunks and inference mode of the calls before, and never hand out a buffer."""
    psf, volume = random_case((3, 7, 12, 10, 4, 2), torch.float32, 5)
    operator = FLFMOperator(psf, (7, 12, 10), depth_chunk=3)
    batches = [volume, torch.stack([volume.flip(-1), volume, 2 * volume]), volume.flip(-2)]
    with torch.no_grad():
        first = operator.forward(batches[0])
    kept = first.clone()
    for mode in (torch.no_grad, torch.inference_mode, torch.no_grad):
        for batch in batches:
            fresh = operator._project(batch.clone().requires_grad_(True)).detach()
            with mode():
                views = operator.forward(batch)
                back = operator.adjoint(views)
            assert torch.equal(views, fresh)
            assert torch.equal(back, operator._back_project(views.clone().requires_grad_(True)))
    assert torch.equal(first, kept)


@pytest.mark.slow
def test_volume_gradient_is_the_adjoint_of_the_autograd_path():
    # Fixed PSF: the projection's backward is A^T (and A^T's is A); compared with
    # differentiating through the FFTs, which is what runs when the PSF itself is learned.
    psf, volume = random_case((2, 5, 7, 6, 1, 2), torch.float64, 7)
    operator = FLFMOperator(psf, (5, 7, 6), depth_chunk=2)
    volume.requires_grad_(True)
    views = torch.rand(2, 7, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(operator.forward, (volume,))
    assert torch.autograd.gradcheck(operator.adjoint, (views,))
    assert torch.autograd.gradgradcheck(operator.forward, (volume,))
    weights = torch.rand(2, 7, 6, dtype=torch.float64)
    (custom,) = torch.autograd.grad((operator.forward(volume) * weights).sum(), volume)
    (traced,) = torch.autograd.grad((operator._project(volume) * weights).sum(), volume)
    torch.testing.assert_close(custom, traced, rtol=1e-12, atol=1e-12)


def test_sensor_round_trip_and_placement():
    views = torch.rand(3, 5, 7, dtype=torch.float64)
    centers = torch.tensor([[10.2, 10.0], [10.0, 30.4], [30.0, 20.0]])
    image = FLFMOperator.sensor(views, centers, (40, 45))
    assert image[10, 10] == views[0, 2, 3]  # patch centre (h // 2, w // 2) on round(center)
    torch.testing.assert_close(FLFMOperator.views_from_sensor(image, centers, (5, 7)), views)
    assert image.sum().item() == pytest.approx(views.sum().item())


@pytest.mark.parametrize(
    "bad,match",
    [
        (dict(psf=torch.zeros(2, 3, 3)), "shape \\(V, Z, h, w\\)"),
        (dict(psf=torch.zeros(1, 2, 3, 3), shape=(3, 8, 8)), "2 depths but volume_shape has Z = 3"),
        (dict(psf=torch.zeros(1, 1, 3, 3, dtype=torch.int64)), "float32 or float64"),
    ],
)
def test_bad_construction(bad, match):
    with pytest.raises(ValueError, match=match):
        FLFMOperator(bad["psf"], bad.get("shape", (1, 8, 8)))


def test_bad_calls():
    with pytest.raises(ValueError, match="depth_chunk must be a positive number"):
        FLFMOperator(torch.rand(2, 3, 3, 3), (3, 8, 8), depth_chunk=0)
    operator = FLFMOperator(torch.rand(2, 3, 3, 3), (3, 8, 8))
    with pytest.raises(ValueError, match="volume must end in shape"):
        operator.forward(torch.rand(3, 8, 9))
    with pytest.raises(ValueError, match="views must end in shape"):
        operator.adjoint(torch.rand(3, 8, 8))
    with pytest.raises(ValueError, match="does not fit"):
        FLFMOperator.sensor(torch.rand(1, 5, 5), torch.tensor([[1.0, 1.0]]), (20, 20))


def test_forward_mode_and_vmap_through_a_fixed_operator_project_the_tangents():
    """With fixed OTFs the projection is linear: its Jacobian-vector product is the projection
    of the tangent (forward mode and vmap take the spectral path), and the forward-mode Jacobian
    equals the reverse-mode one (the adjoint)."""
    generator = torch.Generator().manual_seed(3)
    psf = torch.rand(2, 3, 5, 5, generator=generator, dtype=torch.float64)
    operator = FLFMOperator(psf, (3, 6, 7))
    volume = torch.rand(3, 6, 7, generator=generator, dtype=torch.float64)
    for project, point in ((operator.forward, volume), (operator.adjoint, operator(volume))):
        tangents = torch.rand(4, *point.shape, generator=generator, dtype=torch.float64)
        value, derivative = jvp(project, (point,), (tangents[0],))
        torch.testing.assert_close(value, project(point), rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(derivative, project(tangents[0]), rtol=1e-12, atol=1e-15)
        pushed = vmap(lambda t, p=project, x=point: jvp(p, (x,), (t,))[1])(tangents)
        expected = torch.stack([project(t) for t in tangents])
        torch.testing.assert_close(pushed, expected, rtol=1e-12, atol=1e-15)
        reverse = torch.autograd.functional.jacobian(project, point)
        torch.testing.assert_close(jacfwd(project)(point), reverse, rtol=1e-10, atol=1e-14)
