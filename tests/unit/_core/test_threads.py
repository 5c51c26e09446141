"""fgat._core.threads: the CPUs a process may use (affinity, cgroup v1/v2 quota, OMP_NUM_THREADS)
and the thread environment set before torch starts its OpenMP runtime."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fgat._core.threads import (
    cgroup_cpu_quota,
    configure_threads,
    requested_threads,
    thread_environment,
    usable_cpus,
)

ROOT = Path(__file__).resolve().parents[3]


def cgroup_v2(tmp_path: Path, limits: dict[str, str], group: str = "/") -> tuple[Path, Path]:
    """A fake cgroup v2 mount with ``cpu.max`` files (group path -> content) and the
    ``/proc/self/cgroup`` of a process in ``group``."""
    root = tmp_path / "cgroup"
    root.mkdir()
    for path, content in limits.items():
        folder = root / path.strip("/")
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "cpu.max").write_text(content + "\n")
    self_cgroup = tmp_path / "self_cgroup"
    self_cgroup.write_text(f"0::{group}\n")
    return root, self_cgroup


def cgroup_v1(tmp_path: Path, quota: int, period: int, group: str = "/") -> tuple[Path, Path]:
    """A fake cgroup v1 mount whose ``cpu,cpuacct`` hierarchy holds ``group``'s quota."""
    root = tmp_path / "cgroup"
    folder = root / "cpu,cpuacct" / group.strip("/")
    folder.mkdir(parents=True)
    (folder / "cpu.cfs_quota_us").write_text(f"{quota}\n")
    (folder / "cpu.cfs_period_us").write_text(f"{period}\n")
    self_cgroup = tmp_path / "self_cgroup"
    self_cgroup.write_text(f"4:memory:{group}\n3:cpu,cpuacct:{group}\n0::/\n")
    return root, self_cgroup


@pytest.mark.parametrize(
    ("content", "expected"),
    [("150000 100000", 2), ("100000 100000", 1), ("50000 100000", 1), ("max 100000", 8)],
)
def test_cgroup_v2_quota_rounds_up(tmp_path, content, expected):
    root, self_cgroup = cgroup_v2(tmp_path, {"/": content})
    assert usable_cpus({}, affinity=8, root=root, self_cgroup=self_cgroup) == expected


def test_cgroup_v2_quota_of_a_group_and_its_parent(tmp_path):
    root, self_cgroup = cgroup_v2(
        tmp_path, {"/jobs": "250000 100000", "/jobs/job1": "max 100000"}, group="/jobs/job1"
    )
    assert cgroup_cpu_quota(root, self_cgroup) == pytest.approx(2.5)
    assert usable_cpus({}, affinity=16, root=root, self_cgroup=self_cgroup) == 3
    assert usable_cpus({}, affinity=2, root=root, self_cgroup=self_cgroup) == 2


def test_cgroup_v2_group_outside_the_mount_reads_the_root(tmp_path):
    """A container without its own cgroup namespace: /proc/self/cgroup names the host's path,
    the mount shows the container's group as its root."""
    root, self_cgroup = cgroup_v2(tmp_path, {"/": "300000 100000"}, group="/docker/abc")
    assert cgroup_cpu_quota(root, self_cgroup) == pytest.approx(3.0)


@pytest.mark.parametrize(("quota", "expected"), [(150000, 2), (50000, 1), (-1, 4)])
def test_cgroup_v1_quota(tmp_path, quota, expected):
    root, self_cgroup = cgroup_v1(tmp_path, quota, 100000, group="/batch/42")
    assert usable_cpus({}, affinity=4, root=root, self_cgroup=self_cgroup) == expected


def test_no_cgroup_files_leaves_the_affinity(tmp_path):
    missing = tmp_path / "none"
    assert cgroup_cpu_quota(missing, missing / "cgroup") is None
    assert usable_cpus({}, affinity=3, root=missing, self_cgroup=missing / "cgroup") == 3


def test_affinity_is_this_process_mask():
    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("no affinity mask on this platform")
    missing = Path("/nonexistent")
    expected = len(os.sched_getaffinity(0))
    assert usable_cpus({}, root=missing, self_cgroup=missing) == expected


def test_omp_num_threads_takes_precedence(tmp_path):
    root, self_cgroup = cgroup_v2(tmp_path, {"/": "100000 100000"})
    for text, expected in (("3", 3), (" 6 ", 6), ("4,2", 4)):
        environ = {"OMP_NUM_THREADS": text}
        assert usable_cpus(environ, affinity=2, root=root, self_cgroup=self_cgroup) == expected
    assert requested_threads({"OMP_NUM_THREADS": ""}) is None


@pytest.mark.parametrize("text", ["0", "-2", "abc", "1.5"])
def test_invalid_omp_num_threads(tmp_path, capsys, monkeypatch, text):
    monkeypatch.setitem(sys.modules, "torch", RecordingTorch())
    with pytest.raises(ValueError, match=f"OMP_NUM_THREADS='{text}' is not a positive"):
        requested_threads({"OMP_NUM_THREADS": text})
    missing = tmp_path / "none"
    environ = {"OMP_NUM_THREADS": text, "OMP_WAIT_POLICY": "ACTIVE"}
    threads = configure_threads(environ, affinity=1, root=missing, self_cgroup=missing)
    lines = capsys.readouterr().err.strip().splitlines()
    assert threads == 1
    assert len(lines) == 1 and "OMP_NUM_THREADS" in lines[0] and "ignored" in lines[0]
    assert environ == {"OMP_NUM_THREADS": text, "OMP_WAIT_POLICY": "ACTIVE"}


