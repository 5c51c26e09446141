"""``python -m fgat analyze fwhm|cytometry|track``: tubule widths, volumetric cytometry and cell
tracking on images, volumes and series written by fgat (Notes S8.2, S8.7-S8.9).

Every command reads OME-TIFF files whose voxel sizes (um) are in the OME metadata (as fgat writes
them; ``--voxel-size-um DZ DY DX`` stands in for files without them), checks the inputs'
dimensionality, voxel sizes, every length option against the voxel size and the volume's extent
(:func:`fgat.analysis.scales.check_length_um`) and the output files before the analysis, and
writes tables as CSV and figures as PNG into ``--out``, created only when they are written and
removed with them when a write fails (:func:`fgat.analysis.outputs.write_outputs`).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from functools import partial
from pathlib import Path

from fgat.app.arguments import add_output_folder, number_type

FWHM_FILES = ("widths.csv", "widths.png")
CYTOMETRY_FILES = ("cells.csv", "counts.csv", "summary.json", "montage.png", "fractions.png")
TRACK_FILES = (
    "trajectories.csv",
    "speeds.csv",
    "msd.csv",
    "summary.json",
    "speeds.png",
    "msd.png",
    "trajectories.png",
)
DEFAULT_THRESHOLD = 0.2
"""Relative blob-detection threshold of a channel not given one (``detect_blobs``)."""


def add_analyses(analyses) -> None:
    """Add ``fwhm``, ``cytometry`` and ``track`` to the subparsers of ``fgat analyze``."""
    _add_fwhm(analyses)
    _add_cytometry(analyses)
    _add_track(analyses)


# ------------------------------------------------------------------------------ shared pieces


def _add_common(parser, files: tuple[str, ...], voxel_note: str = "") -> None:
    """``--voxel-size-um`` (its help ending with ``voxel_note``), ``--out`` and ``--overwrite``
    (which replaces ``files``)."""
    parser.add_argument(
        "--voxel-size-um",
        nargs=3,
        type=number_type(above=0),
        metavar=("DZ", "DY", "DX"),
        help="voxel size in um for input files whose OME metadata lacks it (PhysicalSizeZ/Y/X; "
        f"given, it replaces the metadata's{voxel_note})",
    )
    add_output_folder(
        parser,
        f"replace existing {', '.join(files)} in OUT",
        out_help=f"output folder (created; holds {', '.join(files)})",
    )


def _named(convert, example: str):
    """An argparse ``type`` reading ``NAME=VALUE`` as ``(NAME, convert(VALUE))``."""

    def parse(text: str):
        name, equals, value = text.partition("=")
        if not equals or not name:
            raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=VALUE, e.g. {example}")
        try:
            return name, convert(value)
        except (ValueError, argparse.ArgumentTypeError) as error:
            raise argparse.ArgumentTypeError(f"{text!r}: {error}") from None

    return parse


def _mapping(pairs, option: str) -> dict:
    """``[(name, value)]`` of a repeated ``NAME=VALUE`` option as a dict; a repeated name is
    refused."""
    result = {}
    for name, value in pairs or ():
        if name in result:
            raise ValueError(f"{option}: {name!r} is given more than once")
        result[name] = value
    return result


def _input_shape(path, source: str, ndims: tuple[int, ...], expected: str) -> tuple[int, ...]:
    """Shape of the TIFF ``path`` from its header; ``ValueError`` naming ``source`` (the option
    and file) unless it has one of ``ndims`` dimensions (``expected`` in words)."""
    from fgat.io.images import tiff_shape  # imported when used: keeps start-up fast

    shape, _ = tiff_shape(path)
    if len(shape) not in ndims:
        raise ValueError(f"{source}: expected {expected}, got {len(shape)}-D data of shape {shape}")
    return shape


def _voxel_size_um(path, source: str, override, axes: str = "ZYX") -> tuple[float, ...]:
    """Voxel size (um) along ``axes`` of ``path``: ``--voxel-size-um`` (``override``, its last
    ``len(axes)`` values) when given, else the file's OME ``PhysicalSize`` entries; errors name
    ``source`` (the option and file); every stored size must be a finite number > 0."""
    from fgat._core.validation import check_number  # imported when used: keeps start-up fast
    from fgat.io.images import read_voxel_size  # imported when used: keeps start-up fast

    if override is not None:
        return tuple(override[-len(axes) :])
    stored = read_voxel_size(path)
    missing = [axis for axis in axes if axis not in stored]
    if missing:
        raise ValueError(
            f"{source}: no voxel size along {', '.join(missing)} in its OME metadata "
            f"(PhysicalSize{'/'.join(missing)}, um); expected a file written by fgat "
            "(fgat.io.images.write_tiff(..., voxel_size_um=...)), or give the sizes with "
            "--voxel-size-um DZ DY DX"
        )
    return tuple(
        check_number(f"{source}: PhysicalSize{axis} (um)", stored[axis], above=0) for axis in axes
    )


def _output_folder(out, names: tuple[str, ...], overwrite: bool) -> Path:
    """``--out``, checked (not created) so that every one of ``names`` can be written (an
    existing file only with ``overwrite``): :func:`fgat.analysis.outputs.check_output_folder`."""
    from fgat.analysis.outputs import check_output_folder  # imported when used: keeps start-up fast

    return check_output_folder(out, names, overwrite=overwrite, option="--out")


def _check_lengths(lengths: dict, voxel, shape, source: str) -> dict:
    """Every ``--*-um`` length of an analysis, ``{option: (value, diameter_per_value, min_voxels,
    axes)}`` (``value`` ``None`` when not given), checked against the voxel size and extent of
    ``source``'s volume of ``shape`` (:func:`fgat.analysis.scales.check_length_um`) before any
    data is read; returns ``{option: (z, y, x) um}``."""
    from fgat.analysis.scales import check_length_um  # imported when used: keeps start-up fast

    checked = {}
    for option, (value, per_value, min_voxels, axes) in lengths.items():
        if value is None:
            continue
        try:
            checked[option] = check_length_um(
                option,
                value,
                voxel,
                shape,
                diameter_per_value=per_value,
                min_voxels=min_voxels,
                axes=axes,
            )
        except ValueError as error:
            raise ValueError(f"{error} ({source})") from None
    return checked


def _write_table(path: Path, table) -> Path:
    """A DataFrame as CSV, written atomically (:func:`fgat.io.files.write_csv`)."""
    from fgat.io.files import write_csv  # imported when used: keeps start-up fast

    return write_csv(path, list(table.columns), table.itertuples(index=False))


def _finite(value: float) -> float | None:
    """``value``, or ``None`` (JSON null) when it is NaN or infinite."""
    return float(value) if math.isfinite(value) else None


# ------------------------------------------------------------------------------------ fwhm


def _add_fwhm(analyses) -> None:
    parser = analyses.add_parser(
        "fwhm",
        help="apparent tubule widths (FWHM; Note S8.2, Fig. 3j)",
        description="Measure the apparent width of tubules (Note S8.2): one intensity profile "
        "perpendicular to each segment's axis (skimage.measure.profile_line), the local "
        "background from the profile ends subtracted, FWHM by linear interpolation, in um. A "
        "3-D volume is measured on its x-y maximum-intensity projection, or on --plane. Writes "
        "OUT/widths.csv (one row per segment; width_um is empty and reason says why when a "
        "profile gives no width) and OUT/widths.png (the profiles on the image, box plot).",
    )
    parser.add_argument(
        "--image", required=True, help="OME-TIFF: a 2-D (Y, X) image or a 3-D (Z, Y, X) volume"
    )
    parser.add_argument(
        "--segments",
        required=True,
        metavar="SEGMENTS.csv",
        help="CSV with columns center_y, center_x (pixels, row and column of the profile's "
        "centre), axis_angle_rad (the tubule axis, from +x towards +y) and half_length_px (the "
        "profile's half-length, reaching into background on both sides)",
    )
    parser.add_argument(
        "--plane",
        type=number_type(integer=True, minimum=0),
        help="z index of a volume to measure, from 0 (default: its x-y maximum-intensity "
        "projection)",
    )
    parser.add_argument(
        "--width-px",
        type=number_type(integer=True, minimum=1),
        default=1,
        help="width of each profile strip in pixels, averaged across (default 1)",
    )
    _add_common(parser, FWHM_FILES, "; DZ is unused for a 2-D image")
    parser.set_defaults(run=_run_fwhm)


def _read_segments(path):
    """The segment table of ``--segments``, with the columns ``tubule_widths`` needs: every field
    a finite number (``half_length_px`` > 0), or one error naming the file, the line and the
    field."""
    import pandas as pd  # loaded when used: keeps start-up fast

    from fgat._core.validation import check_number  # imported when used: keeps start-up fast
    from fgat.analysis.morphology import SEGMENT_COLUMNS  # imported when used: keeps start-up fast

    source = f"--segments {path}"
    if not Path(path).is_file():
        raise FileNotFoundError(f"{source}: no such file")
    rows = []
    try:
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle, skipinitialspace=True)
            missing = [c for c in SEGMENT_COLUMNS if c not in (reader.fieldnames or ())]
            if missing:
                raise ValueError(
                    f"{source}: expected a header with columns {', '.join(SEGMENT_COLUMNS)}; "
                    f"missing {', '.join(missing)}"
                )
            for row in reader:
                line = f"{source}: line {reader.line_num} (segment {len(rows)})"
                bounds = {"half_length_px": {"above": 0}}
                rows.append(
                    {
                        column: check_number(
                            f"{line}, field {column}",
                            "" if row[column] is None else row[column],
                            **bounds.get(column, {}),
                        )
                        for column in SEGMENT_COLUMNS
                    }
                )
    except (UnicodeDecodeError, csv.Error) as error:
        raise ValueError(f"{source}: not a readable CSV table ({error})") from None
    if not rows:
        raise ValueError(
            f"{source}: expected one row per segment with columns {', '.join(SEGMENT_COLUMNS)}; "
            "the table has no rows"
        )
    return pd.DataFrame(rows, columns=list(SEGMENT_COLUMNS))


def _run_fwhm(args) -> int:
    from fgat.analysis.morphology import (  # imported when used: keeps start-up fast
        Segment,
        tubule_widths,
    )
    from fgat.analysis.outputs import write_outputs  # imported when used: keeps start-up fast
    from fgat.io.images import read_tiff  # imported when used: keeps start-up fast
    from fgat.viz.analysis import plot_tubule_widths  # imported when used: keeps start-up fast

    source = f"--image {args.image}"
    shape = _input_shape(args.image, source, (2, 3), "a 2-D (Y, X) image or a 3-D (Z, Y, X) volume")
    voxel = _voxel_size_um(args.image, source, args.voxel_size_um, "ZYX"[-len(shape) :])
    if args.plane is not None and (len(shape) == 2 or args.plane >= shape[0]):
        planes = "a 2-D image has none" if len(shape) == 2 else f"0 to {shape[0] - 1}"
        raise ValueError(f"--plane {args.plane}: expected a plane of {source} ({planes})")
    segments = _read_segments(args.segments)
    out = _output_folder(args.out, FWHM_FILES, args.overwrite)
    data = read_tiff(args.image)
    widths = tubule_widths(
        data, segments, voxel_size_um=voxel, width_px=args.width_px, plane=args.plane
    )
    measured = widths["width_um"].notna()
    if not measured.any():
        reasons = "; ".join(f"segment {row.segment}: {row.reason}" for row in widths.itertuples())
        raise ValueError(f"{source}: no segment gave a width ({reasons})")
    image = data if data.ndim == 2 else data.max(axis=0) if args.plane is None else data[args.plane]
    profiles = [
        Segment(
            (r.center_y_px, r.center_x_px), r.axis_angle_rad, r.half_length_px
        ).profile_endpoints()
        for r in widths.itertuples()
    ]
    where = (
        "" if data.ndim == 2 else " (x-y MIP)" if args.plane is None else f" (plane {args.plane})"
    )
    write_outputs(
        out,
        {
            "widths.csv": partial(_write_table, table=widths),
            "widths.png": partial(
                plot_tubule_widths,
                image,
                profiles,
                {Path(args.image).name: widths["width_um"]},
                title=f"{Path(args.image).name}{where}: {int(measured.sum())} widths",
            ),
        },
    )
    values = widths.loc[measured, "width_um"]
    print(
        f"{int(measured.sum())} of {len(widths)} segments measured: width median "
        f"{values.median():.4g} um, range {values.min():.4g}-{values.max():.4g} um"
        + ("" if measured.all() else f"; {int((~measured).sum())} without a width (see reason)")
        + f" -> {out}"
    )
    return 0


# ------------------------------------------------------------------------------- cytometry


def _add_cytometry(analyses) -> None:
    parser = analyses.add_parser(
        "cytometry",
        help="3D cell detection and marker classes (Notes S8.7-S8.8)",
        description="Volumetric cytometry (Notes S8.7-S8.8): nuclei are detected in --nuclei "
        "by a 3D Laplacian-of-Gaussian blob detector (the pan-cell reference), each --marker "
        "channel's objects with its own --threshold; every nucleus gets a local background-"
        "corrected signal per marker from the object matched to it within --match-radius-um, "
        "a +/- call and a class (e.g. CD11b-/Ferritin+). With --reference-counts (e.g. flow "
        "cytometry) the fractions are compared by a chi-squared test of homogeneity and a "
        "two-sided Fisher's exact test per class. Writes OUT/cells.csv (one row per nucleus), "
        "OUT/counts.csv (class, count, fraction; with a reference: reference, "
        "reference_fraction, fisher_odds_ratio, fisher_p), OUT/summary.json (inputs, totals, "
        "chi-squared test), OUT/montage.png (x-y MIPs of every channel and their merge with the "
        "cells circled by class) and OUT/fractions.png.",
    )
    parser.add_argument(
        "--nuclei", required=True, help="OME-TIFF 3-D (Z, Y, X) volume of the nuclear channel"
    )
    parser.add_argument(
        "--marker",
        required=True,
        action="append",
        type=_named(str, "CD11b=cd11b.ome.tif"),
        metavar="NAME=FILE",
        help="a marker channel's 3-D (Z, Y, X) OME-TIFF volume; repeat per marker (the class "
        "labels follow their order)",
    )
    parser.add_argument(
        "--sigma-um",
        required=True,
        type=number_type(above=0),
        help="expected nucleus standard deviation in um (a Gaussian nucleus of s.d. s answers "
        "best at s, a uniform ball of radius r at r / sqrt(3))",
    )
    parser.add_argument(
        "--marker-sigma-um",
        type=number_type(above=0),
        help="expected marker-object standard deviation in um (default --sigma-um; about "
        "0.6-0.7 times the cell radius for cell-sized marker signals)",
    )
    parser.add_argument(
        "--threshold",
        action="append",
        type=_named(number_type(above=0, maximum=1), "CD11b=0.2"),
        metavar="NAME=T",
        help="a marker's relative detection threshold in (0, 1] (fraction of its largest blob "
        f"response); repeat per marker (default {DEFAULT_THRESHOLD})",
    )
    parser.add_argument(
        "--nucleus-threshold",
        type=number_type(above=0, maximum=1),
        default=DEFAULT_THRESHOLD,
        help=f"relative detection threshold of the nuclei in (0, 1] (default {DEFAULT_THRESHOLD})",
    )
    parser.add_argument(
        "--match-radius-um",
        required=True,
        type=number_type(above=0),
        help="largest nucleus-to-marker-object distance in um (below the cell spacing)",
    )
    parser.add_argument(
        "--reference-counts",
        action="append",
        type=_named(number_type(integer=True, minimum=0), "CD11b-/Ferritin+=120"),
        metavar="CLASS=N",
        help="reference cell count of a class (e.g. flow cytometry); give every class or none",
    )
    _add_common(parser, CYTOMETRY_FILES)
    parser.set_defaults(run=_run_cytometry)


def _channel_inputs(args) -> tuple[dict, tuple[float, float, float], tuple[int, int, int]]:
    """``{"nuclei": path, marker: path, ...}``, the common voxel size (um) and shape ``(Z, Y,
    X)``, checked: one 3-D volume per channel, all of one shape and one voxel size."""
    import numpy as np  # loaded when used: keeps start-up fast

    markers = _mapping(args.marker, "--marker")
    if "nuclei" in markers:
        raise ValueError("--marker: 'nuclei' names the --nuclei channel; call the marker otherwise")
    paths = {"nuclei": args.nuclei, **markers}
    sources = {name: f"--marker {name}={path}" for name, path in paths.items()}
    sources["nuclei"] = f"--nuclei {args.nuclei}"
    shapes, sizes = {}, {}
    for name, path in paths.items():
        shapes[name] = _input_shape(
            path, sources[name], (3,), "a 3-D (Z, Y, X) volume (one file per channel)"
        )
        sizes[name] = _voxel_size_um(path, sources[name], args.voxel_size_um)
    for name in markers:
        if shapes[name] != shapes["nuclei"] or not np.allclose(sizes[name], sizes["nuclei"]):
            raise ValueError(
                f"{sources[name]}: shape {shapes[name]}, voxel size {sizes[name]} um; expected "
                f"those of {sources['nuclei']}: {shapes['nuclei']}, {sizes['nuclei']} um"
            )
    return paths, sizes["nuclei"], shapes["nuclei"]


def _reference_counts(args, classes: list[str]) -> dict | None:
    """``--reference-counts`` as ``{class: count}`` in the order of ``classes``, or ``None``."""
    reference = _mapping(args.reference_counts, "--reference-counts")
    if not reference:
        return None
    if set(reference) != set(classes):
        unknown = sorted(set(reference) - set(classes))
        missing = [c for c in classes if c not in reference]
        raise ValueError(
            f"--reference-counts: expected one count for each class {classes}"
            + (f"; unknown {unknown}" if unknown else "")
            + (f"; missing {missing}" if missing else "")
        )
    if sum(reference.values()) == 0:
        raise ValueError("--reference-counts: the counts add up to 0")
    return {c: reference[c] for c in classes}


def _run_cytometry(args) -> int:
    import numpy as np  # loaded when used: keeps start-up fast
    import pandas as pd  # loaded when used: keeps start-up fast

    from fgat.analysis.cytometry import (  # imported when used: keeps start-up fast
        classify_cells,
        compare_fractions,
        marker_classes,
    )
    from fgat.analysis.outputs import write_outputs  # imported when used: keeps start-up fast
    from fgat.analysis.scales import (  # imported when used: keeps start-up fast
        BALL_DIAMETER_PER_SIGMA,
    )
    from fgat.io.files import write_json  # imported when used: keeps start-up fast
    from fgat.io.images import read_tiff  # imported when used: keeps start-up fast
    from fgat.viz.analysis import (  # imported when used: keeps start-up fast
        plot_cell_montage,
        plot_class_fractions,
    )

    paths, voxel, shape = _channel_inputs(args)
    _check_lengths(
        {
            "--sigma-um": (args.sigma_um, BALL_DIAMETER_PER_SIGMA, 2.0, "YX"),
            "--marker-sigma-um": (args.marker_sigma_um, BALL_DIAMETER_PER_SIGMA, 2.0, "YX"),
            "--match-radius-um": (args.match_radius_um, 1.0, 0.0, "YX"),
        },
        voxel,
        shape,
        f"--nuclei {args.nuclei}",
    )
    names = [name for name in paths if name != "nuclei"]
    thresholds = _mapping(args.threshold, "--threshold")
    if set(thresholds) - set(names):
        raise ValueError(
            f"--threshold names {sorted(set(thresholds) - set(names))}, not a --marker {names}"
        )
    thresholds = {name: thresholds.get(name, DEFAULT_THRESHOLD) for name in names}
    classes = marker_classes(names)
    reference = _reference_counts(args, classes)
    out = _output_folder(args.out, CYTOMETRY_FILES, args.overwrite)
    channels = {name: read_tiff(path) for name, path in paths.items()}
    start = time.perf_counter()
    cells = classify_cells(
        channels["nuclei"],
        {name: channels[name] for name in names},
        voxel_size_um=voxel,
        sigma_um=args.sigma_um,
        thresholds=thresholds,
        match_radius_um=args.match_radius_um,
        nucleus_threshold=args.nucleus_threshold,
        marker_sigma_um=args.marker_sigma_um,
    )
    if cells.empty:
        raise ValueError(
            f"--nuclei {args.nuclei}: no nuclei detected (--sigma-um {args.sigma_um}, "
            f"--nucleus-threshold {args.nucleus_threshold}); check --sigma-um against the "
            "nuclei's size or lower the threshold"
        )
    counts = cells["class"].value_counts().reindex(classes, fill_value=0)
    table = pd.DataFrame({"class": classes, "count": counts.to_numpy()})
    table["fraction"] = table["count"] / len(cells)
    summary = {
        "nuclei": str(args.nuclei),
        "markers": {name: str(paths[name]) for name in names},
        "voxel_size_um": list(voxel),
        "sigma_um": args.sigma_um,
        "marker_sigma_um": args.marker_sigma_um,
        "thresholds": thresholds,
        "nucleus_threshold": args.nucleus_threshold,
        "match_radius_um": args.match_radius_um,
        "cells": len(cells),
        "counts": {c: int(n) for c, n in counts.items()},
    }
    comparison = None
    if reference is not None:
        comparison = compare_fractions({c: int(n) for c, n in counts.items()}, reference)
        table["reference"] = comparison.reference_counts
        table["reference_fraction"] = comparison.reference_fractions
        table["fisher_odds_ratio"] = comparison.fisher_odds_ratios
        table["fisher_p"] = comparison.fisher_pvalues
        summary["reference_counts"] = reference
        summary["chi2"] = comparison.chi2
        summary["chi2_dof"] = comparison.chi2_dof
        summary["chi2_p"] = comparison.chi2_pvalue
    write_outputs(
        out,
        {
            "cells.csv": partial(_write_table, table=cells),
            "counts.csv": partial(_write_table, table=table),
            "summary.json": partial(write_json, data=summary),
            "montage.png": partial(
                plot_cell_montage,
                {name: volume.max(axis=0) for name, volume in channels.items()},
                cells[["y", "x"]].to_numpy(),
                list(cells["class"]),
                pixel_um=voxel[1:],
                radius_um=args.match_radius_um,
                title=f"{Path(args.nuclei).name}: x-y maximum projections",
            ),
            "fractions.png": partial(
                plot_class_fractions,
                classes,
                table["fraction"].to_numpy(),
                reference_fractions=None if comparison is None else comparison.reference_fractions,
                pvalues=None if comparison is None else comparison.fisher_pvalues,
                title=f"{len(cells)} cells"
                + ("" if comparison is None else f", chi-squared p = {comparison.chi2_pvalue:.3g}"),
            ),
        },
    )
    listed = ", ".join(f"{c} {n} ({n / len(cells):.1%})" for c, n in counts.items())
    print(f"{len(cells)} cells in {time.perf_counter() - start:.1f} s: {listed}")
    if comparison is not None:
        worst = int(np.argmin(comparison.fisher_pvalues))
        print(
            f"against the reference counts: chi-squared p = {comparison.chi2_pvalue:.3g}; "
            f"smallest Fisher p = {comparison.fisher_pvalues[worst]:.3g} ({classes[worst]})"
        )
    print(f"tables, summary and figures -> {out}")
    return 0


# ----------------------------------------------------------------------------------- track


def _add_track(analyses) -> None:
    parser = analyses.add_parser(
        "track",
        help="3D cell tracking, speed classes and MSD (Note S8.9)",
        description="Track cells in a (T, Z, Y, X) volume series (Note S8.9): trackpy's 3D "
        "locate with anisotropic diameters and its linker in um; per cell the mean of the "
        "sliding-window speeds over --window frames, the slow/fast split at the density minimum "
        "between the two modes of the log mean speeds (when bimodal; else every cell is "
        "'unclassified'), the time-averaged MSD (Eq. S62) and its log-log slope alpha (~1 "
        "Brownian, ~2 directed). Writes OUT/trajectories.csv (frame, particle, t_s, z, y, x in "
        "um, mass), OUT/speeds.csv (particle, frames, mean_speed_um_s, class, alpha), "
        "OUT/msd.csv (particle, class, lag_frames, lag_s, msd_um2), OUT/summary.json, and "
        "speeds.png (histogram with the threshold), msd.png (log-log, per class), "
        "trajectories.png (x-y, coloured by class).",
    )
    parser.add_argument(
        "--series", required=True, help="OME-TIFF 4-D (T, Z, Y, X) volume series (T >= 2)"
    )
    parser.add_argument(
        "--frame-interval-s",
        required=True,
        type=number_type(above=0),
        help="time between frames (s)",
    )
    parser.add_argument(
        "--diameter-um",
        required=True,
        nargs="+",
        type=number_type(above=0),
        metavar="D",
        help="cell diameter in um, one value or three (z, y, x); it should span the whole cell "
        "image (about 7 standard deviations of a Gaussian blob per axis)",
    )
    parser.add_argument(
        "--search-range-um",
        required=True,
        type=number_type(above=0),
        help="largest displacement of a cell between linked frames (um)",
    )
    parser.add_argument(
        "--memory",
        type=number_type(integer=True, minimum=0),
        default=0,
        help="frames a cell may vanish for and keep its identity (default 0)",
    )
    parser.add_argument(
        "--minmass",
        type=number_type(minimum=0),
        help="smallest integrated brightness of a located cell (trackpy's minmass, the volumes' "
        "intensity units; default 0)",
    )
    parser.add_argument(
        "--window",
        type=number_type(integer=True, minimum=1),
        default=1,
        help="sliding-window length for the speeds in frames (default 1)",
    )
    _add_common(parser, TRACK_FILES)
    parser.set_defaults(run=_run_track)


def _per_particle(tracks, mean_speeds, threshold: float | None, frame_interval_s: float):
    """``speeds.csv`` and ``msd.csv`` tables: per particle its frames, mean speed, class and
    alpha; per particle and lag its MSD (Eq. S62) over the frames from its first to its last."""
    import numpy as np  # loaded when used: keeps start-up fast
    import pandas as pd  # loaded when used: keeps start-up fast

    from fgat.analysis.tracking import (  # imported when used: keeps start-up fast
        anomalous_exponent,
        msd,
    )

    speeds, curves = [], []
    for particle, one in tracks.groupby("particle"):
        frames = np.arange(one["frame"].min(), one["frame"].max() + 1)
        positions = one.set_index("frame")[["z", "y", "x"]].reindex(frames).to_numpy()
        speed = mean_speeds.get(particle, np.nan)
        label = (
            "unclassified"
            if threshold is None or np.isnan(speed)
            else "fast"
            if speed > threshold
            else "slow"
        )
        alpha = np.nan
        if len(frames) >= 2:
            lags, values = msd(positions)
            curves.append(
                pd.DataFrame(
                    {
                        "particle": particle,
                        "class": label,
                        "lag_frames": lags,
                        "lag_s": lags * frame_interval_s,
                        "msd_um2": values,
                    }
                )
            )
            if np.sum(np.isfinite(values) & (values > 0)) >= 2:
                alpha = anomalous_exponent(lags, values)
        speeds.append(
            {
                "particle": particle,
                "frames": len(one),
                "mean_speed_um_s": speed,
                "class": label,
                "alpha": alpha,
            }
        )
    columns = ["particle", "class", "lag_frames", "lag_s", "msd_um2"]
    table = pd.concat(curves, ignore_index=True) if curves else pd.DataFrame(columns=columns)
    return pd.DataFrame(speeds), table


def _run_track(args) -> int:
    from fgat.analysis.outputs import write_outputs  # imported when used: keeps start-up fast
    from fgat.analysis.tracking import (  # imported when used: keeps start-up fast
        mean_speeds,
        speed_threshold,
        track,
    )
    from fgat.io.files import write_json  # imported when used: keeps start-up fast
    from fgat.io.images import read_tiff  # imported when used: keeps start-up fast
    from fgat.viz.analysis import (  # imported when used: keeps start-up fast
        plot_msd_curves,
        plot_speed_histogram,
        plot_trajectories,
    )

    source = f"--series {args.series}"
    shape = _input_shape(args.series, source, (4,), "a 4-D (T, Z, Y, X) volume series")
    if shape[0] < 2:
        raise ValueError(f"{source}: {shape[0]} frame; tracking needs 2 or more")
    if len(args.diameter_um) not in (1, 3):
        raise ValueError(
            f"--diameter-um: expected one value or three (z, y, x), got {args.diameter_um}"
        )
    voxel = _voxel_size_um(args.series, source, args.voxel_size_um)
    _check_lengths(
        {
            "--diameter-um": (args.diameter_um, 1.0, 2.0, "ZYX"),
            "--search-range-um": (args.search_range_um, 1.0, 0.0, "YX"),
        },
        voxel,
        shape,
        source,
    )
    out = _output_folder(args.out, TRACK_FILES, args.overwrite)
    start = time.perf_counter()
    tracks = track(
        read_tiff(args.series),
        voxel_size_um=voxel,
        frame_interval_s=args.frame_interval_s,
        diameter_um=args.diameter_um,
        search_range_um=args.search_range_um,
        memory=args.memory,
        minmass=args.minmass,
    )
    speeds = mean_speeds(tracks, args.window)
    threshold, note = None, ""
    if speeds.empty:
        note = f"no cell is tracked over --window {args.window} frames: no speeds"
    else:
        try:
            threshold = speed_threshold(speeds.to_numpy())
        except ValueError as error:  # too few cells, or one mode: no slow/fast split
            note = f"no slow/fast threshold: {error}"
    per_particle, curves = _per_particle(tracks, speeds, threshold, args.frame_interval_s)
    groups = per_particle.groupby("class")
    summary = {
        "series": str(args.series),
        "voxel_size_um": list(voxel),
        "frame_interval_s": args.frame_interval_s,
        "window_frames": args.window,
        "particles": len(per_particle),
        "threshold_um_s": threshold,
        "note": note,
        "classes": {
            label: {"cells": len(group), "median_alpha": _finite(group["alpha"].median())}
            for label, group in groups
        },
    }
    name = Path(args.series).name
    by_particle = dict(iter(tracks.groupby("particle")))
    msd_by_particle = dict(iter(curves.groupby("particle")))
    histogram = {
        "speeds.png": partial(
            plot_speed_histogram,
            speeds.to_numpy(),
            threshold=threshold,
            title=f"{name}: {len(speeds)} cells, window {args.window} frames",
        )
    }
    write_outputs(
        out,
        {
            "trajectories.csv": partial(_write_table, table=tracks),
            "speeds.csv": partial(_write_table, table=per_particle),
            "msd.csv": partial(_write_table, table=curves),
            "summary.json": partial(write_json, data=summary),
            **({} if speeds.empty else histogram),
            "msd.png": partial(
                plot_msd_curves,
                {
                    f"{label} (n={len(group)})": [
                        (msd_by_particle[p]["lag_s"], msd_by_particle[p]["msd_um2"])
                        for p in group["particle"]
                        if p in msd_by_particle
                    ]
                    for label, group in groups
                },
                title=f"{name}: time-averaged MSD",
            ),
            "trajectories.png": partial(
                plot_trajectories,
                {
                    f"{label} (n={len(group)})": [
                        by_particle[p][["x", "y"]].to_numpy() for p in group["particle"]
                    ]
                    for label, group in groups
                },
                title=f"{name}: trajectories (x-y)",
            ),
        },
    )
    if speeds.empty:  # no histogram; none of another run's left beside these tables
        (out / "speeds.png").unlink(missing_ok=True)
    print(
        f"{len(per_particle)} cells tracked over {shape[0]} frames in "
        f"{time.perf_counter() - start:.1f} s; "
        + (note if threshold is None else f"slow/fast threshold {threshold:.3g} um/s")
    )
    for label, group in groups:
        print(f"{label}: {len(group)} cells, median alpha {group['alpha'].median():.3g}")
    print(f"tables, summary and figures -> {out}")
    return 0
