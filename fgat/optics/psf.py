"""JPGM: the learnable, differentiable FLFM PSF-stack generator (Supplementary Note S2).

For each depth ``z`` the pupil-plane field of an on-axis point (high-NA defocus phase) is
multiplied by the complex pupil ``P = M exp(i phi_Z)`` (Eqs. S4-S6) and by the hexagonal MLA
(lenslet apertures and thin-lens phases of focal ``f_ML``) (Eq. S7), propagated over ``f_ML``
to the camera (Eq. S8), turned into intensity and normalised per depth (Eq. S9). Each view's
PSF is a bilinear crop of half-width ``r`` around ``c_v + b_v + s_v xi(z)`` (Eqs. S10-S12).

Two numerical paths compute the camera intensity:

``"asm"``
    The angular-spectrum method of Eq. S8 on a grid that holds the whole MLA: two FFTs of that
    grid per depth. The reference.
``"mft"``
    Only the crop windows, lenslet by lenslet. Propagating a field that leaves a thin lens of
    focal ``f`` over the distance ``f`` is a Fourier transform of what the lens multiplies; it is
    evaluated by a matrix Fourier transform (two small matrix products) from the lenslet's
    aperture to the window of its view, with the angular-spectrum phase beyond the paraxial term
    applied at each aperture point's local spatial frequency (stationary phase). It ignores
    light that a lenslet sends into another lenslet's crop window, so ``"auto"`` uses it only
    where a diffraction bound on that light is below ``CROSSTALK_TOLERANCE`` (the Table S1
    systems, whose lenslets have Fresnel numbers near 80) and the ASM elsewhere (the small
    test system).

Pupil-plane sampling. Both paths sample the MLA plane on a grid of pitch ``pixel / s`` and
evaluate the camera intensity at the camera pixel centres (point samples, as at ``s = 1``). The
phase the grid carries must vary by less than the Nyquist limit ``0.5 s`` cycles per camera
pixel: for the ASM the thin lens's, the defocus and the Zernike phase; for the MFT the defocus
and Zernike phase plus the transform kernel's ``kappa |x - c_v|`` at the window pixel farthest
from the lenslet axis (the lens phase is the kernel itself), a few times less at the Table S1
systems. The ASM takes an integer ``s`` (camera pixels are grid samples); the MFT may also
take ``s = 1/2 ... 1 / MFT_SUBSAMPLING``, where each sample carries the fraction of its cell
that the aperture covers (``AREA_SUBSAMPLES^2`` points per cell) rather than the point sample
of its centre: at 20x/0.45, 101 depths and 1-wave aberrations this ``s = 1/2`` grid's stack is
1.7e-4 (relative L2) from the point-sampled ``s = 2`` one, the point-sampled ``s = 1`` grid's
3.1e-4 (``benchmarks/jpgm_update.py``), with a quarter of its samples. The automatic choice
takes the coarsest allowed ``s`` that keeps the phase frequency below ``SAMPLING_MARGIN`` of its
limit (the remainder is the budget for aberrations and shifts to grow before the next
refinement), or ``s = 1`` whenever that samples the phase at all; a refinement, when the Zernike
coefficients or the shifts outgrow the grid during a fit, takes the next coarsest ``s`` with
that margin, up to ``MAX_OVERSAMPLING``.

Shapes: ``V`` views (lenslets), ``Z`` depths, ``K`` Zernike terms. Positions are camera pixels
``(row, col)``; intercepts ``b_v`` and slopes ``s_v`` are stored ``(row, col)`` = ``(y, x)`` too.
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from fgat._core.devices import functorch_wrapped, triton_installed
from fgat.optics.patches import crop_patches, place_patches
from fgat.optics.propagation import (
    angular_spectrum_propagate,
    angular_spectrum_transfer,
    defocus_phase_per_um,
    emission_apodization,
    propagating_pupil,
    quartic_phase_coefficient,
    thin_lens_phase,
)
from fgat.optics.pupil import (
    aperture_circumradius,
    lattice_angle,
    lenslet_aperture,
    pupil_coordinates,
    pupil_radius,
    zernike_disk_radius,
)
from fgat.optics.systems import FLFMSystem
from fgat.optics.zernike import DEFAULT_INDICES, wavefront_map, zernike_basis

NYQUIST = 0.5  # cycles per sample of the pupil-plane grid (per camera pixel at s = 1)
SAMPLING_MARGIN = 0.8  # a chosen oversampling keeps the phase below this fraction of Nyquist
MAX_OVERSAMPLING = 8  # largest pupil-plane oversampling s
MFT_SUBSAMPLING = 4  # the MFT may sample the pupil plane as coarsely as s = 1 / 4
AREA_SUBSAMPLES = 8  # points per cell side of the aperture coverage on grids with s < 1
DEPTH_MEDIA = ("sample", "immersion")  # what a JPGM depth changes (JPGM's depth_medium)
METHODS = ("auto", "mft", "asm")  # intensity paths of the JPGM (see JPGM.resolved_method)
CROSSTALK_TOLERANCE = 1e-4  # relative field amplitude, see JPGM.crosstalk_bound


def normalized_depth(
    n_depths: int, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """Normalised depth coordinate ``xi(z) = 2 (z - 1) / (N_z - 1) - 1`` in [-1, 1] (Eq. S10).

    A single depth gets ``xi = 0``.
    """
    if n_depths == 1:
        return torch.zeros(1, dtype=dtype, device=device)
    return torch.linspace(-1.0, 1.0, n_depths, dtype=dtype, device=device)


def fast_fft_size(n: int) -> int:
    """Smallest integer ``>= n`` whose prime factors are 2, 3 and 5."""
    size = max(int(n), 1)
    while True:
        m = size
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return size
        size += 1


def check_crops_on_sensor(centers: Tensor, radius: int, sensor_shape: tuple[int, int]) -> None:
    """Refuse PSF crops that cannot belong to a view of the camera.

    A crop (Eq. S12) is a model window: both intensity paths compute the field wherever it is
    placed, so a crop may reach past the sensor's edge (an outer view near the edge, a shift
    estimated during a fit) without harm. What is refused is a crop centred off the sensor (no
    view of the camera lies there) or one wider than the sensor.

    Parameters
    ----------
    centers : Tensor
        ``(V, Z, 2)`` crop centres (row, col), camera pixels.
    radius : int
        Crop half-width ``r``, pixels.
    sensor_shape : tuple of int
        Camera ``(H, W)``, pixels.

    Raises
    ------
    ValueError
        Naming the view, the depth index, the centre and the sensor.
    """
    height, width = sensor_shape
    if 2 * radius + 1 > max(height, width):
        raise ValueError(
            f"crop half-width {radius} makes {2 * radius + 1}-pixel crops, wider than the "
            f"{height} x {width} sensor"
        )
    outside = (
        (centers[..., 0] < 0)
        | (centers[..., 1] < 0)
        | (centers[..., 0] > height - 1)
        | (centers[..., 1] > width - 1)
    )
    if bool(outside.any()):
        view, depth = (int(i) for i in torch.nonzero(outside)[0])
        raise ValueError(
            f"crop of view {view} at depth index {depth} is centred at "
            f"{[round(float(x), 2) for x in centers[view, depth]]}, outside the {height} x "
            f"{width} sensor"
        )


def bilinear_crops(images: Tensor, origins: Tensor, centers: Tensor, radius: int) -> Tensor:
    """Sub-pixel square crops by bilinear interpolation, differentiable in images and centers.

    Parameters
    ----------
    images : Tensor
        ``(N, H, W)`` intensities whose pixel ``(0, 0)`` sits at absolute position ``origins[n]``.
    origins : Tensor
        ``(N, 2)`` integer absolute (row, col) of each image's first pixel.
    centers : Tensor
        ``(N, 2)`` absolute (row, col) crop centres (sub-pixel).
    radius : int
        Half-width ``r``: crops are ``(2r + 1, 2r + 1)``, sample ``(i, j)`` at
        ``center + (i - r, j - r)``.

    Returns
    -------
    Tensor
        ``(N, 2r + 1, 2r + 1)``.
    """
    base = torch.floor(centers.detach())
    frac = centers - base
    start = base.long() - radius - origins.long()
    steps = torch.arange(2 * radius + 2, device=images.device)
    rows = (start[:, 0, None] + steps)[:, :, None]
    cols = (start[:, 1, None] + steps)[:, None, :]
    low, high = start.amin(0), start.amax(0) + 2 * radius + 1  # (row, col) reach of all crops
    outside = (low < 0).any() | (high[0] >= images.shape[-2]) | (high[1] >= images.shape[-1])
    if bool(outside):  # one read back to the host (on a GPU, one wait for the queue)
        raise ValueError("bilinear crop reaches outside the computed intensity window")
    # A gather over flat indices: its backward is a scatter-add, not the sorting index_put_
    # that advanced indexing's backward is (a quarter of a JPGM update on a GPU).
    width = images.shape[-1]
    flat = (rows * width + cols).reshape(images.shape[0], -1)
    patch = images.reshape(images.shape[0], -1).gather(1, flat).reshape(-1, *steps.shape * 2)
    fy = frac[:, 0, None, None]
    fx = frac[:, 1, None, None]
    top = patch[:, :-1, :-1] * (1 - fx) + patch[:, :-1, 1:] * fx
    bottom = patch[:, 1:, :-1] * (1 - fx) + patch[:, 1:, 1:] * fx
    return top * (1 - fy) + bottom * fy


def check_optics(
    zernike: dict | None = None, intercepts: dict | None = None, slopes: dict | None = None
) -> tuple[dict[int, float], dict[int, tuple], dict[int, tuple]]:
    """Zernike coefficients ``{j: waves}`` and lenslet shifts ``{view: (row, col)}`` (pixels) as
    numbers, or one ``ValueError`` naming the entry and the value: a Noll index that is not an
    integer >= 1, a view that is not an integer >= 0, a shift that is not two numbers, a
    coefficient or shift that is not finite (NaN, Inf)."""

    def integer(name: str, key, minimum: int, what: str) -> int:
        whole = isinstance(key, (int, np.integer)) and not isinstance(key, bool)
        digits = isinstance(key, str) and key.strip().isdigit()
        if not (whole or digits) or int(key) < minimum:
            raise ValueError(f"{name}: keys must be {what} (integers >= {minimum}), got {key!r}")
        return int(key)

    def finite(name: str, value, unit: str) -> float:
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if isinstance(value, bool) or not math.isfinite(number):
            raise ValueError(f"{name} must be a finite number ({unit}), got {value!r}")
        return number

    for name, table in (("zernike", zernike), ("intercepts", intercepts), ("slopes", slopes)):
        if table is not None and not isinstance(table, Mapping):
            entries = "Noll index: waves" if name == "zernike" else "view: [row, col]"
            raise ValueError(f"{name} must be a mapping ({entries}), got {table!r}")
    coefficients = {
        integer("zernike", j, 1, "Noll indices"): finite(f"zernike[{j}]", c, "waves")
        for j, c in (zernike or {}).items()
    }
    shifts = []
    for name, table in (("intercepts", intercepts or {}), ("slopes", slopes or {})):
        checked = {}
        for view, value in table.items():
            if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
                raise ValueError(f"{name}[{view}] must be (row, col) pixels, got {value!r}")
            checked[integer(name, view, 0, "view numbers")] = tuple(
                finite(f"{name}[{view}]", v, "pixels") for v in value
            )
        shifts.append(checked)
    return coefficients, shifts[0], shifts[1]


class JPGM(nn.Module):
    """Joint pupil-geometry model: PSF stack ``(V, Z, 2r+1, 2r+1)`` from ``(c_j, b_v, s_v)``.

    Parameters
    ----------
    system : FLFMSystem
        Optics (objective, Fourier lens, MLA, camera).
    depths_um : sequence of float or Tensor
        ``(Z,)`` depths of the PSF planes relative to the native focal plane, micrometres of
        depth in the sample medium (see :mod:`fgat.optics.propagation`), scaled by the
        system's calibrated ``depth_scale``.
    centers_px : array-like, optional
        ``(V, 2)`` lenslet centres ``c_v`` on the camera (row, col), in view order (view 0 on the
        optical axis; see :mod:`fgat.optics.lenslets`); default: the system's nominal hexagonal
        MLA. The simulated lenslets sit on these centres, and the pupil image ``M`` (Eq. S4) is
        the disk of diameter ``D = 2 NA f_FL / M`` (Eq. S1) centred on view 0, dark where
        ``NA rho >= n_s`` (supercritical angles of a sample of lower index), with the
        aplanatic emission amplitude ``cos(theta_s)^(-1/2)``
        (:func:`~fgat.optics.propagation.emission_apodization`). Hexagonal
        lenslets take the lattice orientation of these centres
        (:func:`fgat.optics.pupil.lattice_angle`).
    zernike_indices : sequence of int
        Active Noll indices ``J`` (default 5..21, Eq. S5).
    crop_radius_px : int, optional
        Half-width ``r`` of the crops; default ``system.crop_radius_px``.
    method : {"auto", "mft", "asm"}
        Camera-intensity path (see the module docstring).
    oversampling : int or float, optional
        Pupil-plane oversampling ``s`` (grid pitch ``pixel / s``): an integer 1 to
        ``MAX_OVERSAMPLING``, or on the MFT path (``"mft"``, or ``"auto"`` where it picks the
        MFT) also ``1 / k``, ``k`` 2 to ``MFT_SUBSAMPLING``; ``None`` chooses it (module
        docstring). An ``s`` too coarse for the geometry is an error; one outgrown by the pupil
        phase during a fit is refined with a warning.
    depth_medium : {"sample", "immersion"}
        What a depth changes: the point's depth in the sample medium (the default), or the
        thickness of the immersion layer (a stage or objective step, the phase of
        ``sample_index = immersion_index`` with the sample's apodization; see
        :mod:`fgat.optics.propagation`).
    depth_chunk : int, optional
        Depths computed together (bounds memory); default chosen from the grid size.
    dtype, device
        Real dtype (float32 or float64) and device of parameters and outputs.

    Attributes
    ----------
    zernike_coefficients : nn.Parameter
        ``(K,)`` coefficients ``c_j`` in waves, zero at start.
    intercepts, slopes : nn.Parameter
        ``(V, 2)`` ``b_v`` (pixels) and ``s_v`` (pixels per unit of ``xi``), (row, col) order.
    oversampling : int or float
        The current pupil-plane oversampling ``s``.
    """

    def __init__(
        self,
        system: FLFMSystem,
        depths_um: Sequence[float] | Tensor,
        *,
        centers_px: np.ndarray | Tensor | None = None,
        zernike_indices: Sequence[int] = DEFAULT_INDICES,
        crop_radius_px: int | None = None,
        method: str = "auto",
        oversampling: int | None = None,
        depth_chunk: int | None = None,
        depth_medium: str = "sample",
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if method not in METHODS:
            raise ValueError(f"method must be 'auto', 'mft' or 'asm', got {method!r}")
        if oversampling is not None:
            oversampling = _checked_oversampling(oversampling, method)
        self.system = system
        self.radius = int(system.crop_radius_px if crop_radius_px is None else crop_radius_px)
        if self.radius < 1:
            raise ValueError(f"crop_radius_px must be a positive integer, got {crop_radius_px!r}")
        depths = torch.as_tensor(depths_um, dtype=torch.float64).reshape(-1)
        if depths.numel() == 0 or not torch.isfinite(depths).all():
            raise ValueError("depths_um must be a non-empty sequence of finite depths (um)")
        centers = torch.as_tensor(
            system.lenslet_centers_px() if centers_px is None else centers_px, dtype=torch.float64
        )
        if centers.ndim != 2 or centers.shape[1] != 2 or not torch.isfinite(centers).all():
            raise ValueError(
                f"centers_px must be finite with shape (V, 2), got {tuple(centers.shape)}"
            )
        self.zernike_indices = tuple(int(j) for j in zernike_indices)
        if depth_medium not in DEPTH_MEDIA:
            raise ValueError(f"depth_medium must be one of {DEPTH_MEDIA}, got {depth_medium!r}")
        self.method = method
        self.depth_chunk = depth_chunk
        self.depth_medium = depth_medium
        n_views = centers.shape[0]
        self.register_buffer("depths_um", depths.to(dtype))
        self.register_buffer("xi", normalized_depth(len(depths), dtype=dtype))
        self.register_buffer("centers", centers.to(dtype))
        self.zernike_coefficients = nn.Parameter(
            torch.zeros(len(self.zernike_indices), dtype=dtype)
        )
        self.intercepts = nn.Parameter(torch.zeros(n_views, 2, dtype=dtype))
        self.slopes = nn.Parameter(torch.zeros(n_views, 2, dtype=dtype))
        # The geometry is built, and rebuilt on refinement, from the float64 centres.
        self._geometry_centers = centers
        self._extreme_depth_um = float(depths.abs().max())
        self._lattice_angle = lattice_angle(centers, -math.radians(system.lattice_rotation_deg))
        # Without an explicit s the coarsest grid the path may take comes first (the cheapest).
        coarsest = 1 if method == "asm" else 1.0 / MFT_SUBSAMPLING
        self.oversampling = coarsest if oversampling is None else oversampling
        self._build_geometry()
        if oversampling is None:
            self._choose_sampling(with_zernike=False)
        else:
            method, centers = self.resolved_method(), self.crop_centers().detach()
            if method == "asm" and self.oversampling < 1:
                raise ValueError(
                    f"oversampling {self.oversampling:g} is for the 'mft' path; these lenslets "
                    "need the 'asm' path (see JPGM.crosstalk_bound), which takes an integer"
                )
            if self._phase_frequency(method, centers, 0.0) >= self.nyquist:
                raise self._sampling_error(method, centers, 0.0)
        self.to(device)

    @classmethod
    def with_parameters(
        cls,
        system: FLFMSystem,
        depths_um,
        *,
        zernike: dict | None = None,
        intercepts: dict | None = None,
        slopes: dict | None = None,
        **options,
    ) -> JPGM:
        """A JPGM with given optics: ``zernike`` Noll index -> waves (added to the default index
        set), ``intercepts`` / ``slopes`` view -> ``(row, col)`` pixels; other keywords as the
        constructor. Errors name the offending entry (see :func:`check_optics`). With the
        automatic ``oversampling`` the pupil grid is chosen for these coefficients."""
        zernike, intercepts, slopes = check_optics(zernike, intercepts, slopes)
        indices = tuple(sorted(set(options.pop("zernike_indices", DEFAULT_INDICES)) | set(zernike)))
        model = cls(system, depths_um, zernike_indices=indices, **options)
        with torch.no_grad():
            for j, value in zernike.items():
                model.zernike_coefficients[indices.index(j)] = value
            for name, shifts in (("intercepts", intercepts), ("slopes", slopes)):
                for view, value in shifts.items():
                    if not 0 <= view < model.n_views:
                        raise ValueError(
                            f"{name}: view {view} does not exist (views 0..{model.n_views - 1})"
                        )
                    getattr(model, name)[view] = torch.tensor(value)
        if options.get("oversampling") is None:
            model._choose_sampling(with_zernike=True)
        return model

    def memory_bytes(self, n_depths: int | None = None, *, planes: int | None = None) -> int:
        """Peak memory of :meth:`forward` in bytes, an upper bound from the shapes (no gradients);
        with ``n_depths``, of ``forward(depths)`` for a slice of that many planes (the first ones);
        with ``planes``, of the stack of a model like this one with ``planes`` depths over the
        same range (the windows and the sampling depend on the range only, so a model built on
        the two extreme depths sizes a stack of thousands before any of it is made).

        At the current :attr:`oversampling` ``s`` (the lenslet boxes and the FFT grid hold ``s^2``
        times the samples of ``s = 1``; :meth:`check_sampling` first refines ``s`` for the current
        Zernike coefficients). With ``e`` the real item size, ``V`` views, ``Z`` depths, crops of
        ``c = 2r + 1`` pixels, intensity windows of ``n`` pixels (:meth:`_windows`) and lenslet
        boxes of ``B`` samples: the per-lenslet geometry (``V B^2 e (K + 9)``: Zernike basis,
        coverage, amplitude, defocus and its two frequency maps, box coordinates), the windows of
        every depth held twice (chunks, then their concatenation: ``2 V Z n^2 e``), the crops and
        the bilinear interpolation's three temporaries (``4 V Z (c + 1)^2 e``), and one chunk of
        ``Zc`` depths (:meth:`_chunks`) in flight: for ``"mft"`` six ``V Zc B^2`` real arrays
        (phase, frequency, complex field) and the ``V Zc n B`` complex product, for ``"asm"`` the
        lenslet fields (``3 V Zc B^2 e``) and seven real arrays of the ``Zc Gy Gx`` FFT grid.
        """
        if n_depths is not None:
            with self._depth_subset(slice(0, max(1, min(int(n_depths), self.n_depths)))):
                return self.memory_bytes()
        with torch.no_grad():
            centers = self.crop_centers()
            _, size = self._windows(centers)
            method = self.resolved_method(centers)
        item = self.xi.element_size()
        n_views, box = self.n_views, self.basis.shape[-1]
        n_depths = self.n_depths if planes is None else int(planes)
        crop = 2 * self.radius + 2
        total = n_views * box**2 * item * (len(self.zernike_indices) + 9)
        total += 2 * n_views * n_depths * size**2 * item + 4 * n_views * n_depths * crop**2 * item
        if method == "mft":
            chunk = len(range(*self._chunks(box**2 * n_views, n_depths)[0].indices(n_depths)))
            total += n_views * chunk * (6 * box**2 + 2 * size * box) * item
        else:
            origins, _ = self._windows(centers)
            _, grid = self._asm_grid(origins, size)
            chunk = len(range(*self._chunks(grid[0] * grid[1] * 4, n_depths)[0].indices(n_depths)))
            total += (3 * n_views * box**2 + 7 * grid[0] * grid[1]) * chunk * item
        return int(total)

    # ------------------------------------------------------------------ geometry
    def _build_geometry(self) -> None:
        """Per-lenslet boxes ``(V, B, B)`` at pitch ``1 / s`` camera pixels: aperture
        ``coverage``, field ``amplitude`` (coverage times the emission apodization), defocus
        phase per um and its local frequency, Zernike basis; and the geometric phase frequency.

        Box samples sit at camera coordinates ``round(c_v) + k / s`` for ``|k| <= ceil(s h)``,
        ``h`` the circumscribed aperture radius rounded up plus one pixel, so ``B = 2 s h + 1``
        at an integer ``s`` and the box's first sample is the camera pixel ``box_origin``. The
        aperture is the point sample of each sample's centre, or at ``s < 1`` the fraction of
        its cell it covers. Buffers follow the model's dtype and device.
        """
        system, s = self.system, self.oversampling
        centers = self._geometry_centers
        radius = system.lenslet_aperture_mm * 500.0 / system.pixel_um  # disk radius or inradius
        reach = aperture_circumradius(system.lenslet_shape, radius)
        half = int(math.ceil(reach)) + 1
        if s >= 1:
            steps = torch.arange(-half * s, half * s + 1, dtype=torch.float64) / s
            box_origin = torch.round(centers) - half
        else:
            pitch = round(1 / s)
            samples = -(-half // pitch)
            steps = torch.arange(-samples, samples + 1, dtype=torch.float64) * pitch
            box_origin = torch.round(centers) - samples * pitch
        rows = box_origin[:, 0, None] - steps[0] + steps  # (V, B) absolute rows, camera pixels
        cols = box_origin[:, 1, None] - steps[0] + steps
        grid_rows = rows[:, :, None].expand(-1, -1, len(steps))
        grid_cols = cols[:, None, :].expand(-1, len(steps), -1)
        pupil_center = (float(centers[0, 0]), float(centers[0, 1]))
        rho, theta = pupil_coordinates(grid_rows, grid_cols, pupil_center, system.pupil_radius_px)
        zernike_radius = zernike_disk_radius(
            system.zernike_disk, system.pupil_radius_px, centers, reach
        )
        # The lit samples lie inside the disk; the clamp keeps rounding at its rim off zero.
        zernike_rho = (rho * (system.pupil_radius_px / zernike_radius)).clamp(max=1.0)

        def lit(at_rows: Tensor, at_cols: Tensor, views: Tensor) -> Tensor:
            """Whether light passes at camera points of the lenslets ``views`` (broadcast)."""
            rho_at = pupil_radius(at_rows, at_cols, pupil_center, system.pupil_radius_px)
            in_lenslet = lenslet_aperture(
                at_rows - centers[views, 0],
                at_cols - centers[views, 1],
                shape=system.lenslet_shape,
                radius=radius,
                angle=self._lattice_angle,
            )
            propagating = propagating_pupil(
                rho_at, na=system.na, sample_index=system.sample_medium_index
            )
            return in_lenslet & (rho_at <= 1.0) & propagating

        views = torch.arange(len(centers))[:, None, None]
        coverage = lit(grid_rows, grid_cols, views).to(torch.float64)
        if s < 1:
            coverage = _area_weights(coverage, grid_rows, grid_cols, round(1 / s), lit)
        if coverage.sum() == 0:
            raise ValueError(
                "no lenslet aperture lies inside the pupil: check the system and centres"
            )
        apodization = emission_apodization(
            rho.clamp(max=1.0), na=system.na, sample_index=system.sample_medium_index
        )
        amplitude = coverage * apodization
        # Phase per um of sample depth (or of the immersion layer), times FLFMSystem.depth_scale.
        defocus = system.depth_scale * defocus_phase_per_um(
            rho.clamp(max=1.0),
            wavelength_um=system.wavelength_um,
            na=system.na,
            immersion_index=system.immersion_index,
            sample_index=system.immersion_index
            if self.depth_medium == "immersion"
            else system.sample_index,
        )
        self.box_origin = box_origin.long()
        # Geometry derived from the system: rebuilt by the constructor, kept out of checkpoints.
        like = {"dtype": self.xi.dtype, "device": self.xi.device}
        self.register_buffer("box_rows", rows.to(**like), persistent=False)
        self.register_buffer("box_cols", cols.to(**like), persistent=False)
        self.register_buffer("coverage", coverage.to(**like), persistent=False)
        self.register_buffer("amplitude", amplitude.to(**like), persistent=False)
        self.register_buffer("defocus_per_um", defocus.to(**like), persistent=False)
        # Local spatial frequency of the defocus phase per um of depth, cycles per camera pixel.
        frequency = torch.stack(torch.gradient(defocus, spacing=1.0 / s, dim=(-2, -1))) / (
            2 * math.pi
        )  # (2, V, B, B) (row, col)
        self.register_buffer("defocus_frequency", frequency.to(**like), persistent=False)
        self.register_buffer(
            "basis",
            zernike_basis(self.zernike_indices, zernike_rho, theta).transpose(0, 1).to(**like),
            persistent=False,
        )  # (V, K, B, B)
        # Energy of the apodized aperture in grid cells: the integral of A^2 over the aperture.
        self.energy = float((coverage * apodization.square()).sum())
        self.kappa = system.pixel_um**2 / (system.wavelength_um * system.f_mla_mm * 1000.0)
        self.aperture_reach_px = reach  # circumradius, camera pixels
        self.lens_frequency = reach * self.kappa
        self.defocus_frequency_max = self._extreme_depth_um * float(
            (frequency.norm(dim=0) * (amplitude > 0)).max()
        )
        self.geometric_frequency = self.lens_frequency + self.defocus_frequency_max

    @property
    def nyquist(self) -> float:
        """Nyquist limit of the pupil-plane grid, ``0.5 s`` cycles per camera pixel."""
        return NYQUIST * self.oversampling

    def _zernike_frequency(self) -> float:
        """Largest local frequency of the current Zernike phase on the apertures, cycles per
        camera pixel."""
        gradient = _max_gradient(self.zernike_phase(), self.amplitude, self.oversampling)
        return gradient / (2 * math.pi)

    def _kernel_frequency(self, centers: Tensor) -> float:
        """Largest frequency ``kappa |x - c_v|`` of the matrix Fourier transform's kernel over
        the crop windows, cycles per camera pixel."""
        return self.kappa * float(self._window_reach(centers).max())

    def _phase_frequency(self, method: str, centers: Tensor, zernike: float) -> float:
        """Largest local frequency of the phase the pupil grid carries for ``method`` (module
        docstring), with ``zernike`` cycles per camera pixel of Zernike phase."""
        if method == "mft":
            geometry = self._kernel_frequency(centers) + self.defocus_frequency_max
        else:
            geometry = self.geometric_frequency
        return geometry + zernike

    def _next_sampling(self, frequency: float, method: str, *, refine: bool) -> float | None:
        """The coarsest ``s`` allowed for ``method`` (finer than the current one if ``refine``)
        that keeps ``frequency`` below ``SAMPLING_MARGIN`` of its Nyquist limit; ``s = 1`` also
        when it samples ``frequency`` at all, unless refining. ``None`` when no ``s`` up to
        ``MAX_OVERSAMPLING`` does."""
        coarse = [1.0 / k for k in range(MFT_SUBSAMPLING, 1, -1)] if method == "mft" else []
        for s in [*coarse, *range(1, MAX_OVERSAMPLING + 1)]:
            if refine and s <= self.oversampling:
                continue
            if frequency <= SAMPLING_MARGIN * NYQUIST * s or (
                s == 1 and not refine and frequency < NYQUIST
            ):
                return s
        return None

    def _choose_sampling(self, *, with_zernike: bool) -> None:
        """The automatic :attr:`oversampling` for the path :meth:`resolved_method` picks, the
        current shifts, and the current Zernike phase if ``with_zernike`` (else none); rebuilds
        the geometry when it changes, then refines it if the new grid measures the phase
        higher (:meth:`_refine_sampling`)."""
        with torch.no_grad():
            method, centers = self.resolved_method(), self.crop_centers()
            if method == "asm" and self.oversampling < 1:
                self.oversampling = 1
                self._build_geometry()
                method = self.resolved_method()
            zernike = self._zernike_frequency() if with_zernike else 0.0
            frequency = self._phase_frequency(method, centers, zernike)
            chosen = self._next_sampling(frequency, method, refine=False)
            if chosen is None:
                raise self._sampling_error(method, centers, zernike, MAX_OVERSAMPLING)
            if chosen != self.oversampling:
                self.oversampling = chosen
                self._build_geometry()
            self._refine_sampling(method, centers, with_zernike=with_zernike)

    def _refine_sampling(self, method: str, centers: Tensor, *, with_zernike: bool) -> None:
        """Raise :attr:`oversampling` until the phase ``method``'s grid carries (geometry, and
        the current Zernike phase if ``with_zernike``) is below its Nyquist limit, and to at
        least 1 for the ASM: each step takes :meth:`_next_sampling` and rebuilds the geometry.
        ``ValueError`` when no ``s`` up to ``MAX_OVERSAMPLING`` is enough."""
        with torch.no_grad():
            while True:
                zernike = self._zernike_frequency() if with_zernike else 0.0
                frequency = self._phase_frequency(method, centers, zernike)
                if frequency < self.nyquist and (method == "mft" or self.oversampling >= 1):
                    return
                refined = self._next_sampling(frequency, method, refine=True)
                if refined is None:
                    raise self._sampling_error(method, centers, zernike, MAX_OVERSAMPLING)
                self.oversampling = refined
                self._build_geometry()

    def _sampling_error(
        self, method: str, centers: Tensor, zernike: float, oversampling: float | None = None
    ) -> ValueError:
        """The error for ``method``'s pupil phase, the geometry's plus ``zernike`` cycles per
        camera pixel, above the Nyquist limit of ``oversampling`` (default the current one,
        given explicitly; or the largest)."""
        oversampling = self.oversampling if oversampling is None else oversampling
        total = self._phase_frequency(method, centers, zernike)
        limit = f"the Nyquist limit {NYQUIST * oversampling:g} of oversampling {oversampling:g}"
        needed = (
            self._next_sampling(total, method, refine=True)
            if oversampling < MAX_OVERSAMPLING
            else None
        )
        if needed is not None:
            remedy = f"use oversampling >= {needed:g} or None (automatic)"
        elif zernike > 0:
            remedy = "reduce the aberration amplitudes or the depth range"
        else:
            remedy = "use a longer f_mla_mm, smaller pixels or a smaller depth range"
        if zernike > 0:
            what = f"with the current Zernike coefficients (aberrations {zernike:.3f})"
        else:
            first = (
                f"window kernel {self._kernel_frequency(centers):.3f}"
                if method == "mft"
                else f"lenslet phase {self.lens_frequency:.3f}"
            )
            what = (
                f"({first} + defocus {self.defocus_frequency_max:.3f} at "
                f"|z| = {self._extreme_depth_um:g} um)"
            )
        return ValueError(
            f"sampling: the pupil-plane phase varies by {total:.3f} cycles per camera pixel "
            f"{what}, above {limit}; {remedy}"
        )

    # ------------------------------------------------------------------ public API
    @property
    def n_views(self) -> int:
        return self.centers.shape[0]

    @property
    def n_depths(self) -> int:
        return self.depths_um.shape[0]

    def crop_centers(self) -> Tensor:
        """``(V, Z, 2)`` crop centres ``c_v + b_v + s_v xi(z)`` (row, col) (Eqs. S11-S12)."""
        return (self.centers + self.intercepts)[:, None, :] + self.slopes[:, None, :] * self.xi[
            None, :, None
        ]

    def zernike_phase(self) -> Tensor:
        """``(V, B, B)`` Zernike pupil phase (radians) on each lenslet's box (Eq. S5)."""
        return 2.0 * math.pi * torch.einsum("k,vkij->vij", self.zernike_coefficients, self.basis)

    def pupil_phase_map(self, size: int = 128) -> Tensor:
        """The Zernike pupil phase over the whole pupil in waves, ``(size, size)``, NaN outside."""
        return wavefront_map(self.zernike_indices, self.zernike_coefficients, size)

    def crosstalk_bound(self, centers: Tensor | None = None) -> float:
        """Upper bound on the field a lenslet sends into another view's crop window.

        Relative to the field's peak, at the distance ``d`` of the nearest window pixel from
        another lenslet's axis, with ``kappa = pixel^2 / (lambda f_ML)``: for a disk of radius
        ``a`` the envelope ``2 sqrt(2 / pi) v^-1.5`` of the Airy amplitude ``2 J1(v) / v``,
        ``v = 2 pi kappa a d``; for a hexagon of circumradius ``R`` the bound
        ``|F(k)| / F(0) <= 2 w / (|k| A) <= 8 / (3 sqrt(3) v)`` of any convex aperture of area
        ``A`` and width ``w <= 2R`` (divergence theorem), ``v = 2 pi kappa R d``: straight edges
        diffract as ``1 / v`` along their normals (the streaks towards the neighbours), so the
        disk's ``v^-1.5`` envelope would not bound them. Infinite when a window reaches another
        lenslet's axis or lies farther than half the period ``s / kappa`` of the matrix Fourier
        transform from its own lenslet's axis.
        """
        centers = self.crop_centers().detach() if centers is None else centers
        nominal = self.centers
        reach = self._window_reach(centers)
        if bool((reach >= 0.5 * self.oversampling / self.kappa).any()):
            return math.inf
        if self.n_views == 1:
            return 0.0
        distance = torch.cdist(nominal, nominal) - reach[None, :]
        distance = distance[~torch.eye(self.n_views, dtype=torch.bool, device=distance.device)]
        if bool((distance <= 0).any()):
            return math.inf
        v = 2.0 * math.pi * self.kappa * self.aperture_reach_px * float(distance.min())
        if self.system.lenslet_shape == "hexagon":
            return 8.0 / (3.0 * math.sqrt(3.0) * v)
        return 2.0 * math.sqrt(2.0 / math.pi) * v**-1.5

    def _window_reach(self, centers: Tensor) -> Tensor:
        """``(V,)`` bound on the distance (camera pixels) from each lenslet's axis to a pixel
        of its view's crop windows, for crop centres ``(V, Z, 2)``."""
        shift = (centers.detach() - self.centers[:, None]).abs().amax(dim=(1, 2))
        return math.sqrt(2.0) * (shift + self.radius + 1)

    def resolved_method(self, centers: Tensor | None = None) -> str:
        """The path ``"auto"`` picks: ``"mft"`` when :meth:`crosstalk_bound` is below
        ``CROSSTALK_TOLERANCE``, else ``"asm"``."""
        if self.method != "auto":
            return self.method
        return "mft" if self.crosstalk_bound(centers) < CROSSTALK_TOLERANCE else "asm"

    def forward(self, depths: slice | None = None) -> Tensor:
        """The PSF stack ``(V, Z, 2r+1, 2r+1)``, each depth normalised to unit energy on the
        camera (Eq. S9) before cropping; with ``depths`` (a slice of the depth axis) only those
        planes, ``forward()[:, depths]`` computed alone (a depth-chunked gradient keeps one
        chunk's graph in memory at a time)."""
        if depths is not None:
            with self._depth_subset(depths):
                return self.forward()
        centers = self.crop_centers()
        method = self.check_sampling(centers.detach())
        origins, size = self._windows(centers.detach())
        intensity = (self._intensity_mft if method == "mft" else self._intensity_asm)(origins, size)
        n_views, n_depths = centers.shape[:2]
        crops = bilinear_crops(
            intensity.reshape(-1, size, size),
            origins[:, None, :].expand(-1, n_depths, -1).reshape(-1, 2),
            centers.reshape(-1, 2),
            self.radius,
        )
        return crops.reshape(n_views, n_depths, 2 * self.radius + 1, 2 * self.radius + 1)

    @contextlib.contextmanager
    def _depth_subset(self, depths: slice):
        """The model restricted to the planes ``depths`` (their depths and ``xi``) while open."""
        full = self.depths_um, self.xi
        if not isinstance(depths, slice) or not len(range(*depths.indices(len(full[0])))):
            raise ValueError(f"depths must be a non-empty slice of the {len(full[0])} planes")
        self.depths_um, self.xi = full[0][depths], full[1][depths]
        try:
            yield
        finally:
            self.depths_um, self.xi = full

    def check_sampling(self, centers: Tensor | None = None) -> str:
        """Refine the pupil-plane oversampling if the Zernike phase or the shifts have outgrown
        it, or the path :meth:`resolved_method` picks is the ASM on a grid coarser than the
        camera's (with a warning naming the new ``s``); raise ``ValueError`` if even
        ``MAX_OVERSAMPLING`` cannot sample the pupil phase, or a crop is centred off the sensor
        or wider than it (:func:`check_crops_on_sensor`). Returns the path for ``centers`` on
        the grid it leaves."""
        with torch.no_grad():
            centers = self.crop_centers() if centers is None else centers
            method = self.resolved_method(centers)
            zernike = self._zernike_frequency()
            total = self._phase_frequency(method, centers, zernike)
            coarse = self.oversampling
            if total >= self.nyquist or (method == "asm" and coarse < 1):
                self._refine_sampling(method, centers, with_zernike=True)
                warnings.warn(
                    f"JPGM: the pupil-plane phase of the {method} path varies by {total:.3f} "
                    f"cycles per camera pixel (Zernike {zernike:.3f}); the Nyquist limit of "
                    f"oversampling {coarse:g} is {NYQUIST * coarse:g}: refined the pupil grid "
                    f"to oversampling {self.oversampling:g}",
                    RuntimeWarning,
                    stacklevel=2,
                )
                method = self.resolved_method(centers)
            check_crops_on_sensor(centers, self.radius, self.system.sensor_shape)
        return method

    # ------------------------------------------------------------------ intensity paths
    def _windows(self, centers: Tensor) -> tuple[Tensor, int]:
        """Integer window origins ``(V, 2)`` and common size covering every crop of each view."""
        base = torch.floor(centers).long()
        low = base.amin(dim=1) - self.radius
        high = base.amax(dim=1) + self.radius + 1
        size = int((high - low).max()) + 1
        return low, size

    def _chunks(self, per_depth_pixels: int, n_depths: int | None = None) -> list[slice]:
        """Slices of ``depth_chunk`` depths, or by default of at most ``2^25`` samples of
        ``per_depth_pixels`` each, as even as their count allows, over ``n_depths`` planes
        (default the model's)."""
        n_depths = self.n_depths if n_depths is None else n_depths
        chunk = self.depth_chunk
        if not chunk:
            largest = max(1, int(2**25 // max(per_depth_pixels, 1)))
            chunk = -(-n_depths // -(-n_depths // largest))
        return [slice(i, i + chunk) for i in range(0, n_depths, chunk)]

    def _pupil_phase(self, depths: Tensor, zernike: Tensor) -> Tensor:
        """``(V, Zc, B, B)`` defocus phase at ``depths`` plus the Zernike phase ``(V, B, B)``."""
        return torch.addcmul(
            zernike[:, None], depths[None, :, None, None], self.defocus_per_um[:, None]
        )

    def _intensity_mft(self, origins: Tensor, size: int) -> Tensor:
        """Camera intensity ``(V, Z, size, size)`` on each view's window, lenslet by lenslet.

        The field a lenslet's aperture sends to the camera is the matrix Fourier transform of
        ``A exp(i (phi_defocus + phi_Z + psi))``, where ``psi = -K |f|^4`` is the first
        non-paraxial term of the angular-spectrum phase at the local spatial frequency ``f`` of
        the field leaving the lens (thin lens, defocus and Zernike phase gradients). ``|f|^2`` is
        a quadratic in depth, ``a0 + z a1 + z^2 a2``, whose coefficient maps are computed once.
        The aperture samples sit at fractional camera coordinates (pitch ``1 / s``): the
        Riemann sum's weight ``1 / s^2`` and the aperture energy ``sum A^2 / s^2`` give the
        normalisation ``kappa^2 / (s^2 sum A^2)`` of the squared sum.
        """
        steps = torch.arange(size, device=origins.device, dtype=self.xi.dtype)
        out_rows = origins[:, 0, None].to(self.xi.dtype) + steps  # (V, n)
        out_cols = origins[:, 1, None].to(self.xi.dtype) + steps
        rel_in_r = self.box_rows - self.centers[:, 0, None]
        rel_in_c = self.box_cols - self.centers[:, 1, None]
        kernel_r = _dft_matrix(
            out_rows - self.centers[:, 0, None], rel_in_r, self.kappa
        )  # (V, n, B)
        kernel_c = _dft_matrix(out_cols - self.centers[:, 1, None], rel_in_c, self.kappa).transpose(
            -1, -2
        )
        zernike = self.zernike_phase()
        zernike_r, zernike_c = torch.gradient(
            zernike, spacing=1.0 / self.oversampling, dim=(-2, -1)
        )
        f0_r = (
            zernike_r / (2 * math.pi) - self.kappa * rel_in_r[:, :, None]
        )  # cycles / pixel at z = 0
        f0_c = zernike_c / (2 * math.pi) - self.kappa * rel_in_c[:, None, :]
        g_r, g_c = self.defocus_frequency
        a0 = (f0_r.square() + f0_c.square())[:, None]
        a1 = (2 * (f0_r * g_r + f0_c * g_c))[:, None]
        a2 = (g_r.square() + g_c.square())[:, None]
        quartic = (
            quartic_phase_coefficient(
                wavelength_um=self.system.wavelength_um, distance_um=self.system.f_mla_mm * 1000.0
            )
            / self.system.pixel_um**4
        )
        scale = self.kappa**2 / (self.oversampling**2 * self.energy)
        results = []
        defocus = self.defocus_per_um[:, None]
        for part in self._chunks(self.basis.shape[-1] ** 2 * self.n_views):
            field = _DefocusedField.apply(
                self.amplitude[:, None], zernike[:, None], defocus, a0, a1, a2,
                self.depths_um[part], quartic,
            )  # fmt: skip
            camera = kernel_r[:, None] @ field @ kernel_c[:, None]
            results.append(_intensity(camera) * scale)
        return torch.cat(results, dim=1)

    def _asm_grid(self, origins: Tensor, size: int) -> tuple[Tensor, tuple[int, int]]:
        """Origin and shape of an FFT grid of pitch ``1 / s`` camera pixels holding every
        lenslet box and crop window, in grid samples (camera pixel ``p`` is sample ``s p``).

        Besides half a box of margin on each side, each axis spans at least the largest distance
        from a lenslet axis to a window pixel plus the farthest the sampled field of a lenslet
        reaches from its axis on the camera (its aperture's circumradius ``R`` plus ``0.5 s /
        kappa`` for the grid's highest spatial frequency ``0.5 s`` cycles per pixel), so that
        the light that the FFT's periodicity wraps around lands in no window.
        """
        s, box = self.oversampling, self.basis.shape[-1]
        windows = origins.cpu()
        low = s * torch.minimum(self.box_origin.amin(0), windows.amin(0))
        high = torch.maximum(
            s * self.box_origin.amax(0) + box, s * (windows.amax(0) + size - 1) + 1
        )
        margin = box // 2
        axes = self._geometry_centers
        spread = torch.maximum(
            windows.amax(0) + size - 1 - axes.amin(0), axes.amax(0) - windows.amin(0)
        )
        band = s * (spread + self.aperture_reach_px + 0.5 * s / self.kappa)
        shape = tuple(
            fast_fft_size(max(int(h - lo) + 2 * margin, math.ceil(b)))
            for lo, h, b in zip(low, high, band)
        )
        return low - margin, shape

    def _intensity_asm(self, origins: Tensor, size: int) -> Tensor:
        """Camera intensity ``(V, Z, size, size)`` by angular-spectrum propagation of the MLA.

        On the grid of pitch ``1 / s`` pixels the propagation keeps ``sum |E|^2 = sum A^2``;
        the camera pixel centres are every ``s``-th sample (point samples), normalised by
        ``sum A^2 / s^2`` so that they sum to about 1 like the matrix Fourier transform's.
        """
        system, s = self.system, self.oversampling
        grid_origin, shape = self._asm_grid(origins, size)
        complex_dtype = _complex(self.xi.dtype)
        transfer = angular_spectrum_transfer(
            shape,
            pixel_um=system.pixel_um / s,
            wavelength_um=system.wavelength_um,
            distance_um=system.f_mla_mm * 1000.0,
            dtype=complex_dtype,
            device=self.xi.device,
        )
        lens = thin_lens_phase(
            self.box_rows[:, :, None],
            self.box_cols[:, None, :],
            self.centers,
            focal_um=system.f_mla_mm * 1000.0,
            pixel_um=system.pixel_um,
            wavelength_um=system.wavelength_um,
        )
        box_at = (s * self.box_origin - grid_origin).tolist()
        win_at = (s * origins.cpu() - grid_origin).tolist()
        windows = (size, size)
        zernike = self.zernike_phase()
        results = []
        for part in self._chunks(shape[0] * shape[1] * 4):
            phase = self._pupil_phase(self.depths_um[part], zernike) + lens[:, None]
            boxes = aperture_field(self.amplitude[:, None].expand_as(phase), phase)
            field = place_patches(boxes.transpose(0, 1), box_at, shape)  # (Zc, H, W)
            camera = crop_patches(angular_spectrum_propagate(field, transfer), win_at, windows, s)
            results.append(_intensity(camera).transpose(0, 1) / (self.energy / s**2))
        return torch.cat(results, dim=1)


def _phase_gradient(grad: Tensor, field: Tensor) -> Tensor:
    """``dL/dphase`` of ``u = A exp(i phase)`` from ``dL/du`` ``g``: ``Im(g) Re(u) - Re(g)
    Im(u)``, two real products per pixel."""
    return grad.imag * field.real - grad.real * field.imag


def _phase_tangent(field: Tensor, d_phase: Tensor) -> Tensor:
    """``du = i u dphase``: the forward-mode derivative of ``u = A exp(i phase)``."""
    return torch.complex(-field.imag * d_phase, field.real * d_phase)


class _ApertureField(torch.autograd.Function):
    """``amplitude * exp(i phase)``, differentiable in the phase only (the aperture is fixed).

    Its backward is two real products per pixel, ``d L / d phase = Im(g) Re(u) - Re(g) Im(u)``
    for the output ``u`` and incoming gradient ``g``, instead of the general complex
    ``polar`` backward, which also forms the unused amplitude gradient. Its forward-mode
    derivative ``du = i u dphase`` (and vmap) serve the Jacobians of
    :func:`fgat.optics.crossinfo.cross_information`.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(amplitude: Tensor, phase: Tensor) -> Tensor:
        return torch.polar(amplitude, phase)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(output)
        ctx.save_for_forward(output, inputs[1])

    @staticmethod
    def backward(ctx, grad: Tensor):
        (field,) = ctx.saved_tensors
        return None, _phase_gradient(grad, field)

    @staticmethod
    def jvp(ctx, amplitude_tangent, phase_tangent):
        field, phase = ctx.saved_tensors
        tangent = torch.zeros_like(field)
        if phase_tangent is not None:
            tangent = _phase_tangent(field, phase_tangent)
        if amplitude_tangent is not None:
            tangent = tangent + torch.polar(amplitude_tangent, phase)
        return tangent


def _fused_field(*tensors: Tensor) -> bool:
    """Whether :class:`_DefocusedField` runs as Triton kernels
    (:mod:`fgat.optics.defocused_field_triton`) on ``tensors``: float32 on one GPU (or on the
    CPU in Triton's interpreter, ``TRITON_INTERPRET=1``), Triton installed, and no functorch
    transform wrapping them (``vmap`` and ``jvp`` take the PyTorch path)."""
    device = tensors[0].device
    return (
        all(t.dtype == torch.float32 and t.device == device for t in tensors)
        and (
            device.type == "cuda"
            or (device.type == "cpu" and os.environ.get("TRITON_INTERPRET") == "1")
        )
        and not functorch_wrapped(*tensors)
        and triton_installed()
    )


class _DefocusedField(torch.autograd.Function):
    """The lenslet fields of :meth:`JPGM._intensity_mft` at depths ``z``:
    ``A exp(i (Phi + z D - q f^2))`` with ``f = a0 + z a1 + z^2 a2`` (the squared local
    frequency), ``(V, Z, B, B)`` from the per-view maps ``A``, ``Phi``, ``D``, ``a0``, ``a1``,
    ``a2`` ``(V, 1, B, B)``, depths ``(Z,)`` (um) and the quartic coefficient ``q``.

    Differentiable in ``Phi``, ``D`` and ``a0..a2`` (the aperture ``A`` and the depths are
    fixed). Autograd through the same expression keeps several stack-sized intermediates and
    reduces each broadcast map over the depths on its own; here the backward forms ``dL/dphase``
    (:func:`_phase_gradient`) and ``f dL/dphase`` once and reduces both
    against the powers of ``z`` in two small matrix products. In float32 on a GPU
    (:func:`_fused_field`) both directions are fused Triton kernels instead, and the backward
    recomputes the fields from the saved maps rather than keeping the stack. The forward-mode
    derivative ``du = i u dphase`` (and vmap) serve the cross-information's Jacobians.
    """

    generate_vmap_rule = True

    @staticmethod
    def _frequency(a0: Tensor, a1: Tensor, a2: Tensor, depths: Tensor) -> Tensor:
        z = depths[:, None, None]
        return torch.addcmul(a0, z, torch.addcmul(a1, z, a2))

    @staticmethod
    def _phase(zernike, defocus, a0, a1, a2, depths, quartic) -> Tensor:
        frequency = _DefocusedField._frequency(a0, a1, a2, depths)
        phase = torch.addcmul(zernike, depths[:, None, None], defocus)
        return torch.add(phase, frequency.square(), alpha=-quartic)

    @staticmethod
    def _field(amplitude, zernike, defocus, a0, a1, a2, depths, quartic) -> Tensor:
        phase = _DefocusedField._phase(zernike, defocus, a0, a1, a2, depths, quartic)
        return torch.polar(amplitude.expand_as(phase), phase)

    @staticmethod
    def forward(amplitude, zernike, defocus, a0, a1, a2, depths, quartic):
        inputs = amplitude, zernike, defocus, a0, a1, a2, depths
        if _fused_field(*inputs):
            from fgat.optics.defocused_field_triton import (  # Triton: only on the GPU path
                defocused_field,
            )

            return defocused_field(*inputs, quartic)
        return _DefocusedField._field(*inputs, quartic)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.quartic = inputs[-1]
        ctx.fused = _fused_field(*inputs[:7])
        if ctx.fused:
            ctx.save_for_backward(*inputs[:7])
        else:
            ctx.save_for_backward(output, *inputs[3:7])
        ctx.save_for_forward(output, *inputs[:7])

    @staticmethod
    def backward(ctx, grad: Tensor):
        if not ctx.fused:
            return _DefocusedField._moments(grad, *ctx.saved_tensors, ctx.quartic)
        inputs = ctx.saved_tensors
        if _fused_field(grad.real, *inputs) and not torch.is_grad_enabled():
            from fgat.optics.defocused_field_triton import (  # Triton: only on the GPU path
                defocused_field_moments,
            )

            return None, *defocused_field_moments(grad, *inputs, ctx.quartic), None, None
        # A double backward (create_graph) or a functorch transform: the fields recomputed in
        # PyTorch operations, which these differentiate.
        field = _DefocusedField._field(*inputs, ctx.quartic)
        return _DefocusedField._moments(grad, field, *inputs[3:], ctx.quartic)

    @staticmethod
    def _moments(grad, field, a0, a1, a2, depths, quartic):
        """The backward's gradients from the fields ``field`` ``(V, Z, B, B)``."""
        views, n_depths = field.shape[:2]
        d_phase = _phase_gradient(grad, field)  # (V, Z, B, B)
        weighted = _DefocusedField._frequency(a0, a1, a2, depths) * d_phase
        powers = depths[None, :] ** torch.arange(3, device=depths.device)[:, None]  # (3, Z)
        moments = powers[:2] @ d_phase.reshape(views, n_depths, -1)  # sum_z z^k dL/dphase
        frequency_moments = powers @ weighted.reshape(views, n_depths, -1)
        box = field.shape[2:]
        moments = moments.reshape(views, 2, 1, *box)
        frequency_moments = frequency_moments.reshape(views, 3, 1, *box) * (-2.0 * quartic)
        return (
            None,
            moments[:, 0],
            moments[:, 1],
            frequency_moments[:, 0],
            frequency_moments[:, 1],
            frequency_moments[:, 2],
            None,
            None,
        )

    @staticmethod
    def jvp(ctx, d_amplitude, d_zernike, d_defocus, d_a0, d_a1, d_a2, d_depths, d_quartic):
        field, amplitude, zernike, defocus, a0, a1, a2, depths = ctx.saved_tensors
        z = depths[:, None, None]
        d_phase = torch.zeros_like(field.real)
        if d_zernike is not None:
            d_phase = d_phase + d_zernike
        if d_defocus is not None:
            d_phase = d_phase + z * d_defocus
        if d_a0 is not None or d_a1 is not None or d_a2 is not None:
            zero = torch.zeros_like(a0)
            d_frequency = _DefocusedField._frequency(
                zero if d_a0 is None else d_a0,
                zero if d_a1 is None else d_a1,
                zero if d_a2 is None else d_a2,
                depths,
            )
            frequency = _DefocusedField._frequency(a0, a1, a2, depths)
            d_phase = d_phase - 2.0 * ctx.quartic * frequency * d_frequency
        tangent = _phase_tangent(field, d_phase)
        if d_amplitude is not None:
            phase = _DefocusedField._phase(zernike, defocus, a0, a1, a2, depths, ctx.quartic)
            tangent = tangent + torch.polar(d_amplitude.expand_as(phase), phase)
        return tangent


def aperture_field(amplitude: Tensor, phase: Tensor) -> Tensor:
    """Complex field ``amplitude * exp(i phase)`` (same shapes); gradients flow to ``phase``."""
    return _ApertureField.apply(amplitude, phase)


def _intensity(field: Tensor) -> Tensor:
    """``|field|^2`` with a cheap, everywhere-smooth backward (no ``abs``)."""
    return torch.view_as_real(field).square().sum(dim=-1)


def _complex(dtype: torch.dtype) -> torch.dtype:
    return torch.complex128 if dtype == torch.float64 else torch.complex64


def _dft_matrix(out_coords: Tensor, in_coords: Tensor, kappa: float) -> Tensor:
    """``exp(-2 pi i kappa x u)`` for output ``(V, n)`` and input ``(V, B)`` coordinates:
    ``(V, n, B)``."""
    phase = -2.0 * math.pi * kappa * out_coords[:, :, None] * in_coords[:, None, :]
    return torch.polar(torch.ones_like(phase), phase)


def _area_weights(lit_centres: Tensor, rows: Tensor, cols: Tensor, pitch: float, lit) -> Tensor:
    """The fraction of each cell of side ``pitch`` camera pixels that ``lit(rows, cols, views)``
    covers, on ``AREA_SUBSAMPLES^2`` points per cell, for the cells at ``(rows, cols)`` ``(V, B,
    B)`` whose centres ``lit_centres`` (0 or 1) light. Only cells within two of a change of
    ``lit_centres`` are subsampled (every cell of a view none of whose centres is lit): across
    a cell, boundaries whose curvature radius is many cells (the pupil, the lenslets) are nearly
    straight, so a cell they cut has a neighbour or a diagonal neighbour on the other side; the
    others are wholly lit or dark."""
    lit_near = torch.nn.functional.max_pool2d(lit_centres, 5, 1, 2)
    dark_near = -torch.nn.functional.max_pool2d(-lit_centres, 5, 1, 2) < 1
    unlit_view = lit_centres.flatten(1).amax(dim=1) == 0  # an aperture between the centres
    changing = ((lit_near > 0) & dark_near) | unlit_view[:, None, None]
    v, i, j = changing.nonzero(as_tuple=True)
    offsets = (torch.arange(AREA_SUBSAMPLES, dtype=torch.float64) + 0.5) / AREA_SUBSAMPLES - 0.5
    offsets = offsets * pitch
    shape = (len(v), AREA_SUBSAMPLES, AREA_SUBSAMPLES)
    at_rows = (rows[v, i, j][:, None, None] + offsets[:, None]).expand(shape).flatten(1)
    at_cols = (cols[v, i, j][:, None, None] + offsets[None, :]).expand(shape).flatten(1)
    weights = lit_centres.clone()
    weights[v, i, j] = lit(at_rows, at_cols, v[:, None]).to(torch.float64).mean(dim=1)
    return weights


def _checked_oversampling(value, method: str) -> int | float:
    """An explicit ``oversampling``: an integer 1 to ``MAX_OVERSAMPLING``, or for the MFT
    ``1 / k`` (``k`` 2 to ``MFT_SUBSAMPLING``) returned as exactly ``1.0 / k``."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        if 1 <= value <= MAX_OVERSAMPLING:
            return int(value)
    elif isinstance(value, (float, np.floating)) and method != "asm" and 0 < value < 1:
        k = round(1.0 / value)
        if 2 <= k <= MFT_SUBSAMPLING and math.isclose(value * k, 1.0, rel_tol=1e-9):
            return 1.0 / k
    raise ValueError(
        f"oversampling must be None, an integer from 1 to {MAX_OVERSAMPLING}, or for the "
        f"'mft' or 'auto' method 1/k with k from 2 to {MFT_SUBSAMPLING}; got {value!r}"
    )


def _max_gradient(phase: Tensor, amplitude: Tensor, oversampling: float) -> float:
    """Largest phase change per camera pixel (radians) where ``amplitude > 0``, for a phase
    ``(..., H, W)`` sampled at ``oversampling`` samples per pixel."""
    grad_r, grad_c = torch.gradient(phase, spacing=1.0 / oversampling, dim=(-2, -1))
    magnitude = torch.sqrt(grad_r**2 + grad_c**2) * (amplitude > 0)
    return float(magnitude.max()) if magnitude.numel() else 0.0
