"""The high-NA evidence: a hollow microsphere with beads, seen through 37 hexagonal lenslets of
a 60x/1.3 silicone objective imaging into water (configs/simulate/highna_shell.yaml), scored
for what goes wrong silently on such data: an empty volume, a frame of light in the border
voxels, a wrong depth scale (a round shell reconstructed squashed or stretched along z).

``python reproduce/highna_shell.py systems OUT`` writes two wrong variants of the recipe's
system: ``OUT/wrong_pitch.yaml``, its MLA pitch (and lenslet width) given in the wrong
convention, the hexagon's corner-to-corner width, ``2 / sqrt(3)`` times the centre-to-centre
pitch, which ``fgat calibrate`` must refuse; and ``OUT/immersion_depths.yaml``, without its
``sample_index`` (depths taken in the immersion oil, not in the water of the sample: the depth
scale a user gets who leaves it out). ``python reproduce/highna_shell.py summary OUT`` scores every
volume of the recipe and the truth in ``OUT/sim``: PSNR and SSIM (max-normalised,
:func:`fgat.recon.metrics.compare_volumes`), PSNR after registering the scene's translation
(:func:`fgat.recon.metrics.registered_psnr`: the optics estimate's lenslet shifts fix the scene only
up to one, so 4DGAT is comparable only so), the border frame
(:func:`fgat.recon.metrics.border_ratio`, 1 = none), whether the volume is empty, and the shell's
axial/lateral aspect (:func:`fgat.recon.metrics.axial_lateral_aspect`, the truth's is 1), printing a
table and writing ``OUT/summary.json``. ``reproduce/highna_shell.sh`` runs the whole recipe.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import yaml

from fgat.io.files import atomic_path
from fgat.io.images import read_tiff, read_voxel_size
from fgat.optics.systems import load_system
from fgat.recon.metrics import axial_lateral_aspect, border_ratio, compare_volumes, registered_psnr

# Volume file of each reconstruction (relative to OUT) and its label.
VOLUMES = {
    "sim/truth.ome.tif": "truth",
    "shb.ome.tif": "SHB",
    "shb_immersion_depths.ome.tif": "SHB, sample index unset",
    "fit_3dgat/results/*/volume.ome.tif": "3DGAT (optics fixed)",
    "fit_4dgat/results/*/volume.ome.tif": "4DGAT (optics estimated)",
}
# Outcome of the recipe's wrong-convention calibration ("refused" or "accepted"), written by
# reproduce/highna_shell.sh.
WRONG_PITCH_OUTCOME = "wrong_pitch.txt"


def wrong_pitch_system(system: str | Path) -> dict:
    """The fields of a system YAML that is ``system`` with its MLA pitch and lenslet width
    multiplied by ``2 / sqrt(3)``: a hexagon's corner-to-corner width given for its
    flat-to-flat one (the centre-to-centre pitch of a hexagonal array)."""
    nominal = load_system(system)
    factor = 2 / math.sqrt(3)
    return {
        "base": str(Path(system).resolve()),
        "name": f"{nominal.name} (pitch given corner to corner)",
        "mla_pitch_mm": nominal.mla_pitch_mm * factor,
        "lenslet_aperture_mm": nominal.lenslet_aperture_mm * factor,
    }


def immersion_depths_system(system: str | Path) -> dict:
    """The fields of a system YAML that is ``system`` without its ``sample_index``: the PSF's
    depths in the immersion medium."""
    return {
        "base": str(Path(system).resolve()),
        "name": f"{load_system(system).name} (depths in the immersion medium)",
        "sample_index": None,
    }


def is_empty(volume: np.ndarray) -> bool:
    """True for a volume with no light: no finite positive voxel."""
    finite = volume[np.isfinite(volume)]
    return not (finite.size and finite.max() > 0)


def volume_row(volume: np.ndarray, truth: np.ndarray, voxel_size_um) -> dict[str, float]:
    """The scores of one volume ``(Z, Y, X)`` against the truth: ``psnr``, ``ssim``,
    ``psnr_registered`` (dB; NaN where the registration fails), ``border_ratio``, ``empty``,
    ``aspect`` and the shell's ``sigma_z_um`` and lateral ``sigma_xy_um``."""
    empty = is_empty(volume)
    scores = compare_volumes(volume, truth)
    shape = axial_lateral_aspect(volume, voxel_size_um)
    return {
        "psnr": scores["psnr"],
        "ssim": scores["ssim"],
        "psnr_registered": math.nan if empty else registered_psnr(volume, truth, None)[0],
        "border_ratio": border_ratio(volume, truth),
        "empty": empty,
        "aspect": shape["aspect"],
        "sigma_z_um": shape["sigma_z_um"],
        "sigma_xy_um": math.hypot(shape["sigma_y_um"], shape["sigma_x_um"]) / math.sqrt(2),
    }


