"""The stress cases live in ``benchmarks/stress.py`` (the full table); these tests run a fast
subset of the same functions."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
