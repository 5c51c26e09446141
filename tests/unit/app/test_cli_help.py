"""``--help`` of every ``python -m fgat`` subcommand: plain text, a one-line summary, only the
subcommand's own options; every option a hint names exists on the command that prints it."""

from __future__ import annotations

import argparse
import ast
import inspect
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fgat.app import pipeline, report, trials
from fgat.app.arguments import LIGHTNING_COMMANDS, describe, plain_inline, plain_text
from fgat.app.cli import build_parser, main
from fgat.app.commands import data as data_commands
from fgat.recon import costs

ROOT = Path(__file__).resolve().parents[3]
REPRODUCE = ROOT / "reproduce"

REST = re.compile(r":(?:func|class|mod|meth|attr|data|obj|exc|paramref|ref):`|``|`_")
"""reST markup that must not reach a help text: roles, double back-quotes, links."""

OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9_-]*[a-z0-9](?![\w.=-])")
"""An option named in a message (``--refit``); not a command word (``--trainer.x=1``)."""


def subcommands(parser: argparse.ArgumentParser, path=()):
    """``(words, parser, summary)`` of every subcommand (nested ones too) whose help argparse
    prints (the LightningCLI ones are listed without options)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            summaries = {choice.dest: choice.help for choice in action._choices_actions}
            for name, sub in action.choices.items():
                yield (*path, name), sub, summaries[name]
                yield from subcommands(sub, (*path, name))


ARGPARSE_COMMANDS = [
    (words, summary) for words, sub, summary in subcommands(build_parser()) if sub.add_help
]


def help_of(capsys, words) -> str:
    """What ``python -m fgat WORDS --help`` prints."""
    with pytest.raises(SystemExit) as stopped:
        main([*words, "--help"])
    assert stopped.value.code == 0
    return capsys.readouterr().out


@pytest.fixture(scope="module")
def lightning_help() -> dict[str, str]:
    """``--help`` of fit, validate, test and predict, from LightningCLI in this process."""
    import contextlib
    import io

    from fgat.app.lightning_cli import run

    texts = {}
    for command in LIGHTNING_COMMANDS:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
            run([command, "--help"])
        texts[command] = out.getvalue()
    return texts


def test_plain_text_removes_rest_markup():
    doc = """First ``python -m fgat`` line with :func:`fgat.app.trials.fit_trial` and
    :class:`~fgat.app.trials.Fanout`, a :paramref:`~lightning.Trainer.max_steps`, `s3://b/p`
    and `the notes <https://example.org/n>`_.

    * one item
      continued
    * two::

        python -m fgat fit --config a.yaml
    """
    assert plain_text(doc) == (
        "First python -m fgat line with fgat.app.trials.fit_trial and Fanout, a max_steps, "
        "s3://b/p and the notes (https://example.org/n).\n\n"
        "* one item continued\n* two:\n\n"
        "    python -m fgat fit --config a.yaml"
    )
    assert plain_inline(":meth:`scaled <fgat.recon.shb>` ``'auto'``") == "scaled 'auto'"
    assert describe("a grid of runs", None) == "A grid of runs."


def test_top_level_lists_each_subcommand_on_one_line(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    text = help_of(capsys, [])
    listing = text.split("subcommands:", 1)[1]
    for name, summary in [(w[0], s) for w, _, s in subcommands(build_parser()) if len(w) == 1]:
        assert re.search(rf"^    {re.escape(name)} +{re.escape(summary)}$", listing, re.M), name
    nested = help_of(capsys, ["analyze"]).split("analyses:", 1)[1]
    for words, summary in ARGPARSE_COMMANDS:
        if words[0] == "analyze" and len(words) == 2:
            assert re.search(rf"^    {words[1]} +{re.escape(summary)}$", nested, re.M), words


@pytest.mark.parametrize(
    "words,summary", ARGPARSE_COMMANDS, ids=[" ".join(words) for words, _ in ARGPARSE_COMMANDS]
)
def test_subcommand_help_is_plain_with_its_summary(capsys, monkeypatch, words, summary):
    monkeypatch.setenv("COLUMNS", "100")
    text = help_of(capsys, words)
    assert not REST.search(text), REST.search(text).group(0)
    assert "%%" not in text
    description = text.split("\n\n", 2)[1]
    assert description == describe(summary), description
    parser = next(sub for w, sub, _ in subcommands(build_parser()) if w == words)
    silent = [
        a.option_strings[-1]
        for a in parser._actions
        if a.option_strings and not a.help and a.dest != "help"
    ]
    assert not silent, f"options without help: {silent}"


def test_fanout_defaults_agree():
    """``--parallel`` and the other trial options read the same in every command that has them,
    and ``--parallel`` defaults to 1 (one trial at a time, safe on any machine)."""
    seen = {}
    for words, sub, _ in subcommands(build_parser()):
        for action in sub._actions:
            if action.option_strings and action.dest != "help":
                seen.setdefault(action.option_strings[-1], set()).add(
                    (repr(action.default), action.help)
                )
    for option in ("--parallel", "--address", "--gpus-per-trial", "--cpus-per-trial", "--refit"):
        assert len(seen[option]) == 1, option
    assert next(iter(seen["--parallel"]))[0] == "'1'"
    assert len(seen["--device"]) == 1


@pytest.mark.parametrize("command", list(LIGHTNING_COMMANDS))
def test_lightning_help(lightning_help, command):
    text = lightning_help[command]
    assert not REST.search(text), REST.search(text).group(0)
    assert describe(LIGHTNING_COMMANDS[command]) in " ".join(text.split())
    assert "Model hub" not in text and "<class '" not in text
    accelerator = re.search(
        r"^  --trainer\.accelerator ACCELERATOR\n(.*?)\n  --", text, re.M | re.S
    )
    assert "where the run computes" in accelerator.group(1)
    options = set(re.findall(r"^  (--[\w.]+)", text, re.M))
    assert ({"--times", "--out", "--overwrite"} <= options) == (command == "predict")
    assert not {"--times", "--out", "--overwrite"} & options or command == "predict"
    assert "--checkpoint_every" in options  # fit's, in configs that validate and predict read


def test_fit_refuses_predict_options():
    from fgat.app.lightning_cli import PREDICT_ONLY, run

    for option in PREDICT_ONLY:
        with pytest.raises(ValueError, match=f"belong to 'predict'.*; {option} is no option of"):
            run(["fit", option, "x"] if option != "--overwrite" else ["fit", option])


def hint_options(function) -> set[str]:
    """The options named in the strings of ``function``'s body (its docstring left out)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
    body = tree.body[0].body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]
    found = set()
    for node in ast.walk(ast.Module(body=body, type_ignores=[])):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            found.update(OPTION.findall(node.value))
    return found


