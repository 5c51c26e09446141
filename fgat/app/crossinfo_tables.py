"""The numerical experiments of Note S5 on JPGM's pupil-geometry cross-information (Tables S2-S5).

Every experiment works at one point of the JPGM (the true optics of a simulated scene, or the
optics a static fit estimated) with the volume held fixed (Eq. S37), in float64, with the pixel
L2 metric ``W = I``:

* modal profiles (Note S5.2, Tables S2-S3): the row norms ``eta_j^b``, ``eta_j^s`` of the
  cross-information blocks ``C_b``, ``C_s`` (Eqs. S47-S48) and ``||C_s||_F / ||C_b||_F``
  (:func:`modal_table`);
* shift injection (Note S5.3, Table S4): a geometry perturbation ``dTheta_G`` is injected, the
  Zernike coefficients are refitted to the unperturbed prediction, and their change is compared
  with the leakage map ``-A^-1 C dTheta_G`` of Eq. S51 (:func:`leakage_test`);
* noisy repeatability (Note S5.4, Table S5): joint refits of ``(Theta_P, Theta_G)`` under
  additive white Gaussian noise, against the standard errors ``sigma sqrt(diag(S^-1))`` of the
  Schur complements of Eqs. S49-S50 (:func:`repeatability`).

The refits (:func:`refit`) minimise ``0.5 ||y(Theta) - data||^2`` of the JPGM and the forward
operator themselves (not their linearisation) by quasi-Newton steps whose curvature starts at
the Gauss-Newton matrix of Eq. S42 at the analysed point (then BFGS-updated), with the exact
gradient recomputed by reverse-mode automatic differentiation at every iterate, and
backtracking. A fixed point has zero exact gradient, so it is the minimiser that Gauss-Newton
with a fresh Jacobian at every step would reach, at one forward and backward pass per iteration
instead of ``K + 4V`` Jacobian-vector products.

:func:`analysis_scene` makes the scene (a :class:`~fgat.sim.simulation.SimulationConfig`: system,
depths, seeded bead phantom, seeded optics point), :func:`run_scene` reads a static fit's results
folder instead, :func:`analyse` runs the three experiments and :func:`write_report` writes their
tables (CSV and markdown), figures and a summary. ``python -m fgat analyze crossinfo`` is the
command line.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, fields
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.func import functional_call

from fgat._core.resources import check_memory
from fgat._core.validation import check_number, require
from fgat.analysis.outputs import write_outputs
from fgat.io.files import (
    atomic_path,
    check_output_file,
    check_writable_folder,
    read_text,
    write_csv,
    write_json,
)
from fgat.io.images import read_tiff, volume_metadata
from fgat.io.yaml_files import read_yaml, yaml_fields
from fgat.optics.acquisition import MeasuredOperator
from fgat.optics.crossinfo import GEOMETRY, CrossInformation, cross_information
from fgat.optics.operator import FLFMOperator, operator_memory
from fgat.optics.psf import JPGM, METHODS
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.optics.zernike import noll_to_nm, zernike_family
from fgat.recon import names
from fgat.sim.simulation import SimulationConfig, make_phantom, simulation_memory, true_optics
from fgat.viz.optics import plot_cross_information, plot_eta_profiles, plot_leakage

PARAMETERS = ("zernike_coefficients", *GEOMETRY)
"""The JPGM parameters of ``(Theta_P, Theta_G)`` in the column order of the block Hessian."""

SPHERICAL = 11
"""Noll index of primary spherical aberration, the symmetric mode Note S5 singles out."""

SCENE_FIELDS = (
    "system",
    "depths_um",
    "view_size",
    "phantom",
    "zernike",
    "intercepts",
    "slopes",
    "aberrations",
    "seed",
)
"""The :class:`~fgat.sim.simulation.SimulationConfig` fields a scene takes (no camera, no noise)."""

Operator = Callable[[Tensor], object]
"""``operator(psf_stack)`` with ``forward(volume) -> (V, Y, X)``, as in
:func:`~fgat.optics.crossinfo.cross_information`."""


# ---------------------------------------------------------------------------------- tables
@dataclass(frozen=True)
class Table:
    """One result table: rows of named values and the scalar findings that go with it.

    Attributes
    ----------
    name : str
        File stem (``tableS2_intercept_profile`` -> ``.csv`` and ``.md``).
    title : str
        One-line caption.
    columns : tuple of str
        Column names, in order.
    rows : list of dict
        One mapping per row, keyed by ``columns``.
    summary : dict
        Scalar findings (name -> number or text), listed under the markdown table.
    """

    name: str
    title: str
    columns: tuple[str, ...]
    rows: list[dict]
    summary: dict = field(default_factory=dict)

    def markdown(self) -> str:
        """The table as GitHub markdown: caption, table (numbers to 4 significant digits) and
        the summary as a list."""
        lines = [
            f"**{self.title}**",
            "",
            "| " + " | ".join(self.columns) + " |",
            "|" + "---|" * len(self.columns),
        ]
        lines += [
            "| " + " | ".join(_text(row[c]).replace("|", "\\|") for c in self.columns) + " |"
            for row in self.rows
        ]
        if self.summary:
            lines.append("")
            lines += [f"- {key}: {_text(value)}" for key, value in self.summary.items()]
        return "\n".join(lines) + "\n"


def _text(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`fgat.io.files.atomic_path`)."""
    with atomic_path(path) as temporary:
        temporary.write_text(text)
    return Path(path)


def table_writers(table: Table) -> dict[str, Callable[[Path], object]]:
    """``{"<name>.csv": writer, "<name>.md": writer}`` of ``table`` (full precision CSV, markdown),
    for :func:`fgat.analysis.outputs.write_outputs`."""
    return {
        f"{table.name}.csv": partial(write_csv, columns=table.columns, rows=table.rows),
        f"{table.name}.md": partial(_write_text, text=table.markdown()),
    }


def write_table(table: Table, folder: str | Path) -> tuple[Path, Path]:
    """Write ``table`` as ``<folder>/<name>.csv`` (full precision) and ``<name>.md``
    (atomically); return both paths."""
    folder = Path(folder)
    return tuple(write(folder / name) for name, write in table_writers(table).items())


def _mode(j: int) -> dict:
    n, m = noll_to_nm(j)
    return {"noll": j, "n": n, "m": m, "family": zernike_family(j)}


