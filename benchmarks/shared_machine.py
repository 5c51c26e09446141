"""A fair share of a shared machine: the quickstart fit alone and beside a competing CPU load.

Each run is ``python -m fgat fit --config configs/base/common.yaml --config
configs/quickstart.yaml`` in a fresh process (its output and MLflow store in a temporary
folder; ``--steps`` shortens it, validating at the last step), under two thread policies:

- ``before``: fgat's behaviour before it sized its pools (``fgat._core.threads``):
  ``OMP_NUM_THREADS=os.cpu_count()`` and libgomp's default waiting, idle threads spinning about
  3 ms before they sleep (``GOMP_SPINCOUNT=300000``, libgomp's value when ``OMP_WAIT_POLICY``
  is unset);
- ``now``: no thread variable set, fgat's own choice (``usable_cpus()`` threads,
  ``OMP_WAIT_POLICY=PASSIVE``);
- ``active`` (on request): ``OMP_NUM_THREADS=os.cpu_count()``, ``OMP_WAIT_POLICY=ACTIVE``.

Alone, then beside ``--load`` busy processes (pure-Python loops started here, killed after each
run; default twice the usable CPUs), policies interleaved, ``--repeats`` times (the order
reversed every other repeat). Reported per policy (medians): wall time, CPU time of the fit's
process (``getrusage(RUSAGE_CHILDREN)``), the slowdown beside the load, and the fair-share
expectation ``alone wall x (load + 1) / cpus``, load + 1 processes sharing ``cpus`` CPUs equally
(capped below by the alone time), with whether the loaded wall time is within 1.5x of it. Before
that, what the hardware overlaps: the loop rate of ``cpus`` busy processes at once over that of
one (2.0 on two free cores), and the load average. Every run's volume must be the same bit for
bit (same thread count) and its PSNR is recorded. A machine busy with other work inflates every
time; read the load averages recorded with the runs.

    python benchmarks/shared_machine.py [--quick] [--repeats 2] [--steps 250] [--load N]
"""

from __future__ import annotations

import hashlib
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fgat._core.threads import WAIT_VARIABLES, usable_cpus
from fgat.app.recipes.benchmark import parser, provenance, write_json

ROOT = Path(__file__).resolve().parent.parent
POLICIES = {
    "before": {"OMP_NUM_THREADS": str(os.cpu_count()), "GOMP_SPINCOUNT": "300000"},
    "now": {},
    "active": {"OMP_NUM_THREADS": str(os.cpu_count()), "OMP_WAIT_POLICY": "ACTIVE"},
}
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", *WAIT_VARIABLES)
SPIN = (
    "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n"
    "    for _ in range(1000000): pass"
)  # a busy loop that stops when the benchmark does
COUNT = (
    "import time\nn = 0\nend = time.perf_counter() + {seconds}\n"
    "while time.perf_counter() < end: n += 1\nprint(n)"
)
PSNR = re.compile(r"val/psnr_volume ([0-9.]+) dB")


def environment(policy: str) -> dict[str, str]:
    """This process's environment without thread variables, then the policy's."""
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    return {**clean, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": "", **POLICIES[policy]}


def loop_rates(processes: int, seconds: float = 1.0) -> list[float]:
    """Loop iterations per second of each of ``processes`` busy Python processes run at once."""
    code = COUNT.format(seconds=seconds)
    started = [
        subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        for _ in range(processes)
    ]
    return [int(p.communicate()[0]) / seconds for p in started]


def overlap(cpus: int) -> dict:
    """What the hardware overlaps: the total loop rate of ``cpus`` busy processes at once over
    that of one alone (``cpus`` on free cores, less on a busy or oversubscribed machine)."""
    one = loop_rates(1)[0]
    together = sum(loop_rates(cpus))
    return {
        "processes": cpus,
        "rate_one_per_s": one,
        "rate_together_per_s": together,
        "speedup": together / one,
        "load_average": os.getloadavg()[0],
    }


def fit_command(folder: Path, steps: int) -> list[str]:
    """The quickstart fit, output and MLflow store under ``folder``, ``steps`` steps."""
    command = [sys.executable, "-m", "fgat", "fit"]
    for config in ("configs/base/common.yaml", "configs/quickstart.yaml"):
        command += ["--config", str(ROOT / config)]
    return command + [
        f"--trainer.max_steps={steps}",
        f"--trainer.val_check_interval={steps}",
        f"--trainer.default_root_dir={folder / 'run'}",
        f"--mlflow.tracking_uri=sqlite:///{folder / 'mlflow.db'}",
        "--trainer.enable_progress_bar=false",
    ]


def volume_digest(folder: Path) -> str:
    """SHA-256 of the fitted volume's voxels (float32 bytes) in the run's results."""
    import tifffile

    (path,) = (folder / "run" / "results").glob("*/volume.ome.tif")
    return hashlib.sha256(tifffile.imread(path).tobytes()).hexdigest()


def fit(policy: str, load: int, steps: int) -> dict:
    """One fit under ``policy`` beside ``load`` busy processes: its row."""
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(load)]
    try:
        time.sleep(0.5 if load else 0.0)
        with tempfile.TemporaryDirectory() as scratch:
            folder = Path(scratch)
            load_before = os.getloadavg()[0]
            usage = resource.getrusage(resource.RUSAGE_CHILDREN)
            start = time.perf_counter()
            done = subprocess.run(
                fit_command(folder, steps),
                cwd=folder,
                env=environment(policy),
                capture_output=True,
                text=True,
            )
            wall = time.perf_counter() - start
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            if done.returncode != 0:
                raise RuntimeError(f"{policy} fit failed:\n{done.stderr[-3000:]}")
            psnr = PSNR.findall(done.stdout + done.stderr)
            digest = volume_digest(folder)
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait()
    cpu = (after.ru_utime - usage.ru_utime) + (after.ru_stime - usage.ru_stime)
    row = {
        "policy": policy,
        "load": load,
        "wall_s": wall,
        "cpu_s": cpu,
        "psnr_volume_db": float(psnr[-1]) if psnr else None,
        "volume_sha256": digest,
        "load_average_before": load_before,
    }
    print(
        f"{policy:>7} beside {load} busy: {wall:.1f} s wall, {cpu:.1f} s CPU, "
        f"PSNR {row['psnr_volume_db']} dB (load average {load_before:.1f})",
        flush=True,
    )
    return row


