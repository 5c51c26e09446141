"""YAML files fgat reads (configs, optics systems, calibration records): a loader that
refuses duplicate keys, field checks against a schema and one-line error messages.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from pathlib import Path

from fgat.io.files import read_text


@functools.cache
def unique_key_loader() -> type:
    """The :class:`yaml.SafeLoader` subclass every YAML read of fgat uses: a mapping that gives a
    key twice is refused (a ``yaml.constructor.ConstructorError`` naming the key and both lines)
    instead of keeping the last value silently. Built on first use, so importing :mod:`fgat.io`
    does not import PyYAML."""
    import yaml  # loaded when a file is read or written: keeps start-up fast
    from yaml.constructor import (  # loaded when a file is read or written: keeps start-up fast
        ConstructorError,
    )

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                first: dict = {}  # key -> its first line (0-based); merged keys (<<) may be
                for key_node, _ in node.value:  # overridden, as YAML allows: not checked
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    try:
                        seen = key in first
                    except TypeError:
                        continue  # an unhashable key: SafeLoader's own error follows
                    if seen:
                        raise ConstructorError(
                            None,
                            None,
                            f"duplicate key {key!r} at line {key_node.start_mark.line + 1} "
                            f"(first given at line {first[key] + 1}); give each key once",
                            key_node.start_mark,
                        )
                    first[key] = key_node.start_mark.line
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def load_yaml(text: str, source: str) -> object:
    """The YAML document of ``text``, read by :func:`unique_key_loader` (safe
    tags only; a key given twice in a mapping is an error); invalid YAML is one ``ValueError``
    naming ``source`` with the line and column (:func:`describe_yaml_error`)."""
    import yaml  # loaded when a file is read or written: keeps start-up fast

    try:
        return yaml.load(text, Loader=unique_key_loader())  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as error:
        raise ValueError(f"{source}: {describe_yaml_error(error)}") from None


def yaml_fields(text: str, source: str, schema, *, extra: tuple[str, ...] = ()) -> dict:
    """Parse YAML ``text`` into a dict of the fields of dataclass ``schema`` (and the keys
    ``extra``), naming ``source`` (a file, a preset) in every error: invalid YAML, a key given
    twice, not a mapping, unknown fields."""
    fields = load_yaml(text, source)
    fields = {} if fields is None else fields
    if not isinstance(fields, dict):
        raise ValueError(f"{source}: expected a mapping of {schema.__name__} fields")
    check_fields(source, schema, fields, extra=extra)
    return fields


def check_fields(source: str, schema, fields: dict | None, *, extra: tuple[str, ...] = ()) -> None:
    """Raise ``ValueError`` naming ``source`` and the valid keys when ``fields`` has a key that is
    neither a constructor field of dataclass ``schema`` nor one of ``extra``."""
    known = {f.name for f in dataclasses.fields(schema) if f.init} | set(extra)
    unknown = sorted(set(fields or {}) - known)
    if unknown:
        raise ValueError(f"{source}: unknown field(s) {unknown}; expected some of {sorted(known)}")


def read_yaml(path: str | Path, source: str) -> object:
    """The YAML document of the file ``path``; a missing file, one that is not UTF-8 text, invalid
    YAML or a key given twice is one error naming ``source`` (e.g. ``"config runs.yaml"``) with
    the line and column (:func:`describe_yaml_error`, :func:`load_yaml`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{source} does not exist")
    return load_yaml(read_text(path, source), source)


def check_config_files(words: Sequence[str]) -> None:
    """Every ``--config`` (``-c``) of command-line ``words`` must be a readable YAML file, or a
    YAML mapping given inline: a missing file or a syntax error is one error naming the file,
    the line and the column (:func:`read_yaml`; a key given twice names both lines), raised
    before any heavy import or computation, and before jsonargparse, which would keep the
    last value of a repeated key silently.
    """
    for index, word in enumerate(words):
        if word in ("--config", "-c") and index + 1 < len(words):
            path = words[index + 1]
        elif word.startswith("--config="):
            path = word.split("=", 1)[1]
        else:
            continue
        if not Path(path).is_file():
            try:
                if isinstance(load_yaml(path, "--config"), dict):
                    continue  # the options themselves, as jsonargparse accepts them
            except ValueError:
                pass
        read_yaml(path, f"--config {path}")


def describe_yaml_error(error) -> str:
    """One line for a PyYAML error: where (line and column, 1-based) and what, e.g. ``"invalid YAML
    at line 3, column 1: expected ',' or '}', but got '<scalar>' (while parsing a flow mapping
    started at line 2, column 10)"``."""
    mark = getattr(error, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    context = getattr(error, "context", None)
    context_mark = getattr(error, "context_mark", None)
    if context and context_mark is not None:
        context += f" started at line {context_mark.line + 1}, column {context_mark.column + 1}"
    return f"invalid YAML{where}: {problem}" + (f" ({context})" if context else "")