def _ranked(indices: Sequence[int], values: np.ndarray, key: str, top: int | None) -> list[dict]:
    """Rows ``rank, noll, n, m, family, <key>`` sorted by ``values`` descending (``top`` first)."""
    order = np.argsort(-values, kind="stable")[:top]
    return [
        {"rank": rank, **_mode(indices[k]), key: float(values[k])}
        for rank, k in enumerate(order, start=1)
    ]


# ---------------------------------------------------------------------------- the scene
def analysis_scene(
    config, *, crop_radius_px: int | None = None, method: str = "auto", device=None
) -> tuple[JPGM, Tensor]:
    """The JPGM at a scene's true optics and the scene's volume, both float64.

    Parameters
    ----------
    config : SimulationConfig
        ``system``, ``depths_um`` (``Z`` planes), ``view_size`` (``Y = X``), ``phantom`` (seeded
        beads by default), and the optics point: ``zernike`` / ``intercepts`` / ``slopes`` and
        the seeded random ``aberrations`` (:func:`fgat.sim.simulation.true_optics`). Its camera and
        noise fields are not used.
    crop_radius_px : int, optional
        PSF crop half-width ``r`` (default the system's).
    method : {"auto", "mft", "asm"}
        The JPGM's intensity path.
    device : str or torch.device, optional
        Where both live (default the CPU).

    Returns
    -------
    (JPGM, Tensor)
        The generator (parameters ``c_j`` in waves, ``b_v``, ``s_v`` in pixels at the truth)
        and the volume ``(Z, Y, X)`` in ``[0, 1]``.
    """
    config.validate()
    system = load_system(config.system)
    depths = parse_depths(config.depths_um)
    shape = (len(depths), config.view_size, config.view_size)
    radius = system.crop_radius_px if crop_radius_px is None else crop_radius_px
    check_analysis_memory(shape, system.n_lenslets, radius, scene=config, device=device)
    spec = OpticsSpec(system, tuple(depths), None, **true_optics(config, system.n_lenslets))
    jpgm = spec.jpgm(
        crop_radius_px=crop_radius_px, method=method, dtype=torch.float64, device=device
    )
    jpgm.check_sampling()
    check_analysis_memory(shape, jpgm.n_views, jpgm.radius, jpgm=jpgm, scene=config, device=device)
    volume = make_phantom(config, shape)
    return jpgm, torch.from_numpy(volume).to(device=device, dtype=torch.float64)


TANGENTS = 8
"""Jacobian columns per forward-mode pass (:func:`~fgat.optics.crossinfo.jpgm_jacobians`'s
``chunk_size``)."""


def analysis_memory(
    volume_shape: tuple[int, int, int],
    n_views: int,
    radius: int,
    *,
    jpgm: JPGM | None = None,
    scene=None,
) -> int:
    """Peak memory of :func:`analyse` in bytes, a rough upper bound from the shapes; without
    ``jpgm`` (before it is built) a lower bound.

    With ``V = n_views`` views of ``Y x X`` pixels (``N = V Y X`` Jacobian rows), ``K`` Zernike
    terms (0 without ``jpgm``) and ``P = K + 4V`` columns: the Jacobians ``J_P``, ``J_G``
    (``N P`` float64) and one refit's Gauss-Newton copy of them; the forward-mode pass of
    :data:`TANGENTS` columns, the primal and its tangents of the JPGM
    (:meth:`~fgat.optics.psf.JPGM.memory_bytes`, without ``jpgm`` none) and of the float64
    operator on crops of half-width ``radius`` and its projection
    (:func:`fgat.recon.operator_memory`); the float64 volume. With ``scene`` (a
    :class:`~fgat.sim.simulation.SimulationConfig`) the scene is drawn first:
    :func:`fgat.sim.simulation.simulation_memory` (phantom, PSF stack, forward model, views),
    without
    ``jpgm`` its float32 phantom only.
    """
    voxels = int(np.prod(volume_shape))
    n_pupil = 0 if jpgm is None else len(jpgm.zernike_indices)
    rows = n_views * int(volume_shape[1]) * int(volume_shape[2])
    jacobians = 2 * rows * (n_pupil + 4 * n_views) * 8
    psf_shape = (n_views, int(volume_shape[0]), 2 * radius + 1, 2 * radius + 1)
    psf = 0 if jpgm is None else jpgm.memory_bytes()
    operator = operator_memory(psf_shape, volume_shape, itemsize=8, adjoint=False)
    drawn = 0
    if scene is not None:
        drawn = 4 * voxels if jpgm is None else simulation_memory(scene, jpgm, volume_shape)
    return int(jacobians + (1 + TANGENTS) * (psf + operator) + 8 * voxels + drawn)


def check_analysis_memory(
    volume_shape: tuple[int, int, int],
    n_views: int,
    radius: int,
    *,
    jpgm: JPGM | None = None,
    scene=None,
    device=None,
) -> None:
    """Refuse, before anything is allocated, an analysis whose :func:`analysis_memory` exceeds
    what ``device`` has (:func:`fgat._core.resources.check_memory`)."""
    check_memory(
        "the scene, Jacobians and refits of the cross-information of a "
        f"{tuple(int(n) for n in volume_shape)} (Z, Y, X) volume seen by {n_views} views",
        analysis_memory(volume_shape, n_views, radius, jpgm=jpgm, scene=scene),
        device=device,
        hint="fewer depths_um, a smaller view_size or crop_radius_px",
    )