def summary(rows: list[dict], policy: str, load: int, cpus: int) -> dict:
    """Medians of ``policy``'s runs alone and beside ``load`` processes, the slowdown and the
    fair-share expectation ``alone x max(1, (load + 1) / cpus)``."""

    def median(key: str, with_load: int) -> float:
        return statistics.median(
            r[key] for r in rows if r["policy"] == policy and r["load"] == with_load
        )

    alone, loaded = median("wall_s", 0), median("wall_s", load)
    fair = alone * max(1.0, (load + 1) / cpus)
    return {
        "policy": policy,
        "alone_wall_s": alone,
        "alone_cpu_s": median("cpu_s", 0),
        "loaded_wall_s": loaded,
        "loaded_cpu_s": median("cpu_s", load),
        "slowdown": loaded / alone,
        "fair_share_s": fair,
        "over_fair_share": loaded / fair,
        "within_1_5x_of_fair_share": loaded <= 1.5 * fair,
    }


def main() -> None:
    command = parser(__doc__, "benchmarks/results/shared_machine.json", "100 steps, 1 repeat")
    command.set_defaults(repeats=2)
    command.add_argument("--steps", type=int, default=250, help="fit steps (quickstart: 500)")
    command.add_argument("--load", type=int, help="busy processes (default: 2 x usable CPUs)")
    command.add_argument("--policies", default="before,now", help="of: before, now, active")
    args = command.parse_args()
    policies = args.policies.split(",")
    unknown = sorted(set(policies) - set(POLICIES))
    if unknown:
        command.error(f"--policies: unknown {', '.join(unknown)}; expected {', '.join(POLICIES)}")
    steps, repeats = (100, 1) if args.quick else (args.steps, args.repeats)
    cpus = usable_cpus({})
    load = 2 * cpus if args.load is None else args.load
    hardware = overlap(cpus)
    print(
        f"{cpus} usable CPUs of {os.cpu_count()}; {cpus} busy processes at once run "
        f"x{hardware['speedup']:.2f} the loops of one (load average "
        f"{hardware['load_average']:.1f})",
        flush=True,
    )
    rows = []
    for repeat in range(repeats):
        order = policies if repeat % 2 == 0 else policies[::-1]
        for busy in (0, load):
            rows += [{**fit(policy, busy, steps), "repeat": repeat} for policy in order]
    summaries = [summary(rows, policy, load, cpus) for policy in policies]
    for s in summaries:
        print(
            f"{s['policy']:>7}: alone {s['alone_wall_s']:.1f} s ({s['alone_cpu_s']:.1f} s CPU), "
            f"beside {load} busy {s['loaded_wall_s']:.1f} s ({s['loaded_cpu_s']:.1f} s CPU): "
            f"x{s['slowdown']:.2f}; fair share {s['fair_share_s']:.1f} s "
            f"(x{s['over_fair_share']:.2f} of it)"
        )
    digests = {r["volume_sha256"] for r in rows}
    print(f"volumes identical across runs: {len(digests) == 1}")
    option = " --quick" if args.quick else f" --repeats {repeats} --steps {steps}"
    if args.load is not None:
        option += f" --load {load}"
    if args.policies != "before,now":
        option += f" --policies {args.policies}"
    write_json(
        args.out,
        {
            **provenance("python benchmarks/shared_machine.py" + option, usable_cpus=cpus),
            "steps": steps,
            "load_processes": load,
            "fair_share_formula": "alone wall x max(1, (load processes + 1) / usable cpus)",
            "hardware_overlap": hardware,
            "summaries": summaries,
            "volumes_identical": len(digests) == 1,
            "runs": rows,
        },
    )


if __name__ == "__main__":
    main()
