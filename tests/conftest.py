"""Shared fixtures: dtype menu and the path of the external data set."""

from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request):
    return request.param


def tolerance(dtype):
    """Relative tolerance of a computation done in ``dtype``."""
    return 1e-5 if dtype == torch.float32 else 1e-10