def fgat_options(words) -> set[str]:
    parser = next(sub for w, sub, _ in subcommands(build_parser()) if w == tuple(words))
    return {option for action in parser._actions for option in action.option_strings}


def script_options(paths: list[Path]) -> dict[str, set[str]]:
    """The options of reproduce/ scripts by file name, read from the option lines of their
    ``--help``; the scripts start at once (each spends its time importing)."""
    processes = {
        path.name: subprocess.Popen(
            [sys.executable, str(path), "--help"], stdout=subprocess.PIPE, text=True, cwd=ROOT
        )
        for path in paths
    }
    options = {}
    for name, process in processes.items():
        stdout, _ = process.communicate(timeout=300)
        assert process.returncode == 0, name
        options[name] = set(re.findall(r"^  (?:-\w[ \w]*, )?(--[\w-]+)", stdout, re.M))
    return options


def runs_fit_trials(path: Path) -> bool:
    """Whether a reproduce/ script runs fit trials, itself or through the fgat.app.recipes
    module it calls."""
    text = path.read_text()
    for module in re.findall(r"from fgat\.app\.recipes\.(\w+) import", text):
        text += (ROOT / "fgat" / "app" / "recipes" / f"{module}.py").read_text()
    return bool(re.search(r"\b(run_fits|fit_trial)\(", text))


@pytest.mark.slow
def test_hints_name_options_of_their_command():
    """Each message that tells the user to pass an option is printed only by commands that
    have it: the skip line of a finished fit trial (``--refit``) by sweep and by every recipe
    that runs fit trials, the others by the commands that call them."""
    printers = {
        trials.fit_trial: [("sweep",)],
        trials.run_trials: [("sweep",), ("pipeline",)],
        pipeline.parse_channels: [("pipeline",)],
        costs.check_long_run: [("deconvolve",)],
        report.deconvolution_ending: [("deconvolve",)],
        data_commands._run_deconvolve: [("deconvolve",)],  # the cost estimate's levers
    }
    assert hint_options(trials.fit_trial) == {"--refit"}
    for function, commands in printers.items():
        named = hint_options(function)
        assert named, function.__name__
        for words in commands:
            missing = named - fgat_options(words)
            assert not missing, f"{function.__name__} names {missing}, not options of {words}"
    recipes = [path for path in sorted(REPRODUCE.glob("*.py")) if runs_fit_trials(path)]
    assert {path.name for path in recipes} >= {"figS9.py", "optics.py", "fig3j.py"}
    for name, options in script_options(recipes).items():
        missing = hint_options(trials.fit_trial) - options
        assert not missing, f"{name} runs fit trials, whose skip line names {missing}"
