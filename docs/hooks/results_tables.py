"""MkDocs hook: render committed result files into pages, with their provenance.

A line that holds only a placeholder such as ::

    {{ results("hostile", table="cases", columns="id,expect,exit,ok") }}

(outside fenced code) is replaced at build time by a provenance line (date, machine, commit,
command: the header ``fgat.app.recipes.benchmark.provenance()`` writes) and a Markdown table.
Numbers in the documentation come only from such files, never from prose.

Arguments (Python literals):

- the file: a name (``"hostile"`` is ``benchmarks/results/hostile.json``) or a path relative to
  the repository root ending in ``.json`` or ``.csv``;
- ``table``: dotted key of the part to show: a list of records (one row each) or a mapping
  (one row per scalar, nested mappings flattened with dots). Default: the file's top-level
  scalars, or its rows for a CSV;
- ``rows``: comma-separated keys of a mapping of records, one row each (e.g. ``"core,dev"``);
- ``columns``: comma-separated fields to show, in order (default: every scalar field);
- ``where``: ``"field=value"``, keep only the records whose field prints as ``value``;
- ``limit``: at most this many rows (the table says how many were left out);
- ``missing``: the sentence shown when the file is absent (default: not measured on this
  release yet).
"""

from __future__ import annotations

import ast
import csv
import json
import re
from pathlib import Path

from mkdocs.exceptions import PluginError

PLACEHOLDER = re.compile(r"^\{\{\s*results\((?P<arguments>.*)\)\s*\}\}\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")
PROVENANCE = ("date", "machine", "commit", "command")
NOT_MEASURED = "Not measured on this release yet."
_root = Path.cwd()  # the folder of mkdocs.yml, set by on_config


class PlaceholderError(PluginError):
    """A placeholder that cannot be rendered: the build stops with the page and the reason."""


def on_config(config):
    global _root
    _root = Path(config.config_file_path).resolve().parent
    return config


def on_page_markdown(markdown, page, config, files):
    lines, fenced = [], False
    for number, line in enumerate(markdown.split("\n"), start=1):
        if FENCE.match(line):
            fenced = not fenced
        match = None if fenced else PLACEHOLDER.match(line)
        if match is None:
            lines.append(line)
            continue
        try:
            lines.append(render(*parse(match["arguments"])))
        except PlaceholderError as error:
            raise PlaceholderError(f"{page.file.src_uri}:{number}: {error}") from None
    return "\n".join(lines)


def parse(arguments: str) -> tuple[str, dict]:
    """The file and keyword arguments of ``results(...)``, as literals only."""
    try:
        call = ast.parse(f"results({arguments})", mode="eval").body
        positional = [ast.literal_eval(node) for node in call.args]
        keywords = {item.arg: ast.literal_eval(item.value) for item in call.keywords}
    except (SyntaxError, ValueError) as error:
        raise PlaceholderError(f"results({arguments}): not literal arguments ({error})") from None
    if len(positional) != 1 or not isinstance(positional[0], str):
        raise PlaceholderError(f"results({arguments}): expected one file name first")
    unknown = set(keywords) - {"table", "rows", "columns", "where", "limit", "missing"}
    if unknown:
        raise PlaceholderError(f"results(...): unknown argument(s) {', '.join(sorted(unknown))}")
    return positional[0], keywords


def result_path(name: str) -> Path:
    if name.endswith((".json", ".csv")):
        return _root / name
    return _root / "benchmarks" / "results" / f"{name}.json"


def render(name: str, options: dict) -> str:
    path = result_path(name)
    shown = path.relative_to(_root).as_posix()
    if not path.is_file():
        return f"*{options.get('missing', NOT_MEASURED)}* (no `{shown}`)"
    if path.suffix == ".csv":
        with path.open(newline="", encoding="utf-8") as handle:
            data: object = {"rows": list(csv.DictReader(handle))}
        options = {"table": "rows", **options}
    else:
        data = json.loads(path.read_text(encoding="utf-8"))
    header = provenance(data, shown)
    records = select(data, options, shown)
    return header + "\n\n" + table(records, options, shown)