def run_scene(
    folder: str | Path,
    system,
    *,
    centers_px: np.ndarray | None = None,
    method: str = "auto",
    tolerance: float = 1e-2,
    device=None,
):
    """The JPGM and volume of a static fit's results folder (``ReconstructionArtifacts``).

    The folder holds ``optics.yaml`` (``zernike/c{j}`` waves, ``shift/b{v}_y``, ... pixels, from
    a fit with JPGM self-estimation), ``psf.ome.tif`` (the estimated PSF stack ``(V, Z, h, w)``),
    ``volume.ome.tif`` (``(Z, Y, X)`` in counts, with its planes' depths) and, when the fit
    estimated them, ``gains.yaml``. The system and the lenslet centres are not recorded there and
    are given. The JPGM is rebuilt on them, on the volume's depths (in the file's plane order) and
    the PSF file's crop radius, and checked against ``psf.ome.tif``: a relative L2 difference
    above ``tolerance`` (another system, other centres) is refused.

    Parameters
    ----------
    folder : str or Path
        The results folder.
    system : FLFMSystem
        The system the fit used.
    centers_px : numpy.ndarray, optional
        ``(V, 2)`` the lenslet centres the fit used (row, col) pixels; default the system's
        nominal MLA (a phantom's).
    method : {"auto", "mft", "asm"}
        The rebuilt JPGM's intensity path.
    tolerance : float
        Largest accepted ``||rebuilt - psf.ome.tif|| / ||psf.ome.tif||`` (a wrong system or
        wrong centres differ by tens of percent).
    device : str or torch.device, optional
        Where the JPGM and the volume live (default the CPU).

    Returns
    -------
    (JPGM, Tensor, Operator or None)
        The float64 generator at the estimated optics, the volume ``(Z, Y, X)`` float64 and, with
        ``gains.yaml``, a :class:`~fgat.optics.acquisition.MeasuredOperator` factory with those
        gains (``None``: the plain :class:`~fgat.optics.operator.FLFMOperator`).
    """
    folder = Path(folder)
    files = {name: folder / name for name in ("optics.yaml", "psf.ome.tif", "volume.ome.tif")}
    missing = [name for name, path in files.items() if not path.is_file()]
    if missing:
        raise FileNotFoundError(
            f"--run {folder}: no {', '.join(missing)}; expected the results folder of a static "
            "fit with optics estimation (optics.yaml, psf.ome.tif, volume.ome.tif)"
        )
    optics = read_yaml(files["optics.yaml"], f"--run {files['optics.yaml']}")
    psf = read_tiff(files["psf.ome.tif"], ndim=4, axes="(V, Z, h, w)")
    volume = read_tiff(files["volume.ome.tif"], ndim=3, axes="(Z, Y, X)")
    depths = volume_metadata(files["volume.ome.tif"]).get("depths_um")
    if not depths or len(depths) != volume.shape[0] or psf.shape[1] != volume.shape[0]:
        raise ValueError(
            f"--run {folder}: volume.ome.tif records no depths for its {volume.shape[0]} planes, "
            f"or psf.ome.tif has {psf.shape[1]} (written by an older fgat?)"
        )
    if psf.shape[0] != system.n_lenslets:
        raise ValueError(
            f"--run {folder}: psf.ome.tif has {psf.shape[0]} views, system {system.name!r} "
            f"{system.n_lenslets} lenslets"
        )
    optics = optics if isinstance(optics, dict) else {}
    indices = sorted(int(key.split("/c")[1]) for key in optics if str(key).startswith("zernike/c"))
    if not indices:
        raise ValueError(
            f"--run {files['optics.yaml']}: expected zernike/c<j> (waves) and shift/<b|s><v>_<y|x> "
            "(pixels) entries, as a fit with optics estimation writes"
        )
    shifts = {
        kind: {
            v: [float(optics[names.shift_name(kind[0], v, axis)]) for axis in "yx"]
            for v in range(system.n_lenslets)
            if names.shift_name(kind[0], v, "y") in optics
        }
        for kind in ("b", "s")
    }
    jpgm = JPGM.with_parameters(
        system,
        depths,
        zernike={j: float(optics[names.zernike_name(j)]) for j in indices},
        intercepts=shifts["b"],
        slopes=shifts["s"],
        zernike_indices=indices,
        centers_px=centers_px,
        crop_radius_px=(psf.shape[-1] - 1) // 2,
        method=method,
        dtype=torch.float64,
        device=device,
    )
    with torch.no_grad():
        rebuilt = jpgm().cpu().numpy()
    difference = float(np.linalg.norm(rebuilt - psf) / max(np.linalg.norm(psf), 1e-30))
    if difference > tolerance:
        raise ValueError(
            f"--run {folder}: the PSF rebuilt from system {system.name!r} and optics.yaml differs "
            f"from psf.ome.tif by {difference:.2e} (relative L2, tolerance {tolerance:g}): another "
            "system, or other lenslet centres (a fit on measured data: give its --centers)"
        )
    operator = None
    if (folder / "gains.yaml").is_file():
        document = read_yaml(folder / "gains.yaml", f"--run {folder / 'gains.yaml'}")
        gains = document.get("gains") if isinstance(document, dict) else None
        if not isinstance(gains, list) or len(gains) != system.n_lenslets:
            raise ValueError(
                f"--run {folder / 'gains.yaml'}: expected 'gains: [...]' with "
                f"{system.n_lenslets} numbers"
            )
        operator = partial(
            MeasuredOperator,
            view_shape=tuple(volume.shape[1:]),
            gains=torch.tensor(gains, dtype=torch.float64, device=device),
        )
    volume = torch.from_numpy(np.ascontiguousarray(volume)).to(device=device, dtype=torch.float64)
    return jpgm, volume, operator


def predict(
    jpgm: JPGM,
    volume: Tensor,
    parameters: dict[str, Tensor] | None = None,
    operator: Operator | None = None,
) -> Tensor:
    """Predicted views ``(V, Y, X)`` of ``volume`` ``(Z, Y, X)`` through the JPGM with
    ``parameters`` (name -> tensor) in place of its own (Eq. S37); differentiable in them."""
    operator = operator or partial(FLFMOperator, volume_shape=tuple(volume.shape))
    return operator(functional_call(jpgm, parameters or {}, ())).forward(volume)


def pixel_grid_fraction(jpgm: JPGM, within: float = 0.01) -> float:
    """Fraction of the crop-centre coordinates ``c_v + b_v + s_v xi(z)`` (``(V, Z, 2)``, pixels)
    within ``within`` pixels of an integer. There the bilinear crops of Eq. S12 have a kink: the
    Jacobian ``J_G`` is one-sided, and the first-order analysis (Eqs. S38, S51) holds for shifts
    to one side only. Generic shifts put about ``2 within`` of the coordinates there; a fit's
    estimate can put most of them there (its loss may be lowest on the kinks)."""
    centers = jpgm.crop_centers().detach()
    return float(((centers - centers.round()).abs() <= within).double().mean())


# ---------------------------------------------------------------------------------- refit
@dataclass(frozen=True)
class Refit:
    """Result of :func:`refit`.

    Attributes
    ----------
    parameters : dict
        Name -> fitted tensor (the refitted ones only; waves or pixels).
    iterations : int
        Gauss-Newton steps taken.
    converged : bool
        Whether the last step fell below the tolerance, or no shorter step lowered the loss.
    loss : float
        Final ``0.5 ||y - data||^2``.
    """

    parameters: dict[str, Tensor]
    iterations: int
    converged: bool
    loss: float


