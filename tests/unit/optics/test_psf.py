import math
import warnings

import numpy as np
import pytest
import torch

from fgat._core.devices import DispatchCount
from fgat.optics.propagation import (
    angular_spectrum_propagate,
    angular_spectrum_transfer,
    defocus_phase_per_um,
)
from fgat.optics.psf import (
    AREA_SUBSAMPLES,
    CROSSTALK_TOLERANCE,
    JPGM,
    MFT_SUBSAMPLING,
    NYQUIST,
    bilinear_crops,
    fast_fft_size,
    normalized_depth,
)
from fgat.optics.pupil import lattice_angle, lenslet_aperture, pupil_coordinates
from fgat.optics.systems import load_system


def relative_l2(a, b):
    return float((a - b).norm() / b.norm())


def assert_paths_agree(model):
    """``"auto"`` picks the matrix Fourier transform for ``model``, and it agrees with the
    angular-spectrum reference within 1e-3 (relative L2)."""
    assert model.resolved_method() == "mft"
    with torch.no_grad(), warnings.catch_warnings():
        model.method = "mft"
        fast = model()
        model.method = "asm"  # an MFT grid coarser than the camera's is refined for the ASM
        warnings.filterwarnings("ignore", "JPGM: the pupil-plane phase of the asm path")
        reference = model()
    assert relative_l2(fast, reference) < 1e-3


def centroids(stack):
    """(V, Z, 2) intensity centroids (row, col) in crop pixels relative to the crop centre."""
    v, z, h, w = stack.shape
    rows = torch.arange(h, dtype=stack.dtype) - h // 2
    cols = torch.arange(w, dtype=stack.dtype) - w // 2
    total = stack.sum(dim=(2, 3))
    return torch.stack(
        [(stack.sum(3) * rows).sum(2) / total, (stack.sum(2) * cols).sum(2) / total], dim=-1
    )


def reference_parallax_px_per_um(system):
    """Float64 reference, independent of fgat: centroid shift of the lenslet at +pitch (column)
    per um of depth = f_ML / k times the aperture-averaged column gradient of the high-NA
    defocus phase 2 pi n z / lambda sqrt(1 - (NA rho / n)^2)."""
    n, na, lam = system.immersion_index, system.na, system.wavelength_um
    pupil_radius = system.design["pupil_diameter_mm"] * 500.0  # um
    pitch, half = system.mla_pitch_mm * 1000.0, system.lenslet_aperture_mm * 500.0
    x, y = np.meshgrid(np.linspace(pitch - half, pitch + half, 801), np.linspace(-half, half, 801))
    inside = ((x - pitch) ** 2 + y**2 <= half**2) & (np.hypot(x, y) <= pupil_radius)
    r = np.hypot(x, y)
    s = na * r / (n * pupil_radius)
    # d/dx of 2 pi n / lambda sqrt(1 - s^2), per um of depth.
    dphase_dx = 2 * np.pi * n / lam * (-s / np.sqrt(1 - s**2)) * (na / (n * pupil_radius)) * (x / r)
    shift_um = system.f_mla_mm * 1000.0 * lam / (2 * np.pi) * dphase_dx[inside].mean()
    return shift_um / system.pixel_um


@pytest.fixture(scope="module")
def system_20x():
    return load_system("20x/0.45")


@pytest.mark.slow
def test_parallax_of_outer_view_is_linear_and_central_view_fixed(system_20x):
    depths = np.linspace(-30, 30, 5)
    with torch.no_grad():
        stack = JPGM(system_20x, depths, dtype=torch.float64)()
    c = centroids(stack)
    slope = np.polyfit(depths, c[1, :, 1].numpy(), 1)
    residual = c[1, :, 1].numpy() - np.polyval(slope, depths)
    reference = reference_parallax_px_per_um(system_20x)
    assert abs(reference) == pytest.approx(0.284, abs=0.005)  # "about 0.28 px per um" (DESIGN)
    assert slope[0] == pytest.approx(reference, rel=0.01)
    assert np.abs(residual).max() < 0.02  # linear in depth
    assert c[1, :, 0].abs().max() < 0.02  # no vertical drift for the lenslet on the row axis
    assert c[0].abs().max() < 1e-6  # the central view does not move


