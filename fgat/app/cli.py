"""``python -m fgat``: the command line.

Subcommands import what they need when they run, so ``fgat design`` answers without loading
PyTorch.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from functools import partial

from fgat import __version__
from fgat._core.heap import retain_freed_memory
from fgat.app import pipeline, sweep, tracking_server
from fgat.app.arguments import LIGHTNING_COMMANDS, plain_help
from fgat.app.commands.analyze import add_analyze
from fgat.app.commands.data import (
    add_calibrate,
    add_calibrate_depth,
    add_deconvolve,
    add_simulate,
)
from fgat.app.commands.optics import add_design, add_psf
from fgat.app.process import exit_without_finalising, report_errors, run_lightning_command


def build_parser() -> argparse.ArgumentParser:
    """``python -m fgat``'s parser: one subcommand per command family, each with a one-line
    ``help`` and its help as plain text (:func:`fgat.app.arguments.plain_help`); the
    LightningCLI subcommands are listed, their options are LightningCLI's."""
    parser = argparse.ArgumentParser(
        prog="fgat",
        description="fgat: 4DGAT reconstruction of Fourier light-field microscopy volumes. "
        "'python -m fgat SUBCOMMAND --help' lists the options of one.",
    )
    parser.add_argument("--version", action="version", version=f"fgat {__version__}")
    subparsers = parser.add_subparsers(title="subcommands", dest="command", required=True)
    for command, text in LIGHTNING_COMMANDS.items():
        subparsers.add_parser(command, help=text, add_help=False)
    add_design(subparsers)
    add_psf(subparsers)
    add_simulate(subparsers)
    add_calibrate(subparsers)
    add_calibrate_depth(subparsers)
    add_deconvolve(subparsers)
    add_analyze(subparsers)
    pipeline.add_parser(subparsers)
    sweep.add_parser(subparsers)
    tracking_server.add_parser(subparsers)
    plain_help(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run a subcommand (:func:`fgat.app.process.report_errors`: a user error ends with one
    line and exit code 2). The process keeps freed host memory for its next allocations
    (:func:`fgat._core.heap.retain_freed_memory`)."""
    words = list(sys.argv[1:] if argv is None else argv)
    retain_freed_memory()
    return report_errors(words[0] if words else "", partial(run_command, words, argv is None))


def run_command(words: Sequence[str], from_sys_argv: bool = False) -> int:
    """Run the subcommand ``words`` (``["deconvolve", "--measurement", ...]``) in this process
    and return its exit code; errors are raised, not reported (:func:`main` reports them). The
    napari widgets run commands with it in a worker thread (:mod:`fgat.app.monitor`)."""
    words = list(words)
    if words and words[0] in LIGHTNING_COMMANDS:
        return run_lightning_command(words, from_sys_argv)
    parser = build_parser()
    parser.set_defaults(run_command=main)  # trials run in this process (fgat.app.trials)
    args, unknown = parser.parse_known_args(words)
    if unknown and not getattr(args, "forwards_unknown", False):
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.extra = unknown
    return args.run(args)


def run_command_line() -> None:
    """``python -m fgat`` and the ``fgat`` command: :func:`main` on ``sys.argv``, then
    :func:`exit_without_finalising`."""
    exit_without_finalising(main())