def refit(
    jpgm: JPGM,
    volume: Tensor,
    data: Tensor,
    curvature: Tensor,
    *,
    names: Sequence[str] = PARAMETERS,
    overrides: dict[str, Tensor] | None = None,
    operator: Operator | None = None,
    max_iterations: int = 20,
    tolerance: float = 1e-2,
    halvings: int = 3,
) -> Refit:
    """Minimise ``0.5 ||y(Theta) - data||^2`` over the JPGM parameters ``names``.

    Starts from the JPGM's current values or their ``overrides``, and takes quasi-Newton steps
    ``-B^-1 g`` with the exact gradient ``g = J(Theta)^T (y(Theta) - data)`` (reverse mode),
    halving a step until the loss does not grow. ``B`` starts as ``curvature`` (the Gauss-Newton
    matrix at the analysed point: ``A`` for the Zernike terms alone, the block Hessian of
    Eq. S42 for a joint fit) and takes a BFGS update from the gradient change of every step,
    which corrects it where the loss's curvature at the minimum differs (the residual's
    second-order term). Stops when a step is below ``tolerance`` times the distance travelled
    from the start (plus 1e-12), or when ``halvings`` halvings of a step do not lower the loss:
    the minimum then lies within that step. (In the shifts the loss is only piecewise smooth:
    the bilinear crops of Eq. S12 have a kink where a crop centre crosses a pixel, and a joint
    refit's minimum often sits on one.)

    Parameters
    ----------
    jpgm : JPGM
        The generator; its parameters are not changed.
    volume : Tensor
        ``(Z, Y, X)`` the object, held fixed.
    data : Tensor
        ``(V, Y, X)`` the views to fit.
    curvature : Tensor
        ``(P, P)`` symmetric positive definite, ``P`` the number of refitted values in
        ``names`` order (each flattened).
    names : sequence of str
        Parameters to refit, a sub-sequence of :data:`PARAMETERS`.
    overrides : dict, optional
        Name -> value replacing the JPGM's: the start of a refitted parameter, the value of a
        held one (e.g. a perturbed geometry).
    operator : callable, optional
        As :func:`~fgat.optics.crossinfo.cross_information`.
    max_iterations : int
        Largest number of steps.
    tolerance : float
        Relative step size at which the fit counts as converged.
    halvings : int
        Step halvings tried before the loss is taken as minimal along the step.
    """
    point = {name: getattr(jpgm, name).detach() for name in PARAMETERS}
    point.update({k: value.detach().to(point[k]) for k, value in (overrides or {}).items()})
    sizes = [point[name].numel() for name in names]
    start = torch.cat([point[name].reshape(-1) for name in names])
    if curvature.shape != (start.numel(), start.numel()):
        raise ValueError(
            f"refit: curvature must be {start.numel()} x {start.numel()} for {list(names)}, got "
            f"{tuple(curvature.shape)}"
        )
    curvature = curvature.to(start)
    torch.linalg.cholesky(curvature)  # raises unless positive definite
    data = data.detach().to(start)

    def evaluate(theta: Tensor) -> tuple[float, Tensor]:
        theta = theta.detach().requires_grad_(True)
        parts = torch.split(theta, sizes)
        values = {**point, **{n: p.reshape(point[n].shape) for n, p in zip(names, parts)}}
        loss = 0.5 * (predict(jpgm, volume, values, operator) - data).square().sum()
        (gradient,) = torch.autograd.grad(loss, theta)
        return float(loss.detach()), gradient

    theta = start
    loss, gradient = evaluate(theta)
    converged, iterations = False, 0
    while iterations < max_iterations and not converged:
        iterations += 1
        step = -torch.linalg.solve(curvature, gradient)
        for _ in range(halvings + 1):
            trial_loss, trial_gradient = evaluate(theta + step)
            if trial_loss <= loss:
                break
            step = step / 2
        else:  # no lower loss along the step: the minimum lies within it
            converged = True
            break
        change = trial_gradient - gradient
        if float(change @ step) > 0:  # BFGS: the curvature met along the step
            seen = curvature @ step
            curvature = (
                curvature
                - torch.outer(seen, seen) / (step @ seen)
                + torch.outer(change, change) / (change @ step)
            )
        theta, loss, gradient = theta + step, trial_loss, trial_gradient
        converged = float(step.norm()) <= tolerance * float((theta - start).norm()) + 1e-12
    parts = torch.split(theta.detach(), sizes)
    fitted = {n: p.reshape(point[n].shape) for n, p in zip(names, parts)}
    return Refit(fitted, iterations, converged, loss)


def _refit_each(
    jpgm: JPGM,
    volume: Tensor,
    problems: Iterable[dict],
    *,
    callback: Callable[[int], None] | None = None,
    **options,
) -> list[Refit]:
    """:func:`refit` of every problem in turn, with the options all share.

    Parameters
    ----------
    jpgm, volume
        As :func:`refit`.
    problems : iterable of dict
        Per refit, the arguments that differ: ``data`` and ``curvature`` and, optionally,
        ``names`` and ``overrides``.
    callback : callable, optional
        ``callback(k)`` after refit ``k``.
    **options
        ``operator``, ``max_iterations``, ``tolerance``, ``halvings`` of :func:`refit`.
    """
    fits = []
    for k, problem in enumerate(problems):
        fits.append(refit(jpgm, volume, **problem, **options))
        if callback is not None:
            callback(k)
    return fits


def _predict_clean(jpgm: JPGM, volume: Tensor, operator: Operator | None = None) -> Tensor:
    """The noise-free views ``(V, Y, X)`` at the JPGM's own point, without gradients."""
    with torch.no_grad():
        return predict(jpgm, volume, operator=operator)


