"""Argument types and option groups the command families share: depth lists, Zernike
and shift tables, checked numbers, output folders, devices and measured lenslet centres; the
one-line summaries of the LightningCLI subcommands, and help rendered as plain text (docstrings
are reST).
"""

from __future__ import annotations

import argparse
import inspect
import re
import textwrap
from pathlib import Path

LIGHTNING_COMMANDS = {
    "fit": "reconstruct: fit a model to a dataset (LightningCLI)",
    "validate": "a checkpoint's validation metrics (LightningCLI)",
    "test": "a model's test loop on a checkpoint (LightningCLI)",
    "predict": "render a dynamic run at chosen times (LightningCLI)",
}
"""The one-line summary of each LightningCLI subcommand: its line in ``python -m fgat --help``
and the first line of its own ``--help``."""

_LINK = re.compile(r"`([^`<]*?)\s*<([^>`]+)>`_{1,2}")
_ROLE = re.compile(r":[\w.-]+(?::[\w.-]+)*:`([^`]+)`")
_LITERAL = re.compile(r"``(.+?)``", re.DOTALL)
_INTERPRETED = re.compile(r"(?<![\w`])`([^`]+)`(?![\w`])")
_BULLET = re.compile(r"[*-] ")


def _role_text(target: str) -> str:
    """What a reST role shows: ``text`` of ``text <target>``, the last name of ``~a.b.c``, else
    the target."""
    titled = re.fullmatch(r"(.+?)\s*<[^>]+>", target, re.DOTALL)
    if titled:
        return titled.group(1)
    return target[1:].rsplit(".", 1)[-1] if target.startswith("~") else target


def plain_inline(text: str) -> str:
    """One paragraph's reST markup as plain text: ``:func:`~a.b``` -> ``b``, ``:class:`a.B``` ->
    ``a.B``, double back-quoted literals and single back-quoted names -> their text, a link
    ```text <url>`_`` -> ``text (url)``."""
    text = _LINK.sub(lambda m: f"{m.group(1)} ({m.group(2)})" if m.group(1) else m.group(2), text)
    text = _ROLE.sub(lambda m: _role_text(m.group(1)), text)
    text = _LITERAL.sub(lambda m: m.group(1), text)
    return _INTERPRETED.sub(lambda m: m.group(1), text)


def plain_text(doc: str | None) -> str:
    """A reST docstring as plain text: markup removed (:func:`plain_inline`), each paragraph on
    one line, paragraphs separated by a blank line; bullet items (``* ``, ``- ``) one per line,
    indented literal blocks kept line by line, a paragraph's closing ``::`` a colon. Wrapped to
    the terminal by :class:`PlainHelpFormatter`."""
    paragraphs = []
    for block in re.split(r"\n\s*\n", inspect.cleandoc(doc or "")):
        lines = block.splitlines()
        if not lines:
            continue
        if all(line.startswith((" ", "\t")) for line in lines):
            paragraphs.append("\n".join(lines))
            continue
        items: list[list[str]] = []  # the paragraph, or its lead-in and its bullet items
        for line in lines:
            if _BULLET.match(line) or not items:
                items.append([line.strip()])
            else:
                items[-1].append(line.strip())
        paragraphs.append("\n".join(plain_inline(" ".join(item)) for item in items))
    return re.sub(r"::$", ":", "\n\n".join(paragraphs), flags=re.MULTILINE)


def _fill(text: str, width: int, indent: str) -> str:
    """:func:`plain_text`'s paragraphs wrapped to ``width``: a bullet item with a hanging indent,
    an indented (literal) block as it is."""
    out = []
    for paragraph in text.split("\n\n"):
        lines = paragraph.splitlines()
        if lines and all(line.startswith((" ", "\t")) for line in lines):
            out.append("\n".join(indent + line for line in lines))
            continue
        wrapped = []
        for line in lines:
            hanging = "  " if _BULLET.match(line) else ""
            wrapped.append(
                textwrap.fill(
                    line, width, initial_indent=indent, subsequent_indent=indent + hanging
                )
            )
        out.append("\n".join(wrapped))
    return "\n\n".join(out)


class PlainHelpFormatter(argparse.HelpFormatter):
    """argparse's formatter for text made by :func:`plain_text`: paragraphs, bullet items and
    literal blocks kept, each wrapped to the terminal; option help as plain text too."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return _fill(text, width, indent)

    def _get_help_string(self, action) -> str | None:
        help_text = super()._get_help_string(action)
        return None if help_text is None else plain_inline(help_text)


def describe(summary: str, doc: str | None = None) -> str:
    """A subcommand's description: ``summary`` (its one line in the command list) as a sentence,
    then ``doc`` as plain text (:func:`plain_text`)."""
    first = summary[:1].upper() + summary[1:]
    first = first if first.endswith(".") else f"{first}."
    return first if not doc else f"{first}\n\n{plain_text(doc)}"


def plain_help(parser: argparse.ArgumentParser) -> None:
    """Every subcommand of ``parser`` (nested ones too) described as :func:`describe` says, from
    its one-line ``help`` and its own description, with its epilog as plain text and
    :class:`PlainHelpFormatter`; subcommands without ``add_help`` (the LightningCLI ones, whose
    help LightningCLI prints) are left as they are."""
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        summaries = {choice.dest: choice.help for choice in action._choices_actions}
        for name, sub in action.choices.items():
            if not sub.add_help:
                continue
            sub.description = describe(summaries.get(name) or name, sub.description)
            sub.epilog = plain_text(sub.epilog) if sub.epilog else None
            sub.formatter_class = PlainHelpFormatter
            plain_help(sub)


def parse_depths(text: str) -> list[float]:
    """``"-30,-15,0,15,30"`` or ``"start:stop:count"`` (inclusive, evenly spaced) in um,
    distinct."""
    from fgat.optics.systems import parse_depths  # imported when used: keeps start-up fast

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
    from fgat._core.validation import check_number  # imported when used: keeps start-up fast

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
    from fgat.instrument.calibration import (  # imported when used: keeps start-up fast
        read_calibration,
    )
    from fgat.instrument.centres import read_centers  # imported when used: keeps start-up fast
    from fgat.optics.depth_scale import calibrated_system  # imported when used: keeps start-up fast

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
