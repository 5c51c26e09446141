"""MkDocs hook: one API reference page per public module of the ``fgat`` package beside
``mkdocs.yml``, found with :mod:`pkgutil`, so the reference follows the package layout without a
hand-kept list.

A module is public when no part of its dotted name starts with an underscore. Each page holds
``::: fgat.x.y`` for mkdocstrings; ``api/index.md`` lists them all, and the ``API reference``
entry of ``nav`` gets the generated pages (grouped by top-level subpackage).
"""

from __future__ import annotations

import ast
import pkgutil
import re
from pathlib import Path

from mkdocs.structure.files import File

PACKAGE = "fgat"
SECTION = "API reference"
# Sphinx roles in docstrings (:func:`x`, :class:`~a.b.C`), which mkdocstrings leaves as text
# before the code span: the role is dropped, and ``~`` keeps the last dotted part, as in Sphinx.
SPHINX_ROLE = re.compile(
    r":(?:py:)?(?:func|class|meth|mod|data|attr|obj|exc|const):<code>(~?)([^<]*)</code>"
)
_modules: list[str] = []
_root = Path.cwd()  # the folder of mkdocs.yml, set by on_config


def public_modules(root: Path) -> list[str]:
    """Dotted names of ``root/fgat``'s public modules and packages, ``fgat`` first, sorted.

    The folders are walked with :func:`pkgutil.iter_modules` without importing anything, so the
    reference builds wherever the sources are, whether or not PyTorch is installed."""
    names = [PACKAGE]
    folders = [(root / PACKAGE, PACKAGE)]
    while folders:
        folder, prefix = folders.pop()
        for module in pkgutil.iter_modules([str(folder)]):
            if module.name.startswith("_"):
                continue
            names.append(f"{prefix}.{module.name}")
            if module.ispkg:
                folders.append((folder / module.name, f"{prefix}.{module.name}"))
    return sorted(names)


def page_path(module: str) -> str:
    return "api/" + module.replace(".", "/") + ".md"


def index_markdown(modules: list[str]) -> str:
    lines = [
        "# API reference",
        "",
        "Generated from the docstrings of every public module of `fgat` (NumPy style: shapes,",
        "units and the supplement's equation numbers are in each docstring). Modules whose name",
        "starts with an underscore are private and not listed.",
        "",
        "| module | summary |",
        "| --- | --- |",
    ]
    for module in modules:
        summary = _summary(module)
        lines.append(f"| [`{module}`]({page_path(module)[len('api/') :]}) | {summary} |")
    return "\n".join(lines) + "\n"


def _summary(module: str) -> str:
    """First paragraph of the module's docstring, read without importing it."""
    path = _source(module)
    if path is None:
        return ""
    docstring = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    first = docstring.strip().split("\n\n")[0].replace("\n", " ")
    return first.replace("|", "\\|")


def _source(module: str) -> Path | None:
    base = _root / Path(*module.split("."))
    for candidate in (base / "__init__.py", base.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


def _nav(modules: list[str]) -> list:
    groups: dict[str, list] = {}
    for module in modules[1:]:
        group = module.split(".")[1]
        groups.setdefault(group, []).append({module: page_path(module)})
    entries: list = [{"Overview": "api/index.md"}, {PACKAGE: page_path(PACKAGE)}]
    for group, pages in groups.items():
        entries.append({f"{PACKAGE}.{group}": pages} if len(pages) > 1 else pages[0])
    return entries


def on_config(config):
    global _root
    _root = Path(config.config_file_path).resolve().parent
    _modules[:] = public_modules(_root)
    for index, entry in enumerate(config.nav or []):
        if isinstance(entry, dict) and SECTION in entry:
            config.nav[index] = {SECTION: _nav(_modules)}
    return config


def on_files(files, config):
    files.append(File.generated(config, "api/index.md", content=index_markdown(_modules)))
    for module in _modules:
        content = f"# `{module}`\n\n::: {module}\n"
        files.append(File.generated(config, page_path(module), content=content))
    return files


def on_page_content(html, page, config, files):
    if not page.file.src_uri.startswith("api/"):
        return html
    return SPHINX_ROLE.sub(_code_span, html)


def _code_span(match: re.Match) -> str:
    name = match[2].rsplit(".", 1)[-1] if match[1] else match[2]
    return f"<code>{name}</code>"