# ------------------------------------------------------------------------- modal profiles
def modal_table(info: CrossInformation, block: str = "b", top: int | None = None) -> Table:
    """Modal profile of the cross-information with the intercepts (``block="b"``, Table S2) or
    the slopes (``"s"``, Table S3), Eq. S48.

    Parameters
    ----------
    info : CrossInformation
        The cross-information at the analysed point.
    block : {"b", "s"}
        ``C_b`` or ``C_s`` (Eq. S47).
    top : int, optional
        Keep the ``top`` largest rows (default all ``K``).

    Returns
    -------
    Table
        Rows ``rank, noll, n, m, family, eta`` sorted by ``eta`` (dimensionless, squares summing
        to 1 over all ``K``) descending; summary ``||C_s||_F / ||C_b||_F``, ``eta_11``, the median
        ``eta`` and the rank of ``j = 11``.
    """
    if block not in ("b", "s"):
        raise ValueError(f"block must be 'b' or 's', got {block!r}")
    eta = (info.eta_b if block == "b" else info.eta_s).cpu().numpy()
    indices = list(info.zernike_indices)
    ratio = float(torch.linalg.matrix_norm(info.C_s) / torch.linalg.matrix_norm(info.C_b))
    summary = {"frobenius_ratio_s_over_b": ratio, f"median_eta_{block}": float(np.median(eta))}
    if SPHERICAL in indices:
        k = indices.index(SPHERICAL)
        summary[f"eta_{block}_11"] = float(eta[k])
        summary["rank_11"] = int((eta > eta[k]).sum()) + 1
    number, what = ("S2", "intercept") if block == "b" else ("S3", "slope")
    return Table(
        name=f"table{number}_{what}_profile",
        title=f"Table {number}. Zernike contributors to the aberration-{what} cross-information "
        f"block C_{block} (Eq. S48)" + ("" if top is None else f", top {top}"),
        columns=("rank", "noll", "n", "m", "family", f"eta_{block}"),
        rows=_ranked(indices, eta, f"eta_{block}", top),
        summary=summary,
    )


def profile_table(info: CrossInformation) -> Table:
    """Both modal profiles (Eq. S48) of every Noll index, in Noll order."""
    eta_b, eta_s = info.eta_b.tolist(), info.eta_s.tolist()
    return Table(
        name="modal_profiles",
        title="Modal profiles of C_b and C_s (Eq. S48), every Noll index",
        columns=("noll", "n", "m", "family", "eta_b", "eta_s"),
        rows=[
            {**_mode(j), "eta_b": b, "eta_s": s}
            for j, b, s in zip(info.zernike_indices, eta_b, eta_s)
        ],
    )


# ------------------------------------------------------------------------ shift injection
def shift_cases(
    n_views: int, shift_px: float = 0.3, random_scale: float = 2.0, seed: int = 0
) -> dict[str, Tensor]:
    """The three geometry perturbations of Table S4, each ``(4V,)`` float64 (intercepts then
    slopes, ``(V, 2)`` (row, col) each, pixels).

    ``dB_x``: ``shift_px`` on every view's column intercept (``intercepts[:, 1]``); ``dS_y``:
    ``shift_px`` on every view's row slope (``slopes[:, 0]``); ``random``: a standard normal
    draw (``seed``) scaled to ``random_scale`` times their norm ``shift_px sqrt(V)`` (the paper's
    1.587 = 2 x 0.7937 px for 7 views).
    """
    cases = {}
    for label, group, axis in (("dB_x", 0, 1), ("dS_y", 1, 0)):
        delta = torch.zeros(2, n_views, 2, dtype=torch.float64)
        delta[group, :, axis] = shift_px
        cases[f"{label} = {shift_px:g} px"] = delta.reshape(-1)
    generator = torch.Generator().manual_seed(seed)
    draw = torch.randn(4 * n_views, generator=generator, dtype=torch.float64)
    norm = random_scale * shift_px * math.sqrt(n_views)
    cases["random dTheta_G"] = draw * (norm / draw.norm())
    return cases


@dataclass(frozen=True)
class LeakageCase:
    """One shift-injection case: ``delta`` ``(4V,)`` pixels, the measured and predicted Zernike
    changes ``(K,)`` waves, and the refit's iterations and convergence."""

    label: str
    delta: Tensor
    measured: Tensor
    predicted: Tensor
    iterations: int
    converged: bool

    @property
    def ratio(self) -> float:
        """``||measured|| / ||predicted||``."""
        return float(self.measured.norm() / self.predicted.norm())

    @property
    def cosine(self) -> float:
        """Cosine of the angle between measured and predicted."""
        return float(
            self.measured @ self.predicted / (self.measured.norm() * self.predicted.norm())
        )


def leakage_test(
    jpgm: JPGM,
    volume: Tensor,
    info: CrossInformation,
    *,
    shift_px: float = 0.3,
    random_scale: float = 2.0,
    seed: int = 0,
    **options,
) -> list[LeakageCase]:
    """Direct shift-injection test of the leakage map (Note S5.3, Table S4).

    The data are the prediction at the JPGM's point (noise-free); for every case of
    :func:`shift_cases` the geometry is set to the point plus ``dTheta_G`` and the Zernike
    coefficients are refitted (:func:`refit` with curvature ``A``) from the point. Their change is
    compared with ``-A^-1 C dTheta_G`` (Eq. S51).

    Parameters
    ----------
    jpgm, volume : JPGM, Tensor
        The analysed point and the object ``(Z, Y, X)``.
    info : CrossInformation
        :func:`~fgat.optics.crossinfo.cross_information` at that point (``W = I``).
    shift_px, random_scale, seed
        As :func:`shift_cases`.
    **options
        ``operator``, ``max_iterations``, ``tolerance`` and ``callback`` (after case ``k``) of
        :func:`_refit_each`.
    """
    data = _predict_clean(jpgm, volume, options.get("operator"))
    true_pupil = jpgm.zernike_coefficients.detach()
    deltas = {
        label: delta.to(true_pupil)
        for label, delta in shift_cases(jpgm.n_views, shift_px, random_scale, seed).items()
    }
    shifts = [delta.reshape(2, jpgm.n_views, 2) for delta in deltas.values()]
    fits = _refit_each(
        jpgm,
        volume,
        (
            {
                "data": data,
                "curvature": info.A,
                "names": ("zernike_coefficients",),
                "overrides": {"intercepts": jpgm.intercepts + b, "slopes": jpgm.slopes + s},
            }
            for b, s in shifts
        ),
        **options,
    )
    return [
        LeakageCase(
            label,
            delta.cpu(),
            (fit.parameters["zernike_coefficients"] - true_pupil).cpu(),
            info.leakage(delta).cpu(),
            fit.iterations,
            fit.converged,
        )
        for (label, delta), fit in zip(deltas.items(), fits)
    ]


