"""The repository's own code: no script, benchmark or test edits the import path or loads a
module from a file path; what they share is imported from the installed ``fgat``
(:mod:`fgat.app.recipes`)."""

import ast
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
IMPORT_PATH = ".".join(("sys", "path"))  # spelt so that a text search finds only real edits
EDITS = frozenset({"insert", "append", "extend", "remove", "pop", "clear"})
"""Methods of the import path's list that change it."""
LOADERS = frozenset(
    {
        "_".join(("spec", "from", "file", "location")),
        "SourceFileLoader",
        "SourcelessFileLoader",
        "run_path",
        "addsitedir",
    }
)
"""Functions and classes that load a module from a file path, or add a folder to the path."""
IN_TEXT = re.compile(
    "|".join(
        [re.escape(IMPORT_PATH) + r"\s*(\.\s*(" + "|".join(EDITS) + r")\s*\(|\+?=[^=]|\[)"]
        + [re.escape(name) + r"\s*\(" for name in sorted(LOADERS)]
    )
)
"""An edit of the import path or a loader's call inside text: code passed to ``python -c``,
shell scripts."""
SKIPPED = {".git", "__pycache__", "runs", "mlruns", "mlartifacts", "build", "dist"}


def is_import_path(node: ast.AST) -> bool:
    """Whether ``node`` is the attribute ``path`` of the name ``sys`` (the import path)."""
    return (
        isinstance(node, ast.Attribute)
        and node.attr == "path"
        and isinstance(node.value, ast.Name)
        and node.value.id == "sys"
    )


def path_edits(source: str, name: str = "<source>") -> list[str]:
    """The lines of Python ``source`` that edit the import path (a changing method called on it,
    an assignment to it or to an item or slice of it) or load a module from a file path (a
    :data:`LOADERS` name), and the string constants holding such code: ``name:line: what``."""
    found = []
    for node in ast.walk(ast.parse(source, name)):
        what = None
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr in EDITS and is_import_path(node.func.value):
                what = f"{node.func.attr} on the import path"
        elif isinstance(node, ast.Assign | ast.AugAssign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                if isinstance(target, ast.Subscript):
                    target = target.value
                if is_import_path(target):
                    what = "assignment to the import path"
        elif isinstance(node, ast.Attribute | ast.Name | ast.alias):
            word = {ast.Attribute: "attr", ast.Name: "id", ast.alias: "name"}[type(node)]
            identifier = getattr(node, word).rsplit(".", 1)[-1]
            if identifier in LOADERS:
                what = f"{identifier} (a module loaded from a file path)"
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if IN_TEXT.search(node.value):
                what = "code in a string that edits the import path or loads a file"
        if what is not None:
            found.append(f"{name}:{getattr(node, 'lineno', '?')}: {what}")
    return found


def text_edits(text: str, name: str) -> list[str]:
    """The lines of a shell script that edit the import path or load a file (:data:`IN_TEXT`)."""
    return [
        f"{name}:{number}: {line.strip()}"
        for number, line in enumerate(text.splitlines(), 1)
        if IN_TEXT.search(line)
    ]


def repository_files() -> list[Path]:
    """The repository's files (tracked or new, not ignored; every file outside
    :data:`SKIPPED` folders where git is not at hand)."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
            timeout=60,
        ).stdout
        return [ROOT / name for name in listed.split("\0") if name and (ROOT / name).is_file()]
    except (OSError, subprocess.SubprocessError):
        return [
            path
            for path in ROOT.rglob("*")
            if path.is_file() and not SKIPPED & set(path.relative_to(ROOT).parts)
        ]


def scripts() -> tuple[list[Path], list[Path]]:
    """The repository's Python files and shell scripts (by extension or ``#!`` line)."""
    python, shell = [], []
    for path in repository_files():
        if path.suffix == ".py":
            python.append(path)
        elif path.suffix == ".sh":
            shell.append(path)
        elif not path.suffix:
            with path.open("rb") as handle:
                first = handle.readline(200)
            if first.startswith(b"#!"):
                (python if b"python" in first else shell).append(path)
    return python, shell


def test_no_file_edits_the_import_path_or_loads_a_module_from_a_file():
    python, shell = scripts()
    assert len(python) > 100 and ROOT / "reproduce" / "figS9.py" in python
    assert ROOT / "reproduce" / "figS9.sh" in shell and ROOT / ".ci" / "run" in shell
    found = []
    for path in python:
        found += path_edits(path.read_text(), str(path.relative_to(ROOT)))
    for path in shell:
        found += text_edits(path.read_text(), str(path.relative_to(ROOT)))
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    "source",
    [
        f"import sys\n{IMPORT_PATH}.insert(0, 'reproduce')\n",
        f"import sys\n{IMPORT_PATH}.append('benchmarks')\n",
        f"import sys\n{IMPORT_PATH}.extend(['a', 'b'])\n",
        f"import sys\n{IMPORT_PATH} = ['a'] + {IMPORT_PATH}\n",
        f"import sys\n{IMPORT_PATH}[:0] = ['a']\n",
        f"import sys\n{IMPORT_PATH} += ['a']\n",
        "from importlib import util\nspec = util.spec_from_file_" + "location('x', 'x.py')\n",
        "from importlib." + "util import spec_from_file_" + "location\n",
        "import runpy\nrunpy.run_" + "path('benchmarks/common.py')\n",
        f"code = 'import sys; {IMPORT_PATH}.insert(0, \"tests\")'\n",
    ],
)
def test_every_kind_of_edit_is_found(source):
    (line,) = path_edits(source)
    assert line.startswith("<source>:")


@pytest.mark.parametrize(
    "source",
    [
        f"import sys\nprint(list({IMPORT_PATH}))\n",
        f"import sys\nfirst = {IMPORT_PATH}[0]\n",
        "import os\nenv = {**os.environ, 'PYTHONPATH': 'tests'}\n",
        "from fgat.app.recipes import optics\noptics.recipe_configs('figS9', True)\n",
        "import importlib\nmodule = importlib.import_module('fgat.recon')\n",
    ],
)
def test_reading_the_path_and_importing_by_name_are_not_edits(source):
    assert path_edits(source) == []


def test_shell_text_is_searched_line_by_line():
    script = f"set -e\npython -c \"import sys; {IMPORT_PATH}.append('x')\"\npython -m fgat\n"
    assert text_edits(script, "a.sh") == [f"a.sh:2: {script.splitlines()[1]}"]
    assert text_edits("PYTHONPATH=. python reproduce/figS9.py\n", "b.sh") == []
