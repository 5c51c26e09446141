"""How much of a config folder is repeated text: lines that appear in more than one file.

Every ``*.yaml`` file under the folder (sub-folders included) is read as text. A line counts
when, stripped of surrounding white space, it is neither blank nor a comment (``#`` first); a
trailing comment is cut off first (``max_steps: 800  # Table S7`` counts as ``max_steps: 800``).
A counted line is *repeated* when the same stripped line also occurs in another file of the
folder (repeats inside one file do not count: a file is one place to edit). Per file and in
total:

    repeated % = repeated lines / counted lines * 100

Bare keys that only open a block (``model:``, ``init_args:``) are counted like any other line;
the ``structure`` column says how many of a file's repeated lines are such keys, and the total
is also given without them (``settings``: lines that carry a value).

    python benchmarks/config_duplication.py [FOLDER]
        [--out benchmarks/results/config_duplication.json]

FOLDER defaults to ``configs``; run it on a copy of an older ``configs/`` to compare.
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path

from fgat.app.recipes.benchmark import write_json

BLOCK_KEY = re.compile(r"^[^\s:#'\"{}\[\]]+:$")  # a key that opens a nested block, nothing after it


def counted_lines(text: str) -> list[str]:
    """The stripped, non-blank, non-comment lines of a YAML file, trailing comments removed."""
    lines = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        line = re.sub(r"\s+#.*$", "", line)  # `value  # why`: a comment after white space
        lines.append(line)
    return lines


def duplication(folder: Path) -> dict:
    """Per-file and total counts of counted and repeated lines (see the module's notes)."""
    files = sorted(path for path in folder.rglob("*.yaml") if path.is_file())
    if not files:
        raise SystemExit(f"{folder}: no *.yaml files")
    lines = {path: counted_lines(path.read_text()) for path in files}
    owners = defaultdict(set)
    for path, found in lines.items():
        for line in found:
            owners[line].add(path)
    rows = []
    for path, found in lines.items():
        repeated = [line for line in found if len(owners[line]) > 1]
        structure = sum(1 for line in repeated if BLOCK_KEY.match(line))
        rows.append(
            {
                "file": str(path.relative_to(folder)),
                "lines": len(found),
                "repeated": len(repeated),
                "structure": structure,
                "repeated_percent": 100.0 * len(repeated) / len(found) if found else 0.0,
            }
        )
    total = sum(row["lines"] for row in rows)
    repeated = sum(row["repeated"] for row in rows)
    structure_total = sum(1 for found in lines.values() for line in found if BLOCK_KEY.match(line))
    structure_repeated = sum(row["structure"] for row in rows)
    settings = total - structure_total
    return {
        "folder": str(folder),
        "files": rows,
        "lines": total,
        "repeated": repeated,
        "repeated_percent": 100.0 * repeated / total,
        "setting_lines": settings,
        "setting_repeated": repeated - structure_repeated,
        "setting_repeated_percent": 100.0 * (repeated - structure_repeated) / settings
        if settings
        else 0.0,
    }


def print_table(result: dict) -> None:
    width = max(len(row["file"]) for row in result["files"])
    print(f"{'file':<{width}} {'lines':>6} {'repeated':>9} {'structure':>10} {'repeated %':>11}")
    for row in result["files"]:
        print(
            f"{row['file']:<{width}} {row['lines']:>6} {row['repeated']:>9} {row['structure']:>10} "
            f"{row['repeated_percent']:>10.1f}%"
        )
    print(
        f"{'total':<{width}} {result['lines']:>6} {result['repeated']:>9} "
        f"{result['repeated'] - result['setting_repeated']:>10} "
        f"{result['repeated_percent']:>10.1f}%"
    )
    print(
        f"settings only (block keys left out): {result['setting_repeated']} of "
        f"{result['setting_lines']} lines "
        f"repeated, {result['setting_repeated_percent']:.1f}%"
    )


def main(argv: list[str] | None = None) -> None:
    options = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    options.add_argument(
        "folder", nargs="?", default="configs", help="config folder (default: configs)"
    )
    options.add_argument("--out", default="benchmarks/results/config_duplication.json")
    args = options.parse_args(argv)
    folder = Path(args.folder)
    if not folder.is_dir():
        raise SystemExit(f"{folder}: not a folder")
    result = duplication(folder)
    print_table(result)
    write_json(args.out, result)


if __name__ == "__main__":
    main()