def leakage_table(cases: Sequence[LeakageCase]) -> Table:
    """Table S4: per case ``||dTheta_G||`` (pixels), measured and predicted ``||dTheta_P||``
    (waves), their ratio and cosine, and the refit's iterations."""
    rows = [
        {
            "case": case.label,
            "delta_geometry_norm_px": float(case.delta.norm()),
            "measured_norm_waves": float(case.measured.norm()),
            "predicted_norm_waves": float(case.predicted.norm()),
            "ratio": case.ratio,
            "cosine": case.cosine,
            "iterations": case.iterations,
            "converged": case.converged,
        }
        for case in cases
    ]
    ratios = [case.ratio for case in cases]
    return Table(
        name="tableS4_leakage",
        title="Table S4. Direct leakage test: Zernike change of a refit after a geometry "
        "perturbation, measured against -A^-1 C dTheta_G (Eq. S51)",
        columns=tuple(rows[0]),
        rows=rows,
        summary={
            "ratio_min": min(ratios),
            "ratio_max": max(ratios),
            "cosine_min": min(case.cosine for case in cases),
        },
    )


# ----------------------------------------------------------------------- repeatability
@dataclass(frozen=True)
class Repeatability:
    """Joint refits under noise (Note S5.4).

    Attributes
    ----------
    indices : tuple of int
        Noll index of each pupil coefficient.
    sigma : float
        Noise standard deviation, in the views' units.
    pupil : Tensor
        ``(R, K)`` change of the Zernike coefficients of each refit, waves.
    geometry : Tensor
        ``(R, 4V)`` change of the intercepts then slopes, pixels.
    predicted : dict
        :meth:`CrossInformation.standard_errors` ``(sigma, "joint")``: ``"zernike"`` ``(K,)``
        waves, ``"intercepts"``, ``"slopes"`` ``(V, 2)`` pixels.
    iterations : list of int
        Steps of each refit.
    converged : list of bool
        Convergence of each refit.
    """

    indices: tuple[int, ...]
    sigma: float
    pupil: Tensor
    geometry: Tensor
    predicted: dict[str, Tensor]
    iterations: list[int]
    converged: list[bool]

    @property
    def empirical_sd(self) -> np.ndarray:
        """``(K,)`` sample standard deviation (ddof 1) of each Zernike coefficient, waves."""
        return self.pupil.std(dim=0).cpu().numpy()

    @property
    def predicted_sd(self) -> np.ndarray:
        """``(K,)`` ``sigma sqrt(diag(S_P^-1))`` (Eq. S49), waves."""
        return self.predicted["zernike"].cpu().numpy()

    def norms(self) -> dict[str, float]:
        """Mean and s.d. of ``||dTheta_P||`` (waves) and ``||dTheta_G||`` (pixels) over the
        refits, and their predicted root-mean-square ``sigma sqrt(tr S^-1)``."""
        pupil, geometry = self.pupil.norm(dim=1), self.geometry.norm(dim=1)
        shifts = torch.cat([self.predicted[name].reshape(-1) for name in GEOMETRY])
        return {
            "pupil_norm_mean_waves": float(pupil.mean()),
            "pupil_norm_sd_waves": float(pupil.std()),
            "pupil_norm_predicted_rms_waves": float(self.predicted["zernike"].norm()),
            "geometry_norm_mean_px": float(geometry.mean()),
            "geometry_norm_sd_px": float(geometry.std()),
            "geometry_norm_predicted_rms_px": float(shifts.norm()),
        }

    def table(self, top: int | None = 5) -> Table:
        """Table S5: the ``top`` coefficients with the largest empirical s.d. beside the
        predicted s.d.; summary: the norms, ``j = 11`` against the median s.d."""
        empirical, predicted = self.empirical_sd, self.predicted_sd
        rows = _ranked(self.indices, empirical, "empirical_sd_waves", top)
        for row in rows:
            row["predicted_sd_waves"] = float(predicted[self.indices.index(row["noll"])])
        summary = {
            "refits": len(self.iterations),
            "noise_sigma": self.sigma,
            **self.norms(),
            "median_empirical_sd_waves": float(np.median(empirical)),
        }
        if SPHERICAL in self.indices:
            k = self.indices.index(SPHERICAL)
            summary["empirical_sd_11_waves"] = float(empirical[k])
            summary["predicted_sd_11_waves"] = float(predicted[k])
            summary["rank_11"] = int((empirical > empirical[k]).sum()) + 1
        summary["refits_converged"] = int(sum(self.converged))
        summary["refit_iterations_max"] = max(self.iterations)
        return Table(
            name="tableS5_repeatability",
            title=f"Table S5. Zernike coefficients with the largest empirical variability over "
            f"{len(self.iterations)} noisy joint refits, with the inverse-Hessian prediction",
            columns=(
                "rank",
                "noll",
                "n",
                "m",
                "family",
                "empirical_sd_waves",
                "predicted_sd_waves",
            ),
            rows=rows,
            summary=summary,
        )

    def coefficient_table(self) -> Table:
        """Empirical and predicted s.d. of every coefficient, in Noll order."""
        empirical, predicted = self.empirical_sd, self.predicted_sd
        mean = self.pupil.mean(dim=0).tolist()
        return Table(
            name="repeatability_coefficients",
            title="Noisy joint refits: every Zernike coefficient (waves)",
            columns=("noll", "n", "m", "family", "mean_change", "empirical_sd", "predicted_sd"),
            rows=[
                {
                    **_mode(j),
                    "mean_change": mean[k],
                    "empirical_sd": float(empirical[k]),
                    "predicted_sd": float(predicted[k]),
                }
                for k, j in enumerate(self.indices)
            ],
        )


