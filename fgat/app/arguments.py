"""Argument types and option groups the command families share: depth lists, Zernike
and shift tables, checked numbers, output folders, devices and measured lenslet centres.
"""

from __future__ import annotations

import argparse


def parse_depths(text: str) -> list[float]:
    """``"-30,-15,0,15,30"`` or ``"start:stop:count"`` (inclusive, evenly spaced) in um,
    distinct."""
    from fgat.optics.systems import parse_depths

    try:
        depths = parse_depths(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(
            f"{error}; expected comma-separated micrometres (-30,0,30) or start:stop:count"
        ) from None
    if not depths:
        raise argparse.ArgumentTypeError(
            f"depths {text!r}: expected comma-separated micrometres (-30,0,30) or start:stop:count"
        )
    return depths


def parse_pairs(text: str, example: str) -> list[tuple[int, str]]:
    """``"K=V,K=V"`` as ``[(int(K), V)]``; a key given twice is refused."""
    pairs = []
    for item in (i for i in text.split(",") if i.strip()):
        key, value = item.split("=")
        pairs.append((int(key), value))
    keys = [key for key, _ in pairs]
    repeated = sorted({key for key in keys if keys.count(key) > 1})
    if repeated:
        raise argparse.ArgumentTypeError(
            f"{text!r}: {repeated[0]} is given more than once (e.g. {example})"
        )
    return pairs


def parse_zernike(text: str) -> dict[int, float]:
    """``"5=0.3,8=-0.2"``: Noll index = coefficient in waves."""
    try:
        return {j: float(c) for j, c in parse_pairs(text, "5=0.3,8=-0.2")}
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"zernike {text!r}: expected NOLL=WAVES pairs separated by commas, e.g. 5=0.3,8=-0.2"
        ) from None


def parse_shifts(text: str) -> dict[int, tuple[float, float]]:
    """``"1=0.5:-0.3,4=1:0"``: view = row:col in pixels."""
    try:
        result = {}
        for view, value in parse_pairs(text, "1=0.5:-0.3,4=1:0"):
            row, col = value.split(":")
            result[view] = (float(row), float(col))
        return result
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"shifts {text!r}: expected VIEW=ROW:COL pairs separated by commas, e.g. 1=0.5:-0.3"
        ) from None


def number_type(**bounds):
    """An argparse ``type`` reading a number checked by :func:`fgat._core.validation.check_number`
    (``bounds``)."""
    from fgat._core.validation import check_number

    def parse(text: str):
        try:
            return check_number("value", text, **bounds)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error).replace("value must", "must", 1)) from None

    return parse


def add_output_folder(
    parser,
    overwrite_help: str,
    *,
    out_help: str = "output folder (must be empty unless --overwrite)",
) -> None:
    """The ``--out`` folder (required) and ``--overwrite`` (its help ``overwrite_help``)."""
    parser.add_argument("--out", required=True, help=out_help)
    parser.add_argument("--overwrite", action="store_true", help=overwrite_help)


def add_device(parser) -> None:
    """``--device`` (default ``auto``), read by :func:`fgat._core.devices.resolve_device`."""
    parser.add_argument(
        "--device", default="auto", help="auto (CUDA when present), cpu, cuda, cuda:N or mps"
    )


def measured_centers(path: str, system):
    """Lenslet centres ``(V, 2)`` from a centres file or a calibration folder, checked against
    the system's lenslet count, and the system with the calibration's depth scale
    (:func:`fgat.optics.depth_scale.calibrated_system`; unchanged for a centres file)."""
    from pathlib import Path

    from fgat.instrument.calibration import read_calibration
    from fgat.instrument.centres import read_centers
    from fgat.optics.depth_scale import calibrated_system

    if Path(path).is_dir():
        calibration = read_calibration(path)
        centers, system = calibration.centers, calibrated_system(system, calibration)
    else:
        centers = read_centers(path)
    if len(centers) != system.n_lenslets:
        raise ValueError(
            f"{path}: {len(centers)} lenslet centres, but system {system.name!r} has "
            f"{system.n_lenslets} lenslets (n_lenslets)"
        )
    return centers, system