def volume_scores(out: Path) -> dict[str, dict[str, float]]:
    """:func:`volume_row` of every volume of the recipe that exists (the newest run's), the
    truth included (its aspect is the reference)."""
    truth = read_tiff(out / "sim" / "truth.ome.tif")
    scores = {}
    for pattern, label in VOLUMES.items():
        found = sorted(out.glob(pattern), key=lambda path: path.stat().st_mtime)
        if found:
            sizes = read_voxel_size(found[-1])
            scores[label] = volume_row(read_tiff(found[-1]), truth, [sizes[a] for a in "ZYX"])
    return scores


def summary(out: Path) -> dict:
    """The recipe's scores (:func:`volume_scores`) and the wrong-convention calibration's
    outcome (``None`` where not run)."""
    outcome = out / WRONG_PITCH_OUTCOME
    return {
        "volumes": volume_scores(out),
        "wrong_pitch": outcome.read_text().strip() if outcome.is_file() else None,
    }


def table(result: dict) -> str:
    """The summary as a text table."""
    header = (
        f"{'volume':26s} {'PSNR dB':>8s} {'SSIM':>7s} {'reg. dB':>8s} {'border':>7s} "
        f"{'empty':>5s} {'aspect':>7s} {'sz um':>6s} {'sxy um':>6s}"
    )
    lines = [header]
    for label, row in result["volumes"].items():
        lines.append(
            f"{label:26s} {row['psnr']:8.2f} {row['ssim']:7.4f} {row['psnr_registered']:8.2f} "
            f"{row['border_ratio']:7.3f} {'yes' if row['empty'] else 'no':>5s} "
            f"{row['aspect']:7.3f} {row['sigma_z_um']:6.2f} {row['sigma_xy_um']:6.2f}"
        )
    if result["wrong_pitch"] is not None:
        lines.append(f"calibrate with the pitch given corner to corner: {result['wrong_pitch']}")
    return "\n".join(lines)


def main(system: str | Path, argv: list[str] | None = None) -> None:
    """The command line ``systems OUT`` or ``summary OUT`` (module docstring).

    Parameters
    ----------
    system : str or Path
        The recipe's system YAML (``reproduce/systems/highna37.yaml``), the nominal system of
        the wrong variants.
    argv : list of str, optional
        The arguments (default: the command line's).
    """
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("systems", "summary"))
    parser.add_argument("out", type=Path, help="the recipe's folder (runs/highna_shell)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.action == "systems":
        files = {
            "wrong_pitch.yaml": yaml.safe_dump(wrong_pitch_system(system)),
            "immersion_depths.yaml": yaml.safe_dump(immersion_depths_system(system)),
        }
    else:
        result = summary(args.out)
        print(table(result))
        files = {"summary.json": json.dumps(result, indent=2)}
    for name, text in files.items():
        with atomic_path(args.out / name) as temporary:
            temporary.write_text(text)
        print(f"-> {args.out / name}")