def repeatability(
    jpgm: JPGM,
    volume: Tensor,
    info: CrossInformation,
    *,
    refits: int = 30,
    noise_fraction: float = 0.01,
    seed: int = 0,
    **options,
) -> Repeatability:
    """Joint refits of ``(Theta_P, Theta_G)`` under additive Gaussian noise (Note S5.4, Table S5).

    Each refit fits the clean prediction at the JPGM's point plus white Gaussian noise of
    standard deviation ``sigma = noise_fraction x`` the peak of the clean views (seeded), starting
    from the point, by :func:`refit` with the block Hessian of Eq. S42. The empirical spread is
    set beside ``sigma sqrt(diag(S_P^-1))`` and ``sigma sqrt(diag(S_G^-1))`` (Eqs. S49-S50).

    Parameters
    ----------
    jpgm, volume, info
        As :func:`leakage_test`.
    refits : int
        Number of noise draws ``R`` (at least 2).
    noise_fraction : float
        Noise s.d. as a fraction of the clean views' peak.
    seed : int
        Seed of the noise.
    **options
        ``operator``, ``max_iterations``, ``tolerance`` and ``callback`` (after refit ``k``) of
        :func:`_refit_each`.
    """
    refits = check_number("refits", refits, integer=True, minimum=2)
    noise_fraction = check_number("noise_fraction", noise_fraction, above=0)
    clean = _predict_clean(jpgm, volume, options.get("operator"))
    sigma = noise_fraction * float(clean.max())
    start = torch.cat([getattr(jpgm, name).detach().reshape(-1) for name in PARAMETERS])
    generator = torch.Generator().manual_seed(seed)
    noisy = (  # drawn one refit at a time, in order
        clean + torch.randn(clean.shape, generator=generator, dtype=clean.dtype).to(clean) * sigma
        for _ in range(refits)
    )
    fits = _refit_each(
        jpgm, volume, ({"data": data, "curvature": info.hessian} for data in noisy), **options
    )
    changes = torch.stack(
        [
            torch.cat([fit.parameters[name].reshape(-1) for name in PARAMETERS]) - start
            for fit in fits
        ]
    ).cpu()
    n_pupil = len(jpgm.zernike_indices)
    return Repeatability(
        indices=tuple(jpgm.zernike_indices),
        sigma=sigma,
        pupil=changes[:, :n_pupil],
        geometry=changes[:, n_pupil:],
        predicted={k: v.cpu() for k, v in info.standard_errors(sigma, "joint").items()},
        iterations=[fit.iterations for fit in fits],
        converged=[fit.converged for fit in fits],
    )


# --------------------------------------------------------------------- configuration
def _number(default: float | None, **bounds):
    """A dataclass field holding a number within ``bounds`` (of
    :func:`fgat._core.validation.check_number`), checked by :func:`_check_numbers`; a ``None``
    default makes the field optional."""
    return field(default=default, metadata={"bounds": bounds})


def _check_numbers(config) -> None:
    """Check and convert (``"0.5"`` -> 0.5, ``3.0`` -> 3 for integers) every field of the
    frozen dataclass ``config`` declared with :func:`_number`, in field order; ``ValueError``
    names the first field out of its bounds. An optional field may be ``None``."""
    for item in fields(config):
        value = getattr(config, item.name)
        if "bounds" in item.metadata and not (value is None and item.default is None):
            number = check_number(item.name, value, **item.metadata["bounds"])
            object.__setattr__(config, item.name, number)


