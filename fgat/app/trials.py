"""Trials: independent runs of fgat's command line, in parallel on Ray or one after another.

Where they run (:class:`Fanout`): with ``--parallel 1`` one after another in this process;
otherwise as Ray tasks, each trial a ``python -m fgat ...`` process holding ``--cpus-per-trial``
CPUs (also its ``OMP_NUM_THREADS``) and ``--gpus-per-trial`` GPUs (default: one when the Ray
cluster has GPUs), its output in ``trial.log`` of its folder. Without ``--address`` Ray starts on
this machine (and stops after the trials); ``--address auto`` or ``ray://host:port`` joins a
running cluster, whose nodes must see this folder (a shared file system) and have fgat
installed. Parallel trials on this machine that log to a SQLite file log through a tracking
server started for their duration (:func:`fgat.app.tracking_server.starting_server`); on a cluster
they log to the ``http://`` server given as ``--mlflow.tracking_uri``. A failed trial is reported
and run once more (a fit resumes from its ``last.ckpt``); one that fails twice is listed at the end.
Ctrl-C or SIGTERM stops the command for good (:class:`StopSignals`), with exit code 130 or 143
as a stopped fit: the trials under way stop as a stopped fit does (a checkpoint, their MLflow
runs KILLED; on Ray each is sent SIGTERM and given up to a minute, a second signal kills them at
once), none is run again or started after them, and Ray and the tracking server stop. Ray is
optional (``pip install -e ".[cluster]"``): without it the trials run one after another.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import functools
import os
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from fgat.app.fingerprint import Fingerprint, fingerprint, resume_checkpoint
from fgat.app.process import TrialsFailed, report_errors, run_lightning_command
from fgat.app.signals import INTERRUPTED_CODES, Interrupted, StopSignals, stopped_message

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
        """The command line, resuming a fit from the checkpoint of its unfinished run (a retry,
        a stopped sweep); a fit whose run finished before starts afresh."""
        checkpoint = None
        if self.fingerprint is not None:
            checkpoint = resume_checkpoint(self.folder, self.fingerprint, finished=False)
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
    from fgat.app.callbacks.mlflow import (  # imported when used: keeps start-up fast
        finished_fingerprints,
    )
    from fgat.app.lightning_cli import (  # imported when used: keeps start-up fast
        resolved_config,
        tracking_uri,
    )

    if not words or words[0] != "fit":
        raise ValueError(f"a fit trial's command line starts with 'fit', got {list(words)[:1]}")
    config = resolved_config(list(words))
    fp = fingerprint(config)
    uri, experiment = tracking_uri(config["mlflow"]["tracking_uri"]), config["mlflow"]["experiment"]
    if folder is None:
        root = (config.get("trainer") or {}).get("default_root_dir") or f"runs/{experiment}"
        folder = Path(root) / name
    folder = Path(folder)
    checked_store(uri, experiment)
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


@functools.cache
def checked_store(uri: str, experiment: str) -> None:
    """:func:`fgat.app.callbacks.mlflow.check_tracking_uri` once per store and experiment in this
    process (a sweep's trials share them): an unusable store fails in seconds with one line,
    before any trial is resolved further or run."""
    from fgat.app.callbacks.mlflow import (  # imported when used: keeps start-up fast
        check_tracking_uri,
    )

    check_tracking_uri(uri, experiment)


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
    run_command : callable or None
        Runs a trial's command line in this process (serial trials) and returns its exit code:
        ``python -m fgat``'s own dispatcher, which the command line passes in; ``None``: fit
        trials only (:func:`run_fit_command`).
    """

    parallel: int | None = 1
    address: str | None = None
    gpus_per_trial: float | None = None
    cpus_per_trial: float = 1.0
    run_command: Callable[[list[str]], int] | None = field(default=None, compare=False, repr=False)

    @property
    def serial(self) -> bool:
        return self.parallel == 1 and self.address is None


def add_fanout_arguments(parser: argparse.ArgumentParser) -> None:
    """``--parallel``, ``--address``, ``--gpus-per-trial`` and ``--cpus-per-trial`` (checked by
    :func:`fanout_from`), the same for every command that runs trials. ``--parallel`` defaults
    to 1: one trial's memory and devices at a time is safe on a laptop and on a shared node."""
    parser.add_argument(
        "--parallel",
        default="1",
        metavar="N|auto",
        help="trials at once on Ray; auto: as many as the CPUs and GPUs allow; 1 (default): one "
        "after another (in this process unless --address), as one trial's memory fits wherever "
        "fgat runs",
    )
    parser.add_argument(
        "--address", default=None, help="a running Ray cluster: auto or ray://HOST:PORT"
    )
    parser.add_argument(
        "--gpus-per-trial",
        default=None,
        help="GPUs each trial holds, >= 0 (default: 1 when the Ray cluster has GPUs, else 0)",
    )
    parser.add_argument(
        "--cpus-per-trial", default="1", help="CPUs each trial holds, > 0 (default 1)"
    )


def add_refit_argument(parser: argparse.ArgumentParser) -> None:
    """``--refit``: run again the fit trials that :func:`fit_trial` skips as finished."""
    parser.add_argument(
        "--refit",
        action="store_true",
        help="run again fit trials that finished before with the same configuration",
    )


def fanout_from(args: argparse.Namespace) -> Fanout:
    """The :class:`Fanout` of parsed :func:`add_fanout_arguments` options, checked: a bad one
    raises one ``ValueError`` naming the option and what it expects."""
    from fgat._core.validation import check_number  # imported when used: keeps start-up fast

    text = str(args.parallel)
    try:
        parallel = None if text == "auto" else int(text)
    except ValueError:
        parallel = 0
    if parallel is not None and parallel < 1:
        raise ValueError(f"--parallel {text!r}: expected a whole number >= 1 or auto")
    cpus = check_number("--cpus-per-trial", args.cpus_per_trial, above=0)
    gpus = args.gpus_per_trial
    if gpus is not None:
        gpus = check_number("--gpus-per-trial", gpus, minimum=0)
    return Fanout(parallel, args.address, gpus, cpus, getattr(args, "run_command", None))


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
        fanout = Fanout(run_command=fanout.run_command)
    if len(trials) > 1:
        print(f"{label}: {len(trials)} trials", flush=True)
    run = _run_serially if fanout.serial else _run_on_ray
    with StopSignals() as stop:
        outcomes = run(list(trials), fanout, label, stop)
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


def _run_serially(
    trials: list[Trial], fanout: Fanout, label: str, stop: StopSignals
) -> list[Outcome]:
    outcomes = []
    for done, trial in enumerate(trials, 1):
        for attempt in (1, 2):
            start, started_ms = time.monotonic(), now_ms()
            code = _attempt(trial, fanout.run_command or run_fit_command)
            number = stop.number or _signal_of(code)
            if number is not None:  # stopped by a signal: neither run again nor followed
                killed = mark_killed(trial, started_ms, ("RUNNING", "FAILED"))
                raise Interrupted(number, stopped_message(number, [trial.name], killed))
            outcome = Outcome(trial, code, attempt, time.monotonic() - start)
            if outcome.finished or attempt == 2:
                break
            print(f"{label}: {trial.name} failed ({_failure(outcome)}): running it once more")
        outcomes.append(outcome)
        print(_progress(label, done, len(trials), outcome), flush=True)
    return outcomes


def run_fit_command(words: list[str]) -> int:
    """Run a ``fit`` command line in this process (as ``python -m fgat fit`` does); its exit
    code."""
    if not words or words[0] != "fit":
        raise ValueError(f"{' '.join(words[:1])}: only fit trials run here without a dispatcher")
    return report_errors("fit", partial(run_lightning_command, words))


def _attempt(trial: Trial, run_command: Callable[[list[str]], int]) -> int:
    """Run ``trial`` in this process with ``run_command``; its exit code (1: it raised)."""
    try:
        return run_command(trial.command())
    except SystemExit as error:  # an argument parser's exit, or Lightning's on an interrupt
        return error.code if isinstance(error.code, int) else 1
    except KeyboardInterrupt:  # a signal outside a fit's own handling (StopSignals saw it)
        return 128 + signal.SIGINT
    except Exception:  # noqa: BLE001 - reported, retried once, then listed as failed
        traceback.print_exc()
        return 1


def _signal_of(code: int) -> int | None:
    """The signal that stopped a command exiting with ``code`` (:data:`INTERRUPTED_CODES`)."""
    return code - 128 if code in INTERRUPTED_CODES else None


def now_ms() -> int:
    """Now in ms since the epoch, as MLflow stamps a run's start."""
    return int(time.time() * 1000)


def mark_killed(
    trial: Trial, since_ms: int, statuses: Sequence[str], uri: str | None = None
) -> list[str]:
    """Mark KILLED the MLflow runs of ``trial`` (its fingerprint's, for a fit) started since
    ``since_ms`` and left in one of ``statuses``: runs that a signal stopped before their fit
    could end them (Lightning ends a fit interrupted before it trains FAILED; a process killed
    leaves its run RUNNING). ``uri`` defaults to the trial's. Their ids; none when the store
    does not answer at once (the command is stopping: it reports and exits all the same)."""
    import mlflow  # MLflow loaded when used: keeps start-up fast

    from fgat.app.callbacks.mlflow import (  # imported when used: keeps start-up fast
        FINGERPRINT,
        no_http_retries,
    )

    query = f"attributes.start_time >= {since_ms}"
    if trial.fingerprint is not None:
        query += f" and tags.`{FINGERPRINT}` = '{trial.fingerprint.digest}'"
    ids = []
    try:
        with no_http_retries():
            client = mlflow.MlflowClient(uri or trial.tracking_uri)
            experiment = client.get_experiment_by_name(trial.experiment)
            found = (
                [] if experiment is None else client.search_runs([experiment.experiment_id], query)
            )
            for run in found:
                if run.info.status in statuses:
                    client.set_terminated(run.info.run_id, "KILLED")
                    ids.append(run.info.run_id)
    except Exception as error:  # noqa: BLE001 - MLflow raises many types for a store that fails
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        print(
            f"{trial.name}: its MLflow runs could not be marked KILLED ({first})", file=sys.stderr
        )
    return ids


def run_command(words: list[str], cwd: str, log: str, threads: int) -> int:
    """Run ``python -m fgat <words>`` in ``cwd``, its output appended to ``log``; the exit code.
    The body of a Ray task: it runs on whichever node Ray chose. Cancelled (``ray.cancel``
    without ``force``: a stopped sweep), it sends the command SIGTERM and waits for it to stop
    as a stopped fit does (its MLflow run KILLED, its checkpoint written)."""
    if not Path(cwd).is_dir():
        return 127  # this node does not see the sweep's folder
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"}
    with open(log, "a") as output:
        output.write(f"$ python -m fgat {' '.join(words)}\n")
        output.flush()
        process = subprocess.Popen(
            [sys.executable, "-m", "fgat", *words],
            cwd=cwd,
            stdout=output,
            stderr=subprocess.STDOUT,
            env=environment,
            preexec_fn=_stop_with_parent if sys.platform.startswith("linux") else None,
        )
        try:
            while process.poll() is None:  # polled: a cancellation interrupts a sleep, not a wait
                time.sleep(0.2)
        except KeyboardInterrupt:
            process.send_signal(signal.SIGTERM)
            return process.wait()
        return process.returncode


def _stop_with_parent() -> None:
    """In a trial's process, before it runs: be sent SIGTERM when the Ray worker that started
    it dies (a cancelled sweep, Ray shut down), instead of running on unowned (Linux
    ``PR_SET_PDEATHSIG``)."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


def check_cluster_store(uris: Sequence[str], fanout: Fanout) -> None:
    """Trials on a Ray cluster (``fanout.address``) log over HTTP: refuse a SQLite store among
    ``uris`` at once, naming it and what to start instead."""
    files = sorted({uri for uri in uris if uri.startswith("sqlite")})
    if files and fanout.address is not None:
        raise ValueError(
            f"--mlflow.tracking_uri {files[0]}: trials on a Ray cluster log over HTTP; start "
            "python -m fgat tracking-server --host 0.0.0.0 and pass --mlflow.tracking_uri "
            "http://<its host>:5000"
        )


def _run_on_ray(
    trials: list[Trial], fanout: Fanout, label: str, stop: StopSignals
) -> list[Outcome]:
    import ray  # Ray is optional (the cluster extra)

    from fgat.app.tracking_server import starting_server  # imported when used: keeps start-up fast

    check_cluster_store([t.tracking_uri for t in trials], fanout)
    files = sorted({t.tracking_uri for t in trials if t.tracking_uri.startswith("sqlite")})
    for uri, experiment in {(t.tracking_uri, t.experiment) for t in trials}:
        checked_store(uri, experiment)  # created by one process, before the trials start
    started = not ray.is_initialized()
    try:
        with contextlib.ExitStack() as stack:
            # the servers start while Ray does; each is waited for before the first trial
            pending = {uri: stack.enter_context(starting_server(uri)) for uri in files}
            if started:
                ray.init(address=fanout.address, include_dashboard=False, log_to_driver=False)
                stop.install()  # ray.init replaces the handlers with its own
            task = _ray_task(ray, fanout, label)
            servers = {uri: ready() for uri, ready in pending.items()}
            for uri, server in servers.items():
                print(f"{label}: the trials log to {uri} through {server}", flush=True)
            return _dispatch(ray, task, trials, fanout, servers, label, stop)
    finally:
        if started:
            ray.shutdown()


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


STOP_GRACE_S = 60.0
"""How long stopped trials on Ray are given to stop as a stopped fit does (checkpoint, MLflow
run KILLED) before they are killed; a second signal kills them at once."""


def _dispatch(ray, task, trials, fanout, servers, label, stop: StopSignals) -> list[Outcome]:
    """Submit the trials (at most ``fanout.parallel`` at once), each failed one once more; on a
    signal, stop the running ones (:func:`_stop_on_ray`) and raise :class:`Interrupted`."""
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
                running[reference] = (trial, attempt, time.monotonic(), now_ms())
            done, _ = ray.wait(list(running), num_returns=1)
            trial, attempt, start, _ = running.pop(done[0])
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
        number = stop.number or signal.SIGINT
        _stop_on_ray(ray, list(running))
        stopped = [trial.name for trial, *_ in running.values()]
        killed = [  # runs whose process was killed before it could end them
            run
            for trial, _, _, started_ms in running.values()
            for run in mark_killed(trial, started_ms, ("RUNNING",), servers.get(trial.tracking_uri))
        ]
        raise Interrupted(number, stopped_message(number, stopped, killed)) from None
    return [outcomes[trial] for trial in trials]


def _stop_on_ray(ray, references: list) -> None:
    """Cancel the running trials: each is sent SIGTERM (:func:`run_command`) and waited for
    :data:`STOP_GRACE_S` at most (a further signal ends the wait); those left are killed."""
    for reference in references:
        ray.cancel(reference, force=False)
    pending = references
    with contextlib.suppress(KeyboardInterrupt):
        _, pending = ray.wait(references, num_returns=len(references), timeout=STOP_GRACE_S)
    for reference in pending:  # only those: Ray fails on a forced cancel of a finished task
        ray.cancel(reference, force=True)


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
