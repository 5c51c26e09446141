"""``python -m fgat tracking-server``: one MLflow tracking server for many processes.

Processes that log into one SQLite file lock each other; processes that log to one server do
not: the server alone writes the database (SQLite, or PostgreSQL for several machines) and
keeps the artifacts, and every run logs over HTTP (``--mlflow.tracking_uri
http://127.0.0.1:5000`` or ``MLFLOW_TRACKING_URI``). The server listens on 127.0.0.1 unless
told otherwise.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

from fgat.io.files import check_writable_folder

DEFAULT_PORT = 5000


def server_command(
    backend_store_uri: str,
    artifacts_destination: str,
    host: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    workers: int | None = None,
) -> list[str]:
    """The ``mlflow server`` command line, after checking what can be checked before it starts:
    a SQLite database's folder must exist and be writable, and so must the artifact folder's
    parent (the folder itself is created).

    ``workers`` defaults to one worker process on a SQLite store (SQLite takes one writer at a
    time, so more processes only wait on each other's locks, and each one costs seconds of
    start-up) and to MLflow's default otherwise.

    Raises
    ------
    FileNotFoundError, ValueError
        Naming the option and the folder.
    """
    if not 0 < int(port) < 65536:
        raise ValueError(f"--port must be a TCP port (1-65535), got {port}")
    check_database(backend_store_uri, "--backend-store-uri")
    if "://" not in artifacts_destination:  # a local folder
        artifacts = Path(artifacts_destination).resolve()
        if not artifacts.parent.is_dir():
            raise FileNotFoundError(
                f"--artifacts-destination: folder {artifacts.parent} does not exist"
            )
        if artifacts.exists() and not artifacts.is_dir():
            raise ValueError(
                f"--artifacts-destination {artifacts_destination}: a file; expected a folder "
                "(created if missing)"
            )
        check_writable_folder(artifacts.parent, "--artifacts-destination")
        artifacts_destination = str(artifacts)
    command = [sys.executable, "-m", "mlflow", "server"]
    command += ["--backend-store-uri", backend_store_uri]
    command += ["--artifacts-destination", artifacts_destination]
    command += ["--host", host, "--port", str(int(port))]
    if workers is None and backend_store_uri.startswith("sqlite:"):
        workers = 1
    if workers is not None:
        if int(workers) < 1:
            raise ValueError(f"--workers must be at least 1, got {workers}")
        command += ["--workers", str(int(workers))]
    return command


def sqlite_file(uri: str) -> Path | None:
    """The database file of a ``sqlite:///relative.db`` or ``sqlite:////absolute.db`` URI, else
    ``None``."""
    return Path(uri[len("sqlite:///") :]) if uri.startswith("sqlite:///") else None


SQLITE_HEADER = b"SQLite format 3\x00"
"""The first 16 bytes of every SQLite database file."""


def check_database(uri: str, source: str) -> Path | None:
    """The SQLite database file of ``uri`` (``None`` for another kind of store), checked before
    MLflow opens it (MLflow retries a database it cannot open for minutes): its folder must
    exist and be writable, and the file, if there, must be an SQLite database.

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming ``source`` (the option) and the path.
    """
    database = sqlite_file(uri)
    if database is None:
        return None
    if database.is_dir():
        raise ValueError(f"{source} {uri}: {database} is a folder; expected a database file")
    folder = database.resolve().parent
    if not folder.is_dir():
        raise FileNotFoundError(f"{source} {uri}: folder {folder} does not exist")
    check_writable_folder(folder, source)
    if database.is_file() and database.stat().st_size:
        with database.open("rb") as handle:
            if handle.read(len(SQLITE_HEADER)) != SQLITE_HEADER:
                raise ValueError(
                    f"{source} {uri}: {database} exists and is not an SQLite database; name a "
                    "new file or an MLflow database"
                )
    return database


def check_listen(host: str, port: int) -> None:
    """Refuse, before the server starts, a ``host`` and ``port`` it could not listen on (an
    address of another machine, a name that does not resolve, a port taken): ``mlflow server``
    would report it and still exit with code 0.

    Raises
    ------
    ValueError
        One line naming ``--host`` / ``--port`` and the reason.
    """
    try:
        family, kind, protocol, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM
        )[0]
    except (socket.gaierror, UnicodeError) as error:
        reason = getattr(error, "strerror", None) or str(error)
        raise ValueError(f"--host {host}: not an address to listen on ({reason})") from None
    with socket.socket(family, kind, protocol) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server does
        try:
            probe.bind(address)
        except OSError as error:
            raise ValueError(
                f"--host {host} --port {port}: cannot listen there ({error.strerror})"
            ) from None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing listens on now."""
    with socket.socket() as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def wait_until_healthy(uri: str, server: subprocess.Popen, seconds: float = 120) -> None:
    """Return once the server at ``uri`` answers ``/health``.

    Raises
    ------
    RuntimeError
        The server process exited first.
    TimeoutError
        No answer within ``seconds``.
    """
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"the tracking server exited with code {server.returncode}")
        try:
            with urllib.request.urlopen(f"{uri}/health", timeout=2) as reply:
                if reply.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    raise TimeoutError(f"no tracking server at {uri} after {seconds} s")