@dataclass(frozen=True)
class CrossInfoConfig:
    """The settings of ``python -m fgat analyze crossinfo`` (a YAML file of these fields).

    Attributes
    ----------
    scene : dict
        The scene as :class:`~fgat.sim.simulation.SimulationConfig` fields (:data:`SCENE_FIELDS`):
        ``system``, ``depths_um``, ``view_size``, ``phantom`` (seeded beads), the optics point
        ``zernike`` / ``intercepts`` / ``slopes`` and the seeded random ``aberrations``, ``seed``.
        With ``--run`` only ``system`` is used (the fit's system).
    crop_radius_px : int or None
        PSF crop half-width ``r`` (default the system's).
    method : {"auto", "mft", "asm"}
        The JPGM's intensity path.
    shift_px : float
        Table S4's injected ``dB_x`` and ``dS_y``, pixels (pixels per unit ``xi``).
    random_scale : float
        The random ``dTheta_G``'s norm in units of the first case's (:func:`shift_cases`).
    noise_fraction : float
        Table S5's noise s.d. as a fraction of the clean views' peak.
    refits : int
        Number of noisy refits (at least 2).
    seed : int
        Seed of the random ``dTheta_G`` and of the noise (the scene has its own).
    top : int
        Rows of the top-N tables.
    max_iterations : int
        Largest number of Gauss-Newton steps per refit.
    tolerance : float
        A refit stops when its step is below this fraction of its distance from the start.
    """

    scene: dict = field(default_factory=dict)
    crop_radius_px: int | None = _number(None, integer=True, minimum=1)
    method: str = "auto"
    shift_px: float = _number(0.3, above=0)
    random_scale: float = _number(2.0, above=0)
    noise_fraction: float = _number(0.01, above=0)
    refits: int = _number(30, integer=True, minimum=2)
    seed: int = _number(0, integer=True, minimum=0)
    top: int = _number(5, integer=True, minimum=1)
    max_iterations: int = _number(20, integer=True, minimum=1)
    tolerance: float = _number(1e-2, above=0)

    def __post_init__(self) -> None:
        require(
            isinstance(self.scene, dict), "scene", self.scene, f"a mapping of {list(SCENE_FIELDS)}"
        )
        unknown = sorted(set(self.scene) - set(SCENE_FIELDS))
        if unknown:
            raise ValueError(
                f"scene: unknown field(s) {unknown}; expected some of {list(SCENE_FIELDS)}"
            )
        require(self.method in METHODS, "method", self.method, f"one of {list(METHODS)}")
        _check_numbers(self)

    @classmethod
    def from_yaml(cls, path: str | Path) -> CrossInfoConfig:
        """Read a config file; errors name the file and the field (the scene's fields are
        checked as a :class:`~fgat.sim.simulation.SimulationConfig`)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"--config {path} does not exist")
        values = yaml_fields(read_text(path, f"--config {path}"), f"--config {path}", cls)
        if not values:
            raise ValueError(
                f"--config {path}: the file sets no field; expected a mapping of the analysis' "
                f"fields ({', '.join(f.name for f in fields(cls))}; see configs/crossinfo.yaml)"
            )
        try:
            config = cls(**values)
            config.simulation().validate()
        except ValueError as error:
            raise ValueError(f"--config {path}: {error}") from None
        return config

    def simulation(self):
        """The scene as a :class:`~fgat.sim.simulation.SimulationConfig` (noise-free)."""
        return SimulationConfig(**self.scene, photons=None)


# -------------------------------------------------------------------------- the report
@dataclass(frozen=True)
class CrossInfoReport:
    """The three experiments at one point (:func:`analyse`).

    Attributes
    ----------
    info : CrossInformation
        The cross-information at the point (``W = I``).
    leakage : list of LeakageCase
        Table S4's cases.
    repeatability : Repeatability
        Table S5's refits.
    on_pixel_grid : float
        :func:`pixel_grid_fraction` of the analysed point.
    top : int
        Rows of the top-N tables.
    seconds : dict
        Wall-clock time of each experiment.
    """

    info: CrossInformation
    leakage: list[LeakageCase]
    repeatability: Repeatability
    on_pixel_grid: float = 0.0
    top: int = 5
    seconds: dict = field(default_factory=dict)

    def tables(self) -> list[Table]:
        """Tables S2-S5 (top ``top`` rows), the full modal profiles and the per-coefficient
        repeatability."""
        return [
            modal_table(self.info, "b", self.top),
            modal_table(self.info, "s", self.top),
            profile_table(self.info),
            leakage_table(self.leakage),
            self.repeatability.table(self.top),
            self.repeatability.coefficient_table(),
        ]

    def summary(self) -> dict:
        """The scalar findings of every table (nested by experiment), for ``summary.json``."""
        intercept, slope, _, leakage, noisy, _ = self.tables()
        return {
            "intercept_profile": intercept.summary,
            "slope_profile": slope.summary,
            "leakage": {"cases": leakage.rows, **leakage.summary},
            "repeatability": {
                **noisy.summary,
                "median_predicted_sd_waves": float(np.median(self.repeatability.predicted_sd)),
            },
            "crop_coordinates_on_pixel_grid": self.on_pixel_grid,
            "seconds": self.seconds,
        }


SHARED_SETTINGS = ("seed", "max_iterations", "tolerance")
"""The :class:`CrossInfoConfig` fields both refit experiments take (the others: their own)."""


def analyse(
    jpgm: JPGM,
    volume: Tensor,
    config: CrossInfoConfig,
    *,
    operator: Operator | None = None,
    callback: Callable[[str, int], None] | None = None,
) -> CrossInfoReport:
    """Run the experiments of Note S5 at the JPGM's point: the cross-information (one Jacobian),
    the leakage test and the noisy refits.

    Parameters
    ----------
    jpgm, volume
        The analysed point (float64) and the object ``(Z, Y, X)`` (:func:`analysis_scene` or
        :func:`run_scene`).
    config : CrossInfoConfig
        The experiments' settings.
    operator : callable, optional
        As :func:`~fgat.optics.crossinfo.cross_information`.
    callback : callable, optional
        ``callback(stage, k)`` after each step: ``("jacobian", 0)``, ``("leakage", k)``,
        ``("refit", k)``.
    """
    notify = callback or (lambda stage, k: None)
    seconds = {}
    start = time.perf_counter()
    info = cross_information(jpgm, volume, operator=operator)
    seconds["cross_information"] = time.perf_counter() - start
    notify("jacobian", 0)
    results = {}
    for name, experiment, stage, own in (
        ("leakage", leakage_test, "leakage", ("shift_px", "random_scale")),
        ("repeatability", repeatability, "refit", ("refits", "noise_fraction")),
    ):
        settings = {key: getattr(config, key) for key in (*own, *SHARED_SETTINGS)}
        start = time.perf_counter()
        results[name] = experiment(
            jpgm, volume, info, operator=operator, callback=partial(notify, stage), **settings
        )
        seconds[name] = time.perf_counter() - start
    cases, noisy = results["leakage"], results["repeatability"]
    return CrossInfoReport(info, cases, noisy, pixel_grid_fraction(jpgm), config.top, seconds)


REPORT_FILES = (
    *(
        f"{name}.{ext}"
        for name in (
            "tableS2_intercept_profile",
            "tableS3_slope_profile",
            "modal_profiles",
            "tableS4_leakage",
            "tableS5_repeatability",
            "repeatability_coefficients",
        )
        for ext in ("csv", "md")
    ),
    "eta_profiles.png",
    "cross_information.png",
    "leakage.png",
    "summary.json",
    "summary.md",
    "config.yaml",
)
"""The files :func:`write_report` writes."""


def check_report_folder(folder: str | Path, *, overwrite: bool = False) -> Path:
    """Check, before any computation, that a report can be written to ``folder`` (``--out``).

    Refused: a file; a non-empty folder unless ``overwrite`` (which replaces only
    :data:`REPORT_FILES`); a folder that cannot be created or written in.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--out {folder}: exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise ValueError(f"--out {folder}: not empty; choose another folder or pass --overwrite")
    existing = folder.resolve()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"--out {folder}: cannot create it, {existing} is a file")
    check_writable_folder(existing, f"--out {folder}")
    if folder.is_dir():
        for name in REPORT_FILES:
            check_output_file(folder / name, overwrite=True, option="--out")
    return folder


def write_report(
    report: CrossInfoReport,
    folder: str | Path,
    config: CrossInfoConfig,
    *,
    title: str = "",
    extra: dict | None = None,
) -> list[Path]:
    """Write :data:`REPORT_FILES` into ``folder`` (created): every table as CSV and markdown,
    the figures (``eta_profiles.png``, ``cross_information.png``, ``leakage.png``),
    ``summary.json`` (``extra``, then :meth:`CrossInfoReport.summary`), ``summary.md`` (all
    tables) and ``config.yaml`` (``config``'s fields)."""
    import yaml  # loaded when a file is read or written: keeps start-up fast

    tables = report.tables()
    info, indices = report.info, list(report.info.zernike_indices)
    label = f"{title}: " if title else ""
    heading = f"# {title or 'Cross-information'} (Note S5)\n\n"
    writers = {name: write for table in tables for name, write in table_writers(table).items()}
    writers["eta_profiles.png"] = partial(
        plot_eta_profiles,
        indices,
        {
            "intercepts (eta^b)": info.eta_b.cpu().numpy(),
            "slopes (eta^s)": info.eta_s.cpu().numpy(),
        },
        title=f"{label}modal profiles of C_b and C_s (Eq. S48)",
    )
    writers["cross_information.png"] = partial(
        plot_cross_information,
        info.C.cpu().numpy(),
        indices,
        info.n_views,
        title=f"{label}cross-information C = J_P^T J_G (Eq. S43)",
    )
    writers["leakage.png"] = partial(
        plot_leakage,
        indices,
        {case.label: (case.measured.numpy(), case.predicted.numpy()) for case in report.leakage},
        title=f"{label}Zernike leakage: refit against -A^-1 C dTheta_G (Eq. S51)",
    )
    writers["summary.json"] = partial(write_json, data={**(extra or {}), **report.summary()})
    writers["summary.md"] = partial(
        _write_text, text=heading + "\n".join(table.markdown() for table in tables)
    )
    writers["config.yaml"] = partial(
        _write_text, text=yaml.safe_dump(asdict(config), sort_keys=False)
    )
    return write_outputs(folder, writers)
