"""The host-memory policy of fgat processes (fgat._core.heap): freed blocks are reused without page
faults, and handed back to the kernel before memory is measured."""

from __future__ import annotations

import ast
import os
import platform
import subprocess
import sys

import pytest

from fgat._core.heap import OPT_OUT, retain_freed_memory

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
    reason="the policy is glibc's",
)

PAGES = 10 * 2**20 * 4 // 4096
"""Pages of the 40 MiB block the scripts allocate: above glibc's largest mmap threshold."""

FAULTS = """
import resource, sys, torch
from fgat._core.heap import retain_freed_memory
if sys.argv[1] == "retain":
    assert retain_freed_memory()
counts = []
for _ in range(16):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = torch.ones(10 * 2**20)
    del block
    counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(counts)
"""

RELEASE = """
import os, torch
from fgat._core.heap import retain_freed_memory
from fgat._core.resources import available_memory
def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
assert retain_freed_memory()
start = resident()
block = torch.ones(50 * 2**20)
del block
kept = resident()
available_memory()
print([kept - start, resident() - start])
"""


def _run(script: str, *args: str) -> list[int]:
    env = {
        name: value
        for name, value in os.environ.items()
        if not name.startswith("MALLOC_") and name not in ("GLIBC_TUNABLES", OPT_OUT)
    }
    result = subprocess.run(
        [sys.executable, "-c", script, *args], env=env, capture_output=True, text=True, check=True
    )
    return ast.literal_eval(result.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_retained_blocks_are_reused_without_page_faults():
    default, retained = _run(FAULTS, "default"), _run(FAULTS, "retain")
    # glibc's default maps a 40 MiB block anew on every allocation: a fault per page ...
    assert min(default[10:]) > 0.9 * PAGES
    # ... the retained heap, once warm, serves it from pages already mapped.
    assert max(retained[10:]) < 0.01 * PAGES


def test_available_memory_hands_retained_memory_back():
    kept, after = _run(RELEASE)
    block = 50 * 2**20 * 4
    assert kept > 0.9 * block  # freed, but kept mapped for reuse
    assert after < 0.1 * block  # handed back before the kernel is asked what is free


@pytest.mark.parametrize("name", ["MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_", "GLIBC_TUNABLES"])
def test_the_users_allocator_settings_stand(monkeypatch, name):
    monkeypatch.setenv(name, "1")
    assert retain_freed_memory() is False


def test_opt_out_and_bad_threshold(monkeypatch):
    with pytest.raises(ValueError, match="trim_bytes"):
        retain_freed_memory(-1)
    with pytest.raises(ValueError, match="trim_bytes"):
        retain_freed_memory(2**31)
    monkeypatch.setenv(OPT_OUT, "1")
    assert retain_freed_memory() is False