def test_thread_environment_never_replaces_a_user_value():
    assert thread_environment({}, 3) == {"OMP_NUM_THREADS": "3", "OMP_WAIT_POLICY": "PASSIVE"}
    assert thread_environment({"OMP_NUM_THREADS": "5"}, 3) == {"OMP_WAIT_POLICY": "PASSIVE"}
    for name, value in (
        ("OMP_WAIT_POLICY", "ACTIVE"),
        ("GOMP_SPINCOUNT", "300000"),
        ("KMP_BLOCKTIME", "200"),
    ):
        assert thread_environment({name: value}, 3) == {"OMP_NUM_THREADS": "3"}


class RecordingTorch:
    """Stands for an imported torch: records the thread counts set; its inter-op pool has
    started when ``interop_started``."""

    def __init__(self, interop_started: bool = False):
        self.threads, self.interop, self.interop_started = None, None, interop_started

    def set_num_threads(self, n: int) -> None:
        self.threads = n

    def set_num_interop_threads(self, n: int) -> None:
        if self.interop_started:
            raise RuntimeError("Error: cannot set number of interop threads after parallel work")
        self.interop = n


def test_configure_threads_applies_to_an_imported_torch(tmp_path, monkeypatch):
    missing = tmp_path / "none"
    recording = RecordingTorch()
    monkeypatch.setitem(sys.modules, "torch", recording)
    environ = {"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "active"}
    assert configure_threads(environ, root=missing, self_cgroup=missing) == 1
    assert (recording.threads, recording.interop) == (1, 1)
    assert environ == {"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "active"}
    recording = RecordingTorch(interop_started=True)
    monkeypatch.setitem(sys.modules, "torch", recording)
    environ = {}
    assert configure_threads(environ, affinity=2, root=missing, self_cgroup=missing) == 2
    assert (recording.threads, recording.interop) == (2, None)
    assert environ == {"OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE"}


def runtime_settings(code: str, **variables: str) -> tuple[str, str]:
    """stdout and stderr of ``python -c code`` in the repository with libgomp printing its
    settings when torch loads it (``OMP_DISPLAY_ENV=VERBOSE``), the thread variables removed
    from the environment except ``variables``."""
    names = ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME", "KMP_LIBRARY")
    environ = {k: v for k, v in os.environ.items() if k not in names}
    environ.update(OMP_DISPLAY_ENV="VERBOSE", MLFLOW_TRACKING_URI="", **variables)
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env=environ,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    if "GOMP_SPINCOUNT" not in done.stderr:
        pytest.skip("torch's OpenMP runtime is not libgomp: no GOMP_SPINCOUNT to read")
    return done.stdout, done.stderr


COMMAND_LINE = (
    "import os, runpy, sys\n"
    "sys.argv = ['fgat', '--help']\n"
    "try:\n"
    "    runpy.run_module('fgat', run_name='__main__', alter_sys=True)\n"
    "except SystemExit:\n"
    "    pass\n"
    "import torch\n"
    "print(os.environ.get('OMP_WAIT_POLICY'), torch.get_num_threads(), file=sys.stderr)\n"
)


def test_command_line_lets_idle_threads_sleep():
    """``python -m fgat --help`` (run as ``-m`` runs it): the OpenMP runtime torch loads
    afterwards sees OMP_WAIT_POLICY=PASSIVE, i.e. no spinning (libgomp's spin count 0, against
    300000 without fgat)."""
    _, stderr = runtime_settings(COMMAND_LINE)
    assert "GOMP_SPINCOUNT = '0'" in stderr
    policy, threads = stderr.strip().splitlines()[-1].split()
    assert policy == "PASSIVE" and int(threads) == usable_cpus({})
    _, stderr = runtime_settings("import torch")
    assert "GOMP_SPINCOUNT = '300000'" in stderr


@pytest.mark.parametrize(
    ("variables", "spincount"),
    [({"OMP_WAIT_POLICY": "ACTIVE"}, "30000000000"), ({"GOMP_SPINCOUNT": "1000"}, "1000")],
)
def test_command_line_keeps_the_user_waiting_policy(variables, spincount):
    _, stderr = runtime_settings(COMMAND_LINE, **variables)
    assert f"GOMP_SPINCOUNT = '{spincount}'" in stderr


def test_user_thread_count_reaches_torch():
    stdout, _ = runtime_settings(
        "import fgat, torch; print(torch.get_num_threads())", OMP_NUM_THREADS="1"
    )
    assert stdout.strip() == "1"


def test_configure_threads_after_torch_sets_its_pools():
    """A script that imported torch first: importing fgat leaves torch alone, an explicit
    configure_threads() sets both pools."""
    code = (
        "import torch\n"
        "n, m = torch.get_num_threads(), torch.get_num_interop_threads()\n"
        "from fgat._core.threads import configure_threads\n"
        "assert (torch.get_num_threads(), torch.get_num_interop_threads()) == (n, m)\n"
        "configure_threads({'OMP_NUM_THREADS': '1'})\n"
        "print(torch.get_num_threads(), torch.get_num_interop_threads())\n"
    )
    stdout, _ = runtime_settings(code)
    assert stdout.split() == ["1", "1"]