def provenance(data: object, shown: str) -> str:
    """One line: source file, date, machine, commit and command, as far as the file says."""
    if not isinstance(data, dict) or not any(key in data for key in PROVENANCE):
        return f"*From `{shown}` (the file records no date, machine or commit).*"
    parts = [f"From `{shown}`"]
    if "date" in data:
        parts.append(f"measured {data['date']}")
    machine = data.get("machine")
    if isinstance(machine, dict):
        parts.append("on " + machine_summary(machine))
    elif machine:
        parts.append(f"on {machine}")
    if "commit" in data:
        parts.append(f"at commit `{str(data['commit'])[:10]}`")
    if "command" in data:
        parts.append(f"by `{data['command']}`")
    return "*" + "; ".join(parts) + ".*"


def machine_summary(machine: dict) -> str:
    """``processor, N CPUs, platform, Python X`` and any further scalar fields."""
    known = {"processor": "{}", "cpus": "{} CPUs", "platform": "{}", "python": "Python {}"}
    fields = [form.format(machine[key]) for key, form in known.items() if key in machine]
    extras = [
        f"{key} {fmt(value)}"
        for key, value in machine.items()
        if key not in known and scalar(value)
    ]
    return ", ".join(fields + extras)


def select(data: object, options: dict, shown: str) -> list[dict]:
    """The records the table shows, each a flat mapping of field to scalar."""
    part = data
    if "table" in options:
        for key in str(options["table"]).split("."):
            if not isinstance(part, dict) or key not in part:
                raise PlaceholderError(f"{shown}: no field {options['table']!r}")
            part = part[key]
    elif isinstance(data, dict):
        part = {key: value for key, value in data.items() if key not in PROVENANCE}
    if "rows" in options:
        if not isinstance(part, dict):
            raise PlaceholderError(f"{shown}: rows= needs a mapping of records")
        records = []
        for key in str(options["rows"]).split(","):
            key = key.strip()
            if not isinstance(part.get(key), dict):
                raise PlaceholderError(f"{shown}: no record {key!r}")
            records.append({"": key, **flatten(part[key])})
        return records
    if isinstance(part, list):
        return [flatten(item) if isinstance(item, dict) else {"value": item} for item in part]
    if isinstance(part, dict):
        return [{"field": key, "value": value} for key, value in flatten(part).items()]
    return [{"value": part}]


def flatten(mapping: dict, prefix: str = "") -> dict:
    """Scalars of ``mapping``, nested mappings' keys joined with dots; lists of scalars joined."""
    flat = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, f"{name}."))
        elif scalar(value):
            flat[name] = value
        elif isinstance(value, list) and all(scalar(item) for item in value) and len(value) <= 8:
            flat[name] = ", ".join(fmt(item) for item in value)
    return flat


def table(records: list[dict], options: dict, shown: str) -> str:
    if "where" in options:
        field, _, wanted = str(options["where"]).partition("=")
        records = [record for record in records if fmt(record.get(field.strip())) == wanted.strip()]
    if not records:
        return "*(none)*"
    if "columns" in options:
        columns = [column.strip() for column in str(options["columns"]).split(",")]
        unknown = [column for column in columns if all(column not in r for r in records)]
        if unknown:
            raise PlaceholderError(f"{shown}: no column {', '.join(unknown)}")
        if "" in records[0] and "" not in columns:
            columns.insert(0, "")
    else:
        columns = list(dict.fromkeys(key for record in records for key in record))
    limit = options.get("limit")
    left_out = 0
    if isinstance(limit, int) and 0 < limit < len(records):
        left_out, records = len(records) - limit, records[:limit]
    lines = [
        "| " + " | ".join(cell(column) for column in columns) + " |",
        "| " + " | ".join("---" for _ in columns) + " |",
    ]
    for record in records:
        lines.append("| " + " | ".join(cell(fmt(record.get(c, ""))) for c in columns) + " |")
    if left_out:
        lines.append(f"\n*{left_out} more rows in `{shown}`.*")
    return "\n".join(lines)


def scalar(value: object) -> bool:
    return value is None or isinstance(value, (str, int, float, bool))


def fmt(value: object) -> str:
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")
