import math

import numpy as np
import pytest
import torch

from fgat.optics.propagation import angular_spectrum_propagate, angular_spectrum_transfer
from fgat.optics.psf import JPGM, bilinear_crops, fast_fft_size, normalized_depth
from fgat.optics.systems import load_system


def relative_l2(a, b):
    return float((a - b).norm() / b.norm())


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
def test_fast_path_matches_angular_spectrum(name, depths, radius, aberration, shift):
    model = JPGM(load_system(name), depths, crop_radius_px=radius)
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.zernike_coefficients.copy_(aberration * (2 * torch.rand(17, generator=generator) - 1))
        model.intercepts.copy_(shift * (2 * torch.rand(7, 2, generator=generator) - 1))
        model.slopes.copy_(2 * shift * (2 * torch.rand(7, 2, generator=generator) - 1))
        assert model.resolved_method() == "mft"
        model.method = "mft"
        fast = model()
        model.method = "asm"
        reference = model()
    assert relative_l2(fast, reference) < 1e-3


def test_small_system_uses_the_reference_path():
    model = JPGM(load_system("small"), [-20.0, 0.0, 20.0])
    assert model.crosstalk_bound() > 1e-4
    assert model.resolved_method() == "asm"


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


def test_angular_spectrum_conserves_energy():
    field = torch.randn(64, 64, dtype=torch.complex128) * (torch.rand(64, 64) > 0.5)
    transfer = angular_spectrum_transfer(
        (64, 64), pixel_um=6.5, wavelength_um=0.51, distance_um=5e3, dtype=torch.complex128
    )
    out = angular_spectrum_propagate(field, transfer)
    assert float(out.abs().square().sum()) == pytest.approx(
        float(field.abs().square().sum()), rel=1e-12
    )


def test_sampling_and_geometry_errors():
    system = load_system("small")
    with pytest.raises(ValueError, match="Nyquist"):
        JPGM(system.replace(f_mla_mm=4.0), [0.0])
    model = JPGM(system, [0.0])
    with torch.no_grad():
        model.zernike_coefficients.fill_(3.0)
    with pytest.raises(ValueError, match="Zernike coefficients.*Nyquist"):
        model()
    model = JPGM(system, [0.0])
    with torch.no_grad():
        model.intercepts[4, 1] = -60.0
    with pytest.raises(ValueError, match="view 4 .* leaves the 256 x 256 sensor"):
        model()
    with pytest.raises(ValueError, match="method"):
        JPGM(system, [0.0], method="fresnel")
    with pytest.raises(ValueError, match="depths_um"):
        JPGM(system, [math.nan])


def test_aperture_field_gradient():
    from fgat.optics.psf import aperture_field

    amplitude = (torch.rand(4, 5, dtype=torch.float64) > 0.3).double()
    phase = torch.randn(4, 5, dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(aperture_field(amplitude, phase), torch.polar(amplitude, phase))
    assert torch.autograd.gradcheck(lambda p: aperture_field(amplitude, p), (phase,))