@contextlib.contextmanager
def starting_server(
    backend_store_uri: str, artifacts_destination: str | None = None
) -> Iterator[Callable[[], str]]:
    """A tracking server on 127.0.0.1 (a free port) for the duration of the ``with`` block,
    started at once: yields a function that waits until the server answers and returns its
    ``http://`` URI, so that the seconds it takes to start can overlap other work; stops it on
    exit.

    Parallel trials on one machine log through it instead of locking each other out of one
    SQLite file. ``artifacts_destination`` defaults to ``mlartifacts`` beside a SQLite database
    (where ``mlflow ui`` run from that folder finds them).
    """
    if artifacts_destination is None:
        database = sqlite_file(backend_store_uri)
        folder = Path.cwd() if database is None else database.resolve().parent
        artifacts_destination = str(folder / "mlartifacts")
    port = free_port()
    command = server_command(backend_store_uri, artifacts_destination, port=port)
    uri = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryFile("w+") as output:
        server = subprocess.Popen(
            command, stdout=output, stderr=subprocess.STDOUT, start_new_session=True
        )

        def ready() -> str:
            try:
                wait_until_healthy(uri, server)
            except (RuntimeError, TimeoutError) as error:
                output.seek(0)
                raise RuntimeError(
                    f"{backend_store_uri}: the tracking server did not start ({error}): "
                    f"{output.read()[-2000:]}"
                ) from None
            return uri

        try:
            yield ready
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(server.pid, signal.SIGTERM)
            server.wait(timeout=60)


@contextlib.contextmanager
def local_server(backend_store_uri: str, artifacts_destination: str | None = None) -> Iterator[str]:
    """:func:`starting_server`, waited for: yields the server's ``http://`` URI once it answers."""
    with starting_server(backend_store_uri, artifacts_destination) as ready:
        yield ready()


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "tracking-server",
        help="an MLflow server that many runs log to over HTTP",
        description=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument(
        "--backend-store-uri",
        default="sqlite:///mlflow.db",
        help="database of runs and metrics (default sqlite:///mlflow.db; postgresql://... for "
        "a shared database)",
    )
    parser.add_argument(
        "--artifacts-destination",
        default="mlartifacts",
        help="where the server keeps the runs' artifacts (default ./mlartifacts)",
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1: this machine only)",
    )
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"port to listen on (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="server worker processes (default 1 on a SQLite store, MLflow's default otherwise)",
    )
    parser.set_defaults(run=_run)


def _run(args) -> int:
    command = server_command(
        args.backend_store_uri, args.artifacts_destination, args.host, args.port, args.workers
    )
    check_listen(args.host, args.port)
    uri = f"http://{args.host}:{args.port}"
    print(
        f"fgat tracking-server: {uri} (runs in {args.backend_store_uri}); log to it with "
        f"--mlflow.tracking_uri {uri} or MLFLOW_TRACKING_URI={uri}; browse it at {uri}",
        flush=True,
    )
    os.execv(command[0], command)  # the server replaces this process: Ctrl-C stops it
    return 0
