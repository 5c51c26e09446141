"""How an fgat process ends: the errors reported as one line (exit code 2), the exit that
skips module finalisation, and recipes run as commands.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
import threading
from collections.abc import Callable

from fgat.app.signals import Interrupted, StopSignals
from fgat.io.yaml_files import check_config_files


class TrialsFailed(RuntimeError):
    """Trials failed twice; their names and logs were listed by
    :func:`fgat.app.trials.run_trials`."""


USER_ERRORS = (ValueError, FileNotFoundError, FloatingPointError, TrialsFailed)


def report_errors(command: str, body: Callable[[], int]) -> int:
    """Run ``body`` (a command of ``python -m fgat``) and return its exit code; a user error
    (bad input, a diverged fit) ends with one line and exit code 2, or with the full traceback
    when ``FGAT_TRACEBACK=1``; a stop by SIGINT or SIGTERM with one line and 128 + the signal."""
    try:
        return body()
    except Interrupted as stop:
        print(f"fgat {command}: {stop}", file=sys.stderr)
        return stop.exit_code
    except USER_ERRORS as error:
        if os.environ.get("FGAT_TRACEBACK") == "1":
            raise
        print(f"fgat {command}: error: {error}", file=sys.stderr)
        return 2


def run_lightning_command(words: list[str], from_sys_argv: bool = False) -> int:
    """Run a Lightning command line (``fit``, ``validate``, ``test``, ``predict`` and its
    options, ``words``) in this process, its ``--config`` files checked first, seconds before
    Lightning is imported; with ``from_sys_argv`` LightningCLI reads ``sys.argv`` itself.
    Returns 0 (a failure raises)."""
    check_config_files(words)
    from fgat.app.lightning_cli import run  # imported when used: keeps start-up fast

    run(None if from_sys_argv else words)
    return 0


def exit_without_finalising(code: int) -> None:
    """End the process with exit status ``code`` as Python's own exit does (shut down the
    thread pools and wait for the non-daemon threads, run the ``atexit`` handlers: MLflow's,
    logging's, multiprocessing's, Ray's; flush stdout and stderr), but skip the finalisation of
    every module that torch, Lightning and MLflow import, which takes seconds after a fit has
    written everything (``python benchmarks/startup.py`` measures it). fgat closes each file it
    writes when the write ends, so nothing is left for that finalisation to flush.

    The threads are ended by the interpreter's own first step of exiting (``threading``'s
    shutdown): it tells idle thread-pool workers (MLflow's artifact downloads keep some) to
    stop before it joins them, where joining them directly would wait for ever."""
    threading._shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def run_recipe(main: Callable[[], object], label: str) -> None:
    """Run a recipe's ``main`` (``reproduce/*.py``) as ``python -m fgat`` runs a command, then
    exit (:func:`exit_without_finalising`): SIGINT or SIGTERM ends it for good with one line
    and exit code 130 or 143 (:class:`StopSignals`: the trial under way stopped, its
    MLflow run KILLED, no further trial started), a user error (a bad tracking URI, trials that
    failed twice) with one line and exit code 2 (the traceback with ``FGAT_TRACEBACK=1``)."""
    from fgat.app.process import (  # imported when used: keeps start-up fast
        USER_ERRORS,
        exit_without_finalising,
    )

    code = 0
    try:
        with StopSignals():
            main()
    except Interrupted as stop:
        print(f"{label}: {stop}", file=sys.stderr)
        code = stop.exit_code
    except USER_ERRORS as error:
        if os.environ.get("FGAT_TRACEBACK") == "1":
            raise
        print(f"{label}: error: {error}", file=sys.stderr)
        code = 2
    exit_without_finalising(code)