@pytest.mark.parametrize(
    "name,depths,radius,aberration,shift",
    [
        ("20x/0.45", [-30.0, 0.0, 25.0], 40, 0.1, 1.0),
        ("60x/1.25", [-3.0, 0.0, 3.0], 24, 0.05, 0.5),
    ],
)
@pytest.mark.slow
def test_fast_path_matches_angular_spectrum(name, depths, radius, aberration, shift):
    model = JPGM(load_system(name), depths, crop_radius_px=radius)
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.zernike_coefficients.copy_(aberration * (2 * torch.rand(17, generator=generator) - 1))
        model.intercepts.copy_(shift * (2 * torch.rand(7, 2, generator=generator) - 1))
        model.slopes.copy_(2 * shift * (2 * torch.rand(7, 2, generator=generator) - 1))
    assert_paths_agree(model)


def test_small_system_uses_the_reference_path():
    model = JPGM(load_system("small"), [-20.0, 0.0, 20.0])
    assert model.crosstalk_bound() > 1e-4
    assert model.resolved_method() == "asm"


@pytest.mark.slow
def test_normalisation_and_symmetry():
    model = JPGM(load_system("small"), [-20.0, 0.0, 20.0], dtype=torch.float64)
    with torch.no_grad():
        stack = model()
    captured = stack.sum(dim=(0, 2, 3))
    assert ((captured > 0.98) & (captured <= 1.0)).all()  # per-depth unit energy on the camera
    central = stack[0]
    torch.testing.assert_close(central, central.flip(-1), rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(central, central.flip(-2), rtol=1e-8, atol=1e-12)
    assert (
        central[1].max() > central[0].max() and central[1].max() > central[2].max()
    )  # in focus at 0


def test_coma_breaks_the_symmetry():
    model = JPGM(load_system("small"), [0.0], zernike_indices=(8,), dtype=torch.float64)
    with torch.no_grad():
        model.zernike_coefficients.fill_(0.2)
        central = model()[0, 0]
    assert relative_l2(central.flip(-1), central) > 0.05


@pytest.mark.slow
def test_intercepts_and_slopes_shift_the_crops():
    model = JPGM(load_system("small"), [-10.0, 0.0, 10.0], method="mft", dtype=torch.float64)
    with torch.no_grad():
        base = model()
        model.intercepts[1] = torch.tensor([2.0, -3.0], dtype=torch.float64)
        model.slopes[1] = torch.tensor([0.0, 1.0], dtype=torch.float64)
        moved = model()
    # column shift at depth k is -3 + xi_k: -4, -3, -2 pixels; row shift +2
    for k, dx in enumerate((-4, -3, -2)):
        torch.testing.assert_close(moved[1, k, 2:-5, 5:-5], base[1, k, 4:-3, 5 + dx : -5 + dx])
    torch.testing.assert_close(moved[0], base[0])


@pytest.mark.parametrize("method", ["mft", "asm"])
def test_gradients_reach_all_jpgm_parameters(method):
    system = load_system("small")
    model = JPGM(
        system,
        [-8.0, 8.0],
        centers_px=system.lenslet_centers_px()[:2],
        zernike_indices=(5, 8),
        crop_radius_px=3,
        method=method,
        dtype=torch.float64,
    )
    with torch.no_grad():
        model.intercepts.copy_(torch.tensor([[0.3, -0.2], [0.1, 0.4]], dtype=torch.float64))

    def psf(c, b, s):
        return torch.func.functional_call(
            model, {"zernike_coefficients": c, "intercepts": b, "slopes": s}, ()
        )

    inputs = (
        torch.tensor([0.05, -0.03], dtype=torch.float64, requires_grad=True),
        model.intercepts.detach().clone().requires_grad_(True),
        torch.tensor([[0.2, 0.1], [-0.3, 0.2]], dtype=torch.float64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(psf, inputs, fast_mode=True, atol=1e-7, rtol=1e-4)


def test_normalized_depth_and_helpers():
    torch.testing.assert_close(
        normalized_depth(5, dtype=torch.float64),
        torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=torch.float64),
    )
    assert normalized_depth(1).item() == 0.0
    assert [fast_fft_size(n) for n in (1, 7, 11, 461, 2049)] == [1, 8, 12, 480, 2160]


def test_bilinear_crop_interpolates():
    image = torch.arange(100, dtype=torch.float64).reshape(1, 10, 10)
    crop = bilinear_crops(
        image, torch.tensor([[0, 0]]), torch.tensor([[4.25, 5.5]], dtype=torch.float64), 1
    )
    expected = image[0, 3:6, 4:7] + 0.25 * 10 + 0.5
    torch.testing.assert_close(crop[0], expected)


@pytest.mark.parametrize("center", [(1.0, 5.0), (5.0, 0.5), (8.5, 5.0), (5.0, 8.0)])
def test_bilinear_crop_refuses_to_leave_the_window_with_one_host_read(center):
    """A crop (with its interpolation's extra row and column) inside the window reads one
    value back to the host; one reaching past any edge is refused."""
    image = torch.rand(2, 10, 10, dtype=torch.float64)
    origins = torch.zeros(2, 2, dtype=torch.long)
    with DispatchCount() as count:
        bilinear_crops(image, origins, torch.tensor([[4.5, 4.5], [5.0, 5.0]]), 2)
    assert count.host_reads == 1
    with pytest.raises(ValueError, match="outside the computed intensity window"):
        bilinear_crops(image, origins, torch.tensor([[4.5, 4.5], center]), 2)


def test_angular_spectrum_conserves_energy():
    field = torch.randn(64, 64, dtype=torch.complex128) * (torch.rand(64, 64) > 0.5)
    transfer = angular_spectrum_transfer(
        (64, 64), pixel_um=6.5, wavelength_um=0.51, distance_um=5e3, dtype=torch.complex128
    )
    out = angular_spectrum_propagate(field, transfer)
    assert float(out.abs().square().sum()) == pytest.approx(
        float(field.abs().square().sum()), rel=1e-12
    )


@pytest.mark.slow
def test_sampling_and_geometry_errors():
    system = load_system("small")
    # f_ML = 4 mm needs 0.80 cycles per pixel: oversampled twice now; 0.5 mm needs 6.4 > 4.
    assert JPGM(system.replace(f_mla_mm=4.0), [0.0]).oversampling == 2
    with pytest.raises(ValueError, match="Nyquist limit 4 of oversampling 8"):
        JPGM(system.replace(f_mla_mm=0.5), [0.0])
    model = JPGM(system, [0.0])
    with torch.no_grad():
        model.zernike_coefficients.fill_(3.0)
    with pytest.raises(ValueError, match="Zernike coefficients.*Nyquist"):
        model()
    model = JPGM(system, [0.0])
    with torch.no_grad():
        model.intercepts[4, 1] = -60.0
    with pytest.raises(ValueError, match=r"view 4 .* centred at \[128.0, -8.92\], outside the 256"):
        model()
    with pytest.raises(ValueError, match="641-pixel crops, wider than the 256 x 256 sensor"):
        JPGM(system, [0.0], crop_radius_px=320)()
    with pytest.raises(ValueError, match="method"):
        JPGM(system, [0.0], method="fresnel")
    with pytest.raises(ValueError, match="depths_um"):
        JPGM(system, [math.nan])


@pytest.mark.parametrize("method", ["mft", "asm"])
def test_crops_may_reach_past_the_sensor_edge(method):
    """A crop is a model window: crops of the small system's outer views that reach 9 px past
    the 256 x 256 sensor's edge (and a fitted shift towards it) equal those of the same optics
    on a 320 x 320 sensor, where they lie inside, with every centre moved with the axis."""
    system = load_system("small")
    larger = system.replace(sensor_shape=(320, 320))
    depths, shift = [-10.0, 0.0, 10.0], torch.tensor([[2.0, -3.5]])
    stacks = []
    for optics in (system, larger):
        model = JPGM(optics, depths, crop_radius_px=60, method=method, dtype=torch.float64)
        with torch.no_grad():
            model.intercepts[4] = shift
            assert float(model.crop_centers()[..., 1].min() - 60) < 0 or optics is larger
            stacks.append(model())
    assert torch.allclose(stacks[0], stacks[1], rtol=0, atol=1e-12 * float(stacks[1].max()))


def test_aperture_field_gradient():
    from fgat.optics.psf import aperture_field

    amplitude = (torch.rand(4, 5, dtype=torch.float64) > 0.3).double()
    phase = torch.randn(4, 5, dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(aperture_field(amplitude, phase), torch.polar(amplitude, phase))
    assert torch.autograd.gradcheck(lambda p: aperture_field(amplitude, p), (phase,))


def test_defocused_field_equals_its_expression_in_value_gradient_and_forward_mode():
    """The MFT path's lenslet fields: the custom function against autograd through the plain
    expression ``A exp(i (Phi + z D - q (a0 + z a1 + z^2 a2)^2))``, in reverse mode (gradcheck,
    and equal gradients), forward mode and under vmap (the cross-information's Jacobians)."""
    from fgat.optics.psf import _DefocusedField

    g = torch.Generator().manual_seed(5)
    maps = [torch.randn(2, 1, 3, 4, generator=g, dtype=torch.float64) for _ in range(5)]
    amplitude = (torch.rand(2, 1, 3, 4, generator=g, dtype=torch.float64) > 0.3).double()
    depths = torch.tensor([-2.0, -0.5, 0.0, 1.5], dtype=torch.float64)
    quartic = 0.3

    def plain(zernike, defocus, a0, a1, a2):
        z = depths[:, None, None]
        frequency = a0 + z * a1 + z**2 * a2
        phase = zernike + z * defocus - quartic * frequency**2
        return torch.polar(amplitude.expand_as(phase), phase)

    def fused(*m):
        return _DefocusedField.apply(amplitude, *m, depths, quartic)

    inputs = [m.clone().requires_grad_(True) for m in maps]
    torch.testing.assert_close(fused(*inputs), plain(*inputs), rtol=1e-13, atol=1e-14)
    assert torch.autograd.gradcheck(fused, inputs, check_forward_ad=True)
    weights = torch.randn(2, 4, 3, 4, generator=g, dtype=torch.complex128)
    ours = torch.autograd.grad((fused(*inputs) * weights).real.sum(), inputs)
    reference = torch.autograd.grad((plain(*inputs) * weights).real.sum(), inputs)
    for a, b in zip(ours, reference):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-13)
    tangents = [torch.randn(3, *m.shape, generator=g, dtype=torch.float64) for m in maps]

    def directional(jvp_of):
        return torch.func.vmap(lambda *t: torch.func.jvp(jvp_of, tuple(maps), t)[1])(*tangents)

    torch.testing.assert_close(directional(fused), directional(plain), rtol=1e-12, atol=1e-13)


# ---------------------------------------------------------------- sample medium
HIGH_NA = dict(name="small 60x/1.3", magnification=60, na=1.3, immersion_index=1.406)


@pytest.mark.slow
def test_sample_index_none_is_the_immersion_medium():
    """``sample_index=None`` and ``sample_index=immersion_index`` give the same stack bit for bit,
    and its defocus is the immersion-medium phase 2 pi n / lambda (sqrt(1 - (NA rho / n)^2) - 1)
    of the model before sample media existed."""
    system = load_system("small")
    stacks = []
    for sample_index in (None, system.immersion_index):
        model = JPGM(
            system.replace(sample_index=sample_index), [-20.0, 0.0, 20.0], dtype=torch.float64
        )
        with torch.no_grad():
            model.zernike_coefficients[3] = 0.1
            stacks.append(model())
    assert torch.equal(stacks[0], stacks[1])
    n, na = system.immersion_index, system.na
    rho = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    q = (na * rho / n) ** 2
    legacy = -2.0 * math.pi * n / system.wavelength_um * (q / (1.0 + torch.sqrt(1.0 - q)))
    torch.testing.assert_close(
        defocus_phase_per_um(rho, wavelength_um=system.wavelength_um, na=na, immersion_index=n),
        legacy,
        rtol=0,
        atol=0,
    )


def test_sample_index_sets_the_defocus_and_darkens_supercritical_angles():
    """Water under oil at NA 1.45: the pupil is dark exactly where NA rho >= 1.33, and the
    defocus per um is the sample-medium phase there is light."""
    system = load_system("small").replace(
        name="tirf", magnification=100, na=1.45, immersion_index=1.518, sample_index=1.33
    )
    model = JPGM(system, [-1.0, 0.0, 1.0], dtype=torch.float64)
    assert model.oversampling == 2  # the phase steepens towards the critical angle
    rows = model.box_rows[:, :, None].expand(-1, -1, model.box_cols.shape[1])
    cols = model.box_cols[:, None, :].expand(-1, model.box_rows.shape[1], -1)
    center = tuple(float(c) for c in model.centers[0])
    rho = torch.sqrt((rows - center[0]) ** 2 + (cols - center[1]) ** 2) / system.pupil_radius_px
    lit = model.amplitude > 0
    assert lit.any() and (system.na * rho[lit] < 1.33).all()
    dark_supercritical = (rho <= 1) & (system.na * rho >= 1.33)
    assert dark_supercritical.any() and not lit[dark_supercritical].any()
    expected = (
        -2.0 * math.pi / system.wavelength_um * (1.33 - torch.sqrt(1.33**2 - (1.45 * rho) ** 2))
    )
    torch.testing.assert_close(model.defocus_per_um[lit], expected[lit], rtol=1e-9, atol=1e-9)
    with torch.no_grad():
        captured = model().sum(dim=(0, 2, 3))
    # The emission apodization weights the steep near-critical rim (1 / cos(theta_s)), whose
    # parallax carries some light past the crops one um from focus: 0.91 of it stays.
    assert ((captured > 0.9) & (captured <= 1.0)).all()


# ---------------------------------------------------------------- pupil-plane oversampling
@pytest.mark.parametrize("oversampling", [1, 2, 3])
def test_mft_matches_asm_when_oversampled(oversampling):
    """One lenslet (no crosstalk), aberrated and shifted: the two paths agree at every s."""
    system = load_system("small")
    model = JPGM(
        system,
        [-20.0, 0.0, 20.0],
        centers_px=system.lenslet_centers_px()[:1],
        oversampling=oversampling,
        dtype=torch.float64,
    )
    with torch.no_grad():
        model.zernike_coefficients.copy_(0.1 * torch.arange(17, dtype=torch.float64).sin())
        model.intercepts.fill_(0.4)
        model.slopes.fill_(-0.7)
    assert_paths_agree(model)


def table_model(aberration: float = 0.3, dtype=torch.float64, **options):
    """Two 20x/0.45 lenslets, three depths, 40 px crops, aberrated (Zernike terms drawn from
    +-``aberration`` waves) and shifted."""
    system = load_system("20x/0.45")
    model = JPGM(
        system,
        [-30.0, 0.0, 25.0],
        centers_px=system.lenslet_centers_px()[:2],
        crop_radius_px=40,
        dtype=dtype,
        **options,
    )
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.zernike_coefficients.copy_(aberration * (2 * torch.rand(17, generator=generator) - 1))
        model.intercepts.copy_(2 * torch.rand(2, 2, generator=generator) - 1)
        model.slopes.copy_(2 * (2 * torch.rand(2, 2, generator=generator) - 1))
    return model


@pytest.mark.slow
def test_mft_matches_asm_oversampled_on_a_table_system():
    assert_paths_agree(table_model(0.1, torch.float32, oversampling=2))


def test_oversampling_converges_and_scales_memory():
    """A system that s = 1 samples well changes little at s = 2 and 3 (the aperture edges are
    pixelised differently); the memory estimate grows with s^2 and covers the geometry."""
    system = load_system("small")
    stacks, memory, boxes = {}, {}, {}
    for s in (1, 2, 3):
        model = JPGM(system, [-20.0, 20.0], oversampling=s)
        with torch.no_grad():
            stacks[s] = model()
        memory[s] = model.memory_bytes()
        boxes[s] = model.basis.shape[-1]
        geometry = sum(b.numel() * b.element_size() for b in model.buffers())
        assert memory[s] > geometry
        torch.testing.assert_close(
            model.box_rows[:, 1] - model.box_rows[:, 0], 1.0 / s + 0 * model.box_rows[:, 0]
        )
    assert boxes[2] - 1 == 2 * (boxes[1] - 1) and boxes[3] - 1 == 3 * (boxes[1] - 1)
    assert relative_l2(stacks[2], stacks[1]) < 1e-2
    assert relative_l2(stacks[3], stacks[2]) < 1e-2
    assert 3.0 < memory[2] / memory[1] < 5.0 and 2.0 < memory[3] / memory[2] < 3.0


def test_high_na_depth_range_is_oversampled_not_refused():
    """NA 1.3 at 60x (the small module) over +-12 um: 0.65 cycles per pixel at s = 1, which used
    to raise; now s = 2 is chosen, an explicit s = 1 is refused, and the energies are sane."""
    depths = [-12.0, 0.0, 12.0]
    for sample_index in (None, 1.33):
        system = load_system("small").replace(**HIGH_NA, sample_index=sample_index)
        model = JPGM(system, depths, dtype=torch.float64)
        assert model.oversampling == 2
        assert NYQUIST < model.geometric_frequency <= 0.8 * model.nyquist
        with torch.no_grad():
            stack = model()
        captured = stack.sum(dim=(0, 2, 3))
        assert torch.isfinite(stack).all() and (stack >= 0).all()
        assert captured[1] > 0.98  # in focus: nearly all light in the crops
        # Defocused: parallax carries light past the crop edges, never more than all of it.
        assert ((captured > 0.6) & (captured <= 1.0)).all()
    with torch.no_grad():
        finer = JPGM(system, depths, oversampling=3, dtype=torch.float64)()
    torch.testing.assert_close(captured, finer.sum(dim=(0, 2, 3)), rtol=0.01, atol=0)
    assert relative_l2(stack, finer) < 0.01
    with pytest.raises(ValueError, match="oversampling 1; use oversampling >= 2 or None"):
        JPGM(system, depths, oversampling=1)


def test_zernike_growth_refines_the_sampling_with_a_warning():
    system = load_system("small")
    model = JPGM(system, [-20.0, 0.0, 20.0], dtype=torch.float64)
    assert model.oversampling == 1
    coefficients = torch.zeros(17, dtype=torch.float64)
    coefficients[model.zernike_indices.index(11)] = 3.0  # 0.32 cycles per pixel of spherical
    with torch.no_grad():
        model.zernike_coefficients.copy_(coefficients)
        with pytest.warns(RuntimeWarning, match="refined the pupil grid to oversampling 2"):
            refined = model()
    assert model.oversampling == 2
    direct = JPGM(system, [-20.0, 0.0, 20.0], oversampling=2, dtype=torch.float64)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("error")
        direct.zernike_coefficients.copy_(coefficients)
        assert torch.equal(refined, direct())
        chosen = JPGM.with_parameters(system, [-20.0, 0.0, 20.0], zernike={11: 3.0})
    assert chosen.oversampling == 2
    captured = refined.sum(dim=(0, 2, 3))
    assert ((captured > 0.9) & (captured <= 1.0)).all()


def test_oversampling_argument_is_checked():
    system = load_system("small")
    for bad in (0, 9, 1.5, True, "2"):
        with pytest.raises(ValueError, match="oversampling must be None, an integer"):
            JPGM(system, [0.0], oversampling=bad)


# ---------------------------------------------------------------- hexagonal lenslets
def ray_mean(image, angle, radii):
    """Mean of ``image`` (bilinear) along a ray from its centre at ``angle`` (theta sense)."""
    c = image.shape[-1] // 2
    y, x = c + radii * math.sin(angle), c + radii * math.cos(angle)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - y0, x - x0
    values = (
        image[y0, x0] * (1 - fy) * (1 - fx)
        + image[y0, x0 + 1] * (1 - fy) * fx
        + image[y0 + 1, x0] * fy * (1 - fx)
        + image[y0 + 1, x0 + 1] * fy * fx
    )
    return float(values.mean())


@pytest.mark.parametrize("rotation", [0.0, 0.2])
def test_hexagonal_lenslets_diffract_six_streaks(rotation):
    """In focus, the central view of hexagonal lenslets is brighter along the six flat normals
    (which turn with the calibrated array) than 30 degrees away; a circle's is isotropic."""
    system = load_system("small")
    turn = np.array(
        [[math.cos(rotation), -math.sin(rotation)], [math.sin(rotation), math.cos(rotation)]]
    )
    nominal = system.lenslet_centers_px()
    centers = (nominal - nominal[0]) @ turn.T + nominal[0]
    radii = np.linspace(6.0, 30.0, 97)
    ratio = {}
    for shape in ("circle", "hexagon"):
        model = JPGM(
            system.replace(lenslet_shape=shape), [0.0], centers_px=centers, dtype=torch.float64
        )
        assert model._lattice_angle == pytest.approx(-rotation, abs=1e-12)
        with torch.no_grad():
            image = model()[0, 0].numpy()
        normals = [-rotation + k * math.pi / 3 for k in range(6)]
        along = np.mean([ray_mean(image, a, radii) for a in normals])
        between = np.mean([ray_mean(image, a + math.pi / 6, radii) for a in normals])
        ratio[shape] = along / between
    assert ratio["hexagon"] > 10.0
    assert 0.8 < ratio["circle"] < 1.3


@pytest.mark.slow
def test_hexagon_crosstalk_bound_holds_where_the_disk_envelope_fails():
    """The far field of a hexagon (the mask JPGM uses, Fourier transformed numerically) along a
    flat normal falls as 1 / v: below the bound 8 / (3 sqrt(3) v) of ``crosstalk_bound``, above
    the disk envelope 2 sqrt(2 / pi) v^-1.5 at the circumradius; so the 20x system with
    hexagonal lenslets computes its crosstalk with the angular spectrum."""
    from fgat.optics.pupil import lenslet_aperture

    step = 1.0 / 1000  # circumradius 1
    u = torch.arange(-1.0, 1.0 + step / 2, step, dtype=torch.float64)
    dy, dx = torch.meshgrid(u, u, indexing="ij")
    inside = lenslet_aperture(dy, dx, shape="hexagon", radius=math.sqrt(3.0) / 2.0)
    chord = inside.sum(dim=0).double().numpy()  # mask height per column: F along +x is 1D
    v = np.linspace(20.0, 200.0, 181)  # |k| R with R = 1, along the flat normal (+x)
    far = np.abs(np.exp(-1j * np.outer(v, u.numpy())) @ chord) / chord.sum()
    assert (far <= 8.0 / (3.0 * math.sqrt(3.0) * v)).all()
    assert (far > 2.0 * math.sqrt(2.0 / math.pi) * v**-1.5)[v > 100].mean() > 0.3
    hexagon = JPGM(load_system("20x/0.45").replace(lenslet_shape="hexagon"), [0.0])
    assert hexagon.crosstalk_bound() > CROSSTALK_TOLERANCE
    assert hexagon.resolved_method() == "asm"


@pytest.mark.parametrize("disk", ["pupil", "aperture"])
def test_zernike_unit_disk_follows_the_system(disk):
    """The basis on the lit samples is Noll's Z_j over the chosen disk (Eq. S4): independent
    float64 spherical (j = 11) and coma (j = 8) at the analytic radius of each disk."""
    system = load_system("small").replace(zernike_disk=disk)
    model = JPGM(
        system, depths_um=torch.tensor([0.0]), zernike_indices=(8, 11), dtype=torch.float64
    )
    center = model.centers[0]
    lens_radius = system.lenslet_aperture_mm * 500.0 / system.pixel_um
    radius = system.pupil_radius_px if disk == "pupil" else system.pitch_px + lens_radius
    dy = model.box_rows[:, :, None] - center[0]
    dx = model.box_cols[:, None, :] - center[1]
    rho, theta = torch.hypot(dy, dx) / radius, torch.atan2(dy, dx)
    lit = model.amplitude > 0
    spherical = math.sqrt(5) * (6 * rho**4 - 6 * rho**2 + 1)
    coma = math.sqrt(8) * (3 * rho**3 - 2 * rho) * torch.cos(theta)
    torch.testing.assert_close(model.basis[:, 1][lit], spherical[lit], atol=1e-9, rtol=0)
    torch.testing.assert_close(model.basis[:, 0][lit], coma[lit], atol=1e-9, rtol=0)
    reach = float(rho[lit].max())
    expected = (system.pitch_px + lens_radius) / system.pupil_radius_px
    assert reach == pytest.approx(1.0 if disk == "aperture" else expected, abs=0.02)


@pytest.mark.slow
def test_mft_takes_an_area_weighted_grid_coarser_than_the_camera():
    """The MFT's own phase (kernel over the windows, defocus, Zernike) allows s = 1/4 here: the
    grid's aperture weights add up to the disk's area, and the stack matches the camera-pitch
    and the twice finer point-sampled grids to well within their distance (3.3e-4) from the ASM."""
    system = load_system("20x/0.45")
    model = table_model()
    assert model.resolved_method() == "mft" and model.oversampling == 1 / MFT_SUBSAMPLING
    pitch = 1 / model.oversampling
    torch.testing.assert_close(
        model.box_rows[:, 1] - model.box_rows[:, 0], torch.full((2,), pitch, dtype=torch.float64)
    )
    radius = system.lenslet_aperture_mm * 500.0 / system.pixel_um
    area = float(model.coverage[0].sum()) * pitch**2  # view 0 lies inside the pupil
    assert area == pytest.approx(math.pi * radius**2, rel=1e-4)
    partial = model.coverage[(model.coverage > 0) & (model.coverage < 1)]
    assert partial.numel() > 0 and (partial >= 1 / AREA_SUBSAMPLES**2).all()
    with torch.no_grad():
        coarse = model()
        camera_pitch = table_model(oversampling=1)()
        finer = table_model(oversampling=2, method="mft")()
    assert relative_l2(coarse, finer) < 2e-4  # measured 1.3e-4; 8e-5 at the camera pitch
    assert relative_l2(camera_pitch, finer) < 1e-4
    assert_paths_agree(model)


@pytest.mark.slow
def test_a_coarse_grid_is_refined_step_by_step_and_the_asm_never_takes_it():
    model = table_model()
    with torch.no_grad():
        model.zernike_coefficients.mul_(25.0)  # 0.16 cycles per pixel
        with pytest.warns(RuntimeWarning, match="refined the pupil grid to oversampling 0.5"):
            refined = model()
        direct = table_model(oversampling=0.5)
        direct.zernike_coefficients.mul_(25.0)
        assert torch.equal(refined, direct())
    assert table_model(oversampling=1 / 3).oversampling == 1 / 3
    for bad in (0.4, 0.2, float("nan")):
        with pytest.raises(ValueError, match="1/k with k from 2 to 4"):
            table_model(oversampling=bad)
    with pytest.raises(ValueError, match="1/k with k from 2 to 4"):
        table_model(oversampling=0.5, method="asm")
    with pytest.raises(ValueError, match="oversampling 0.5 is for the 'mft' path"):
        JPGM(load_system("small"), [0.0], oversampling=0.5)


@pytest.mark.parametrize("shape", ["circle", "hexagon"])
def test_area_weights_equal_subsampling_every_cell(shape):
    """Only cells near an edge are subsampled; the weights equal the brute-force average of
    every cell's AREA_SUBSAMPLES^2 points, for the central and two outer 20x/0.45 lenslets, as
    disks and as tilted hexagons."""
    system = load_system("20x/0.45").replace(lenslet_shape=shape)
    nominal = system.lenslet_centers_px()
    turn = np.array([[math.cos(0.2), -math.sin(0.2)], [math.sin(0.2), math.cos(0.2)]])
    centers = (nominal - nominal[0]) @ turn.T + nominal[0]
    model = JPGM(system, [0.0], centers_px=centers[[0, 1, 4]], method="mft", oversampling=1 / 3)
    pitch, views = 3.0, torch.arange(3)[:, None, None]
    radius = system.lenslet_aperture_mm * 500.0 / system.pixel_um
    axes = torch.as_tensor(centers[[0, 1, 4]], dtype=torch.float64)
    rows = model.box_rows.double()[:, :, None].expand(-1, -1, model.box_cols.shape[1])
    cols = model.box_cols.double()[:, None, :].expand(-1, model.box_rows.shape[1], -1)
    total = torch.zeros_like(rows)
    offsets = ((torch.arange(AREA_SUBSAMPLES) + 0.5) / AREA_SUBSAMPLES - 0.5) * pitch
    for dy in offsets.tolist():
        for dx in offsets.tolist():
            rho, _ = pupil_coordinates(
                rows + dy, cols + dx, tuple(centers[0]), system.pupil_radius_px
            )
            inside = lenslet_aperture(
                rows + dy - axes[views, 0],
                cols + dx - axes[views, 1],
                shape=shape,
                radius=radius,
                angle=lattice_angle(axes),
            )
            total += (inside & (rho <= 1.0)).double()
    expected = total / AREA_SUBSAMPLES**2
    assert ((expected > 0) & (expected < 1)).sum() > 1000
    torch.testing.assert_close(model.coverage.double(), expected, rtol=0, atol=1e-7)
