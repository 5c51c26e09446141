"""Trials: independent runs of fgat's command line, in parallel on Ray or one after another.

Where they run (:class:`Fanout`): with ``--parallel 1`` one after another in this process;
otherwise as Ray tasks, each trial a ``python -m fgat ...`` process holding ``--cpus-per-trial``
CPUs (also its ``OMP_NUM_THREADS``) and ``--gpus-per-trial`` GPUs (default: one when the Ray
cluster has GPUs), its output in ``trial.log`` of its folder. Without ``--address`` Ray starts on
this machine (and stops after the trials); ``--address auto`` or ``ray://host:port`` joins a
running cluster, whose nodes must see this folder (a shared file system) and have fgat
installed. Parallel trials on this machine that log to a SQLite file log through a tracking
server started for their duration (:func:`fgat.tracking_server.starting_server`); on a cluster they
log to the ``http://`` server given as ``--mlflow.tracking_uri``. A failed trial is reported and
run once more (a fit resumes from its ``last.ckpt``); one that fails twice is listed at the end.
Ctrl-C or SIGTERM stops the running trials, Ray and the tracking server. Ray is optional
(``pip install -e ".[cluster]"``): without it the trials run one after another.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from fgat.fingerprint import Fingerprint, fingerprint, resume_checkpoint

LOG = "trial.log"


@dataclass(frozen=True)
class Trial:
    """One run of fgat's command line.

    Attributes
    ----------
    name : str
        For progress lines and the summary.
    words : tuple of str
        The command line after ``python -m fgat`` (``fit ...`` or ``pipeline ...``).
    folder : Path
        Where it runs; its output goes to ``folder/trial.log`` when it runs as a process.
    tracking_uri, experiment : str
        Where it logs.
    fingerprint : Fingerprint or None
        A fit's: a retry resumes from the ``last.ckpt`` of the same fingerprint in ``folder``.
    """

    name: str
    words: tuple[str, ...]
    folder: Path
    tracking_uri: str
    experiment: str
    fingerprint: Fingerprint | None = field(default=None, compare=False)

    def command(self, *extra: str) -> list[str]:
        """The command line, resuming a fit from its checkpoint when one was saved."""
        checkpoint = None
        if self.fingerprint is not None:
            checkpoint = resume_checkpoint(self.folder, self.fingerprint)
        resume = [] if checkpoint is None else ["--ckpt_path", str(checkpoint)]
        return [*self.words, *extra, *resume]


def fit_trial(
    words: Sequence[str],
    folder: str | Path | None = None,
    *,
    name: str = "trial",
    refit: bool = False,
) -> Trial | None:
    """The trial ``fgat fit ...`` (``words``) in ``<folder>-<fingerprint[:8]>``, or ``None``
    (and a line saying so) when a finished MLflow run of its experiment carries the same
    fingerprint, unless ``refit``. ``folder`` defaults to ``<root>/<name>``, ``<root>`` the
    configuration's ``trainer.default_root_dir`` else ``runs/<experiment>``. The configuration
    is resolved and checked here, before any trial starts."""
    from fgat.callbacks.mlflow import finished_fingerprints
    from fgat.lightning_cli import resolved_config, tracking_uri

    if not words or words[0] != "fit":
        raise ValueError(f"a fit trial's command line starts with 'fit', got {list(words)[:1]}")
    config = resolved_config(list(words))
    fp = fingerprint(config)
    uri, experiment = tracking_uri(config["mlflow"]["tracking_uri"]), config["mlflow"]["experiment"]
    if folder is None:
        root = (config.get("trainer") or {}).get("default_root_dir") or f"runs/{experiment}"
        folder = Path(root) / name
    folder = Path(folder)
    if not refit and fp.digest in finished_fingerprints(uri, experiment):
        print(
            f"{experiment}: {folder.name} finished before with this configuration "
            f"(fingerprint {fp.short}): skipped (--refit to redo it)"
        )
        return None
    folder = folder.with_name(f"{folder.name}-{fp.short}")
    return Trial(
        folder.name,
        (*words, f"--trainer.default_root_dir={folder}"),
        folder,
        uri,
        experiment,
        fp,
    )


@dataclass(frozen=True)
class Fanout:
    """Where trials run.

    Attributes
    ----------
    parallel : int or None
        Trials at once; ``1``: one after another in this process (no Ray); ``None``: as many as
        Ray's resources allow.
    address : str or None
        A running Ray cluster (``auto``, ``ray://host:port``); ``None``: Ray on this machine.
    gpus_per_trial : float or None
        ``None``: one GPU per trial when the cluster has GPUs, else none.
    cpus_per_trial : float
        Also the trial's ``OMP_NUM_THREADS`` (at least 1).
    """

    parallel: int | None = 1
    address: str | None = None
    gpus_per_trial: float | None = None
    cpus_per_trial: float = 1.0

    @property
    def serial(self) -> bool:
        return self.parallel == 1 and self.address is None


def add_fanout_arguments(parser: argparse.ArgumentParser, parallel_default: str = "1") -> None:
    """``--parallel``, ``--address``, ``--gpus-per-trial`` and ``--cpus-per-trial``."""
    parser.add_argument(
        "--parallel",
        default=parallel_default,
        metavar="N|auto",
        help="trials at once on Ray; 1: one after another in this process; auto: as many as "
        f"the resources allow (default {parallel_default})",
    )
    parser.add_argument(
        "--address", default=None, help="a running Ray cluster: auto or ray://HOST:PORT"
    )
    parser.add_argument(
        "--gpus-per-trial",
        type=float,
        default=None,
        help="GPUs each trial holds (default: 1 when the Ray cluster has GPUs, else 0)",
    )
    parser.add_argument("--cpus-per-trial", type=float, default=1.0, help="default 1")


def fanout_from(args: argparse.Namespace) -> Fanout:
    """The :class:`Fanout` of parsed :func:`add_fanout_arguments` options, checked."""
    text = str(args.parallel)
    try:
        parallel = None if text == "auto" else int(text)
    except ValueError:
        parallel = 0
    if parallel is not None and parallel < 1:
        raise ValueError(f"--parallel {text!r}: expected a whole number >= 1 or auto")
    if args.cpus_per_trial <= 0 or (args.gpus_per_trial is not None and args.gpus_per_trial < 0):
        raise ValueError("--cpus-per-trial must be > 0 and --gpus-per-trial >= 0")
    return Fanout(parallel, args.address, args.gpus_per_trial, args.cpus_per_trial)


@dataclass(frozen=True)
class Outcome:
    """How a trial ended: ``finished`` or ``failed`` (exit code of its last attempt)."""

    trial: Trial
    returncode: int
    attempts: int
    seconds: float
    log: Path | None = None

    @property
    def finished(self) -> bool:
        return self.returncode == 0


def run_trials(trials: Sequence[Trial], fanout: Fanout, label: str = "fgat sweep") -> list[Outcome]:
    """Run ``trials`` where ``fanout`` says, each failed one once more; a progress line per
    finished trial and a summary at the end. Returns every trial's outcome."""
    if not trials:
        print(f"{label}: nothing to run")
        return []
    if not fanout.serial and not ray_available():
        if fanout.address is not None:
            raise ValueError(f"--address {fanout.address}: Ray is not installed ({CLUSTER_HINT})")
        print(f"{label}: Ray is not installed: the trials run one after another ({CLUSTER_HINT})")
        fanout = Fanout()
    run = _run_serially if fanout.serial else _run_on_ray
    outcomes = run(list(trials), fanout, label)
    print_summary(outcomes, label)
    return outcomes


CLUSTER_HINT = 'pip install -e ".[cluster]" runs them in parallel'


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _progress(label: str, done: int, total: int, outcome: Outcome) -> str:
    state = "finished" if outcome.finished else f"failed (exit code {outcome.returncode})"
    return f"{label} [{done}/{total}] {outcome.trial.name}: {state} in {outcome.seconds:.0f} s"


def _run_serially(trials: list[Trial], fanout: Fanout, label: str) -> list[Outcome]:
    from fgat.cli import main

    outcomes = []
    for done, trial in enumerate(trials, 1):
        for attempt in (1, 2):
            start = time.monotonic()
            try:
                code = main(trial.command())
            except SystemExit as error:  # an argument parser's exit
                code = error.code if isinstance(error.code, int) else 1
            except Exception:  # noqa: BLE001 - reported, retried once, then listed as failed
                traceback.print_exc()
                code = 1
            if code in INTERRUPTED_CODES:  # Ctrl-C or SIGTERM stopped it: stop the trials
                raise KeyboardInterrupt(f"{trial.name}: stopped by a signal")
            outcome = Outcome(trial, code, attempt, time.monotonic() - start)
            if outcome.finished or attempt == 2:
                break
            print(f"{label}: {trial.name} failed ({_failure(outcome)}): running it once more")
        outcomes.append(outcome)
        print(_progress(label, done, len(trials), outcome), flush=True)
    return outcomes


def run_command(words: list[str], cwd: str, log: str, threads: int) -> int:
    """Run ``python -m fgat <words>`` in ``cwd``, its output appended to ``log``; the exit code.
    The body of a Ray task: it runs on whichever node Ray chose."""
    if not Path(cwd).is_dir():
        return 127  # this node does not see the sweep's folder
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"}
    with open(log, "a") as output:
        output.write(f"$ python -m fgat {' '.join(words)}\n")
        output.flush()
        command = [sys.executable, "-m", "fgat", *words]
        return subprocess.run(
            command,
            cwd=cwd,
            stdout=output,
            stderr=subprocess.STDOUT,
            env=environment,
            preexec_fn=_stop_with_parent if sys.platform.startswith("linux") else None,
        ).returncode


def _stop_with_parent() -> None:
    """In a trial's process, before it runs: be sent SIGTERM when the Ray worker that started
    it dies (a cancelled sweep, Ray shut down), instead of running on unowned (Linux
    ``PR_SET_PDEATHSIG``)."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


def _run_on_ray(trials: list[Trial], fanout: Fanout, label: str) -> list[Outcome]:
    import contextlib

    import ray

    from fgat.callbacks.mlflow import ensure_store
    from fgat.tracking_server import starting_server

    files = sorted({t.tracking_uri for t in trials if t.tracking_uri.startswith("sqlite")})
    if files and fanout.address is not None:
        raise ValueError(
            f"--mlflow.tracking_uri {files[0]}: trials on a Ray cluster log over HTTP; start "
            "python -m fgat tracking-server --host 0.0.0.0 and pass --mlflow.tracking_uri "
            "http://<its host>:5000"
        )
    for uri, experiment in {(t.tracking_uri, t.experiment) for t in trials}:
        ensure_store(uri, experiment)  # created by one process, before the trials start
    started = not ray.is_initialized()
    replaced = _interrupt_on_sigterm()
    try:
        with contextlib.ExitStack() as stack:
            # the servers start while Ray does; each is waited for before the first trial
            pending = {uri: stack.enter_context(starting_server(uri)) for uri in files}
            if started:
                ray.init(address=fanout.address, include_dashboard=False, log_to_driver=False)
                _interrupt_on_sigterm()  # ray.init replaces the handler with its own
            task = _ray_task(ray, fanout, label)
            servers = {uri: ready() for uri, ready in pending.items()}
            for uri, server in servers.items():
                print(f"{label}: the trials log to {uri} through {server}", flush=True)
            return _dispatch(ray, task, trials, fanout, servers, label)
    finally:
        if started:
            ray.shutdown()
        if replaced is not None:
            signal.signal(signal.SIGTERM, replaced)


def interrupt(number: int, frame=None) -> None:
    """A signal handler that interrupts this process as Ctrl-C does (``KeyboardInterrupt``)."""
    raise KeyboardInterrupt(f"signal {number}")


class Interrupted(Exception):
    """A run stopped by SIGINT (Ctrl-C) or SIGTERM; the command line exits with
    :attr:`exit_code`, 128 + the signal number (130 for SIGINT, 143 for SIGTERM), as a shell
    reports a process the signal ended."""

    def __init__(self, number: int, message: str) -> None:
        super().__init__(message)
        self.number = number

    @property
    def exit_code(self) -> int:
        return 128 + self.number


INTERRUPTED_CODES = (128 + signal.SIGINT, 128 + signal.SIGTERM)
"""Exit codes of a command stopped by SIGINT or SIGTERM (:class:`Interrupted`)."""


def set_handler(number: int, handler):
    """Install ``handler`` for signal ``number``; the handler it replaced, or ``None`` outside
    the main thread, where handlers cannot be set."""
    try:
        return signal.signal(number, handler)
    except ValueError:
        return None


def _interrupt_on_sigterm():
    """Make SIGTERM (``kill``, SLURM's ``scancel``) interrupt this process as Ctrl-C does, so
    that the running trials are cancelled and Ray and the tracking server stopped; returns the
    handler it replaced (``None`` outside the main thread, where handlers cannot be set)."""
    return set_handler(signal.SIGTERM, interrupt)


def _ray_task(ray, fanout: Fanout, label: str):
    """:func:`run_command` as a Ray task holding the trial's resources (checked against this
    machine's when Ray runs here)."""
    resources = ray.cluster_resources()
    gpus = fanout.gpus_per_trial
    if gpus is None:
        gpus = 1.0 if resources.get("GPU", 0) >= 1 else 0.0
    if fanout.address is None:
        for name, wanted in (("CPU", fanout.cpus_per_trial), ("GPU", gpus)):
            if wanted > resources.get(name, 0):
                raise ValueError(
                    f"--{name.lower()}s-per-trial {wanted:g}: this machine has "
                    f"{resources.get(name, 0):g} {name}s"
                )
    print(
        f"{label}: Ray with {resources.get('CPU', 0):g} CPUs and {resources.get('GPU', 0):g} GPUs; "
        f"{fanout.cpus_per_trial:g} CPUs and {gpus:g} GPUs per trial",
        flush=True,
    )
    return ray.remote(run_command).options(
        num_cpus=fanout.cpus_per_trial, num_gpus=gpus, max_retries=0
    )


def _dispatch(ray, task, trials, fanout, servers, label) -> list[Outcome]:
    """Submit the trials (at most ``fanout.parallel`` at once), each failed one once more."""
    cwd, threads = os.getcwd(), max(1, int(fanout.cpus_per_trial))
    queue = [(trial, 1) for trial in trials]
    running, outcomes = {}, {}
    limit = fanout.parallel or len(trials)
    try:
        while queue or running:
            while queue and len(running) < limit:
                trial, attempt = queue.pop(0)
                extra = ["--trainer.enable_progress_bar=false"]
                if trial.tracking_uri in servers:
                    extra.append(f"--mlflow.tracking_uri={servers[trial.tracking_uri]}")
                log = str((trial.folder / LOG).absolute())  # appended to by the retry
                reference = task.remote(trial.command(*extra), cwd, log, threads)
                running[reference] = (trial, attempt, time.monotonic())
            done, _ = ray.wait(list(running), num_returns=1)
            trial, attempt, start = running.pop(done[0])
            try:
                code = ray.get(done[0])
            except ray.exceptions.RayError as error:  # the worker died (killed, out of memory)
                print(f"{label}: {trial.name}: {str(error).strip().splitlines()[0]}")
                code = 1
            seconds = time.monotonic() - start
            outcome = Outcome(trial, code, attempt, seconds, trial.folder / LOG)
            if not outcome.finished and attempt == 1:
                print(f"{label}: {trial.name} failed ({_failure(outcome)}): running it once more")
                queue.append((trial, 2))
                continue
            outcomes[trial] = outcome
            print(_progress(label, len(outcomes), len(trials), outcome), flush=True)
    except KeyboardInterrupt:
        for reference in running:
            ray.cancel(reference, force=True)
        raise
    return [outcomes[trial] for trial in trials]


def _failure(outcome: Outcome) -> str:
    """The exit code and where the output is (or why there is none)."""
    if outcome.log is None:
        return f"exit code {outcome.returncode}, output above"
    if outcome.returncode == 127:
        return f"the Ray node does not see {os.getcwd()}: run the sweep from a shared folder"
    return f"exit code {outcome.returncode}, output in {outcome.log}"


def print_summary(outcomes: Sequence[Outcome], label: str) -> None:
    """One line per trial, failed ones with where their output is."""
    failed = [o for o in outcomes if not o.finished]
    print(f"{label}: {len(outcomes) - len(failed)} of {len(outcomes)} trials finished")
    for outcome in failed:
        print(f"  {outcome.trial.name}: failed twice ({_failure(outcome)})")


class TrialsFailed(RuntimeError):
    """Trials failed twice; their names and logs were listed by :func:`run_trials`."""


def require_finished(outcomes: Sequence[Outcome]) -> None:
    """Raise :class:`TrialsFailed` when a trial failed (a recipe cannot summarise missing
    runs)."""
    failed = [o.trial.name for o in outcomes if not o.finished]
    if failed:
        raise TrialsFailed(f"{len(failed)} trial(s) failed twice: {', '.join(failed)}")


def run_fits(
    fits: Sequence[tuple[Sequence[str], str | Path]],
    fanout: Fanout,
    *,
    refit: bool = False,
    label: str = "fgat sweep",
) -> list[Outcome]:
    """A recipe's fits: ``(words, folder)`` pairs as :func:`fit_trial` trials (the finished ones
    skipped) run by :func:`run_trials`; raises when one failed twice."""
    trials = [fit_trial(words, folder, refit=refit) for words, folder in fits]
    outcomes = run_trials([trial for trial in trials if trial is not None], fanout, label)
    require_finished(outcomes)
    return outcomes
