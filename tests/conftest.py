"""Shared fixtures: dtype menu, the path of the external data set, and Triton's interpreter."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def migrated_mlflow_stores(tmp_path_factory):
    """Fresh SQLite MLflow stores made in this process start as a copy of one store migrated
    once. MLflow builds a new store's schema by running its whole migration history (about
    1.5 s on two cores), and most tests log to a store of their own; the copy (SQLite's backup
    API) holds the same schema and revision, and the store then adds its default experiment
    with its own artifact root as usual. Stores made by subprocesses migrate as users' do."""
    import sqlite3
    from contextlib import closing

    from mlflow.store.db import utils

    migrate = getattr(utils, "_initialize_tables", None)
    engine_of = getattr(utils, "create_sqlalchemy_engine_with_retry", None)
    if migrate is None or engine_of is None:  # another MLflow: its stores migrate as usual
        yield
        return
    template = tmp_path_factory.mktemp("mlflow_template") / "migrated.db"
    migrate(engine_of(f"sqlite:///{template}"))

    def copy_migrated(engine):
        if engine.url.get_backend_name() != "sqlite":
            return migrate(engine)
        with engine.connect() as connection, closing(sqlite3.connect(template)) as source:
            source.backup(connection.connection.dbapi_connection)

    utils._initialize_tables = copy_migrated
    yield
    utils._initialize_tables = migrate


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request):
    return request.param


def tolerance(dtype):
    """Relative tolerance of a computation done in ``dtype``."""
    return 1e-5 if dtype == torch.float32 else 1e-10


def run_interpreted(module: str, expression: str):
    """The value of ``expression`` (``t`` being the test module ``module``; JSON-serialisable)
    computed in a fresh process under Triton's interpreter (``TRITON_INTERPRET=1`` must be set
    before Triton is imported): how the Triton kernels run on a machine without a GPU. The
    repository (which holds the ``tests`` package) comes first on the process's ``PYTHONPATH``,
    as pytest puts it first on the import path."""
    code = f"import json; import {module} as t; print(json.dumps({expression}))"
    repository = str(Path(__file__).resolve().parents[1])
    path = os.pathsep.join([repository, *filter(None, [os.environ.get("PYTHONPATH")])])
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "TRITON_INTERPRET": "1", "PYTHONPATH": path},
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


PATHS = (
    ("triton", torch.float32, "triton"),
    ("torch", torch.float32, "torch"),
    ("reference", torch.float64, "torch"),
)
"""The Triton path and the PyTorch path in float32, and the PyTorch path in float64 (the
reference the kernels' tests measure both against): name, dtype, back-end."""


def on_each_path(run) -> dict:
    """``run(dtype, backend)`` on each of :data:`PATHS`, by name."""
    return {name: run(dtype, backend) for name, dtype, backend in PATHS}
