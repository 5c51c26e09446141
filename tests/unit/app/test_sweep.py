"""``fgat sweep``: the grid, the trial's seed, and a 2 x 2 quick sweep on a local Ray."""

import itertools
from pathlib import Path

import mlflow
import pytest

from fgat.app.callbacks.mlflow import FINGERPRINT
from fgat.app.cli import main
from fgat.app.lightning_cli import resolved_config
from fgat.app.sweep import grid_points, overrides, parse_grid, point_name, seed_options

CONFIGS = Path(__file__).resolve().parents[3] / "configs"
QUICKSTART = ["--config", str(CONFIGS / "base" / "common.yaml")]
QUICKSTART += ["--config", str(CONFIGS / "quickstart.yaml")]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("seed=0:5", ("seed", range(5))),
        ("x=-2:3:2", ("x", range(-2, 3, 2))),
        ("--model.init_args.lr_means=0.5, 1", ("model.init_args.lr_means", ["0.5", "1"])),
        ("path=a:b", ("path", ["a:b"])),
        (
            "a={terms: 17, rms: 0.5},{terms: 17, rms: 1}",
            ("a", ["{terms: 17, rms: 0.5}", "{terms: 17, rms: 1}"]),
        ),
        ("l=[1, 2],[3]", ("l", ["[1, 2]", "[3]"])),
    ],
)
def test_parse_grid(text, expected):
    assert parse_grid(text) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("seed", "expected KEY=V1,V2"),
        ("=1", "expected KEY=V1,V2"),
        ("k=", "no value, or an empty one"),
        ("k=1,,2", "no value, or an empty one"),
        ("k=5:0", "no value"),
        ("k=1:4:0", "step cannot be 0"),
        ("k=1,1", "a value is given twice"),
    ],
)
def test_bad_grid_is_named(text, message):
    with pytest.raises(ValueError, match=f"--grid '{text}': .*{message}"):
        parse_grid(text)


def test_grid_is_the_cartesian_product_last_varying_fastest():
    points = grid_points(["a.rms=0.5,1", "seed=0:3"])
    assert points == [
        {"a.rms": rms, "seed": seed} for rms, seed in itertools.product(["0.5", "1"], "012")
    ]
    assert point_name(points[1]) == "rms0.5-seed1"
    assert point_name({"x": "{a: 1}", "p": "a/b"}) == "xa1-pab"
    with pytest.raises(ValueError, match="--grid: seed is swept twice"):
        grid_points(["seed=0:2", "seed=3,4"])


def test_seed_is_every_seed_of_the_trial():
    config = resolved_config(["fit", *QUICKSTART])
    seeds = seed_options(config)
    assert seeds == ["seed_everything", "model.init_args.seed", "data.init_args.simulation.seed"]
    words = overrides({"seed": "7", "trainer.max_steps": "3"}, seeds)
    assert words == [
        "--seed_everything=7",
        "--model.init_args.seed=7",
        "--data.init_args.simulation.seed=7",
        "--trainer.max_steps=3",
    ]
    seeded = resolved_config(["fit", *QUICKSTART, *words])
    assert seeded["seed_everything"] == seeded["model"]["init_args"]["seed"] == 7
    assert seeded["data"]["init_args"]["simulation"]["seed"] == 7
    measured = {"model": {"init_args": {"seed": 0}}, "data": {"init_args": {"measurement": "x"}}}
    assert seed_options(measured) == ["seed_everything", "model.init_args.seed"]
    figs9 = ["fit", *QUICKSTART[:2]]
    for name in ("base/optics_quick", "figS9", "figS9_quick"):
        figs9 += ["--config", str(CONFIGS / f"{name}.yaml")]
    seeds = seed_options(resolved_config(figs9))
    assert seeds[-1] == "data.init_args.simulation.aberrations.seed"  # figS9.yaml gives it
    drawn = resolved_config([*figs9, *overrides({"seed": "3"}, seeds)])
    assert drawn["data"]["init_args"]["simulation"]["aberrations"]["seed"] == 3


def test_sweep_options_are_checked_before_anything_runs(capsys):
    assert main(["sweep", *QUICKSTART, "--grid", "seed=0:2", "--static", "s.yaml"]) == 2
    assert "--static and --dynamic belong to --command pipeline" in capsys.readouterr().err
    assert main(["sweep", *QUICKSTART, "--grid", "seed", "--parallel", "1"]) == 2
    assert "--grid 'seed': expected KEY=V1,V2" in capsys.readouterr().err
    assert main(["sweep", *QUICKSTART, "--grid", "seed=0:2", "--model.init_args.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err


TINY = [
    "--trainer.max_steps=20",
    "--trainer.val_check_interval=20",
    "--trainer.log_every_n_steps=10",
    "--trainer.callbacks=[]",
    "--model.init_args.n_gaussians=100",
    "--mlflow.experiment=sweep",
]


def finished_runs(uri: str) -> dict[str, str]:
    """Run name -> fingerprint of the finished runs of the ``sweep`` experiment."""
    client = mlflow.MlflowClient(uri)
    experiment = client.get_experiment_by_name("sweep")
    runs = client.search_runs([experiment.experiment_id])
    assert {run.info.status for run in runs} == {"FINISHED"}
    found = {run.info.run_name: run.data.tags[FINGERPRINT] for run in runs}
    assert len(found) == len(runs)  # no trial ran twice
    return found


@pytest.mark.slow
def test_quick_sweep_on_ray_runs_skips_and_reruns_only_what_changed(tmp_path, monkeypatch, capsys):
    """The acceptance of the sweep: two quick fits on a local Ray finish as two MLflow runs; the
    same sweep again runs nothing; one changed value runs only its trial (the grid's Cartesian
    product is checked by
    ``test_grid_is_the_cartesian_product_last_varying_fastest``)."""
    pytest.importorskip("ray")
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = ["sweep", *QUICKSTART, *TINY, f"--mlflow.tracking_uri={uri}", "--grid", "seed=0"]
    sweep += ["--parallel", "auto"]
    assert main([*sweep, "--grid", "model.init_args.lr_means=0.5,1"]) == 0
    out = capsys.readouterr().out
    names = {f"seed0-lr_means{lr}" for lr in ("0.5", "1")}
    first = finished_runs(uri)
    assert set(first) == names and len(set(first.values())) == 2
    assert "fgat sweep: the trials log to" in out and "fgat sweep: 2 of 2 trials finished" in out
    for name, digest in first.items():
        folder = tmp_path / "runs" / "quickstart" / f"{name}-{digest[:8]}"
        assert "MLflow: run" in (folder / "trial.log").read_text()
        assert (folder / "checkpoints" / "last.ckpt").is_file()
    assert main([*sweep, "--grid", "model.init_args.lr_means=0.5,1"]) == 0
    out = capsys.readouterr().out
    assert out.count("finished before with this configuration") == 2
    assert "fgat sweep: nothing to run" in out and finished_runs(uri) == first
    # in this process: Ray's part is above, the skip by fingerprint is the same either way
    assert main([*sweep, "--grid", "model.init_args.lr_means=0.5,2", "--parallel", "1"]) == 0
    out = capsys.readouterr().out
    assert out.count("finished before with this configuration") == 1
    runs = finished_runs(uri)
    assert set(runs) == names | {"seed0-lr_means2"}
    assert {name: runs[name] for name in first} == first  # nothing else ran again


@pytest.mark.slow
def test_pipeline_sweep_makes_one_pipeline_per_point(tmp_path, monkeypatch):
    """``--command pipeline``: each point one ``fgat pipeline`` in ``<root>/<point>``, the
    stages' configs passed through, the overrides after the shared options."""
    import argparse

    from fgat.app.sweep import sweep_trials

    monkeypatch.chdir(tmp_path)
    shared = ["--config", str(CONFIGS / "base" / "common.yaml")]
    shared += ["--config", str(CONFIGS / "dynamic_quick.yaml")]
    args = argparse.Namespace(
        grid=["seed=0:2"],
        config=[shared[1], shared[3]],
        static=[str(CONFIGS / "dynamic_quick_static.yaml")],
        dynamic=[str(CONFIGS / "dynamic_quick_dynamic.yaml")],
        command="pipeline",
        refit=False,
        max_trials=1000,
        extra=[
            "--trainer.default_root_dir",
            "sw",
            f"--mlflow.tracking_uri=sqlite:///{tmp_path}/m.db",
        ],
    )
    trials = sweep_trials(args)
    assert [trial.name for trial in trials] == ["seed0", "seed1"]
    for seed, trial in enumerate(trials):
        assert trial.folder == Path("sw") / f"seed{seed}"
        assert (
            trial.words[0] == "pipeline"
            and trial.words[-1] == f"--trainer.default_root_dir=sw/seed{seed}"
        )
        assert list(trial.words[1:5]) == shared
        assert "--static" in trial.words and "--dynamic" in trial.words
        assert f"--model.init_args.seed={seed}" in trial.words
        assert f"--data.init_args.simulation.seed={seed}" in trial.words
        assert trial.tracking_uri == f"sqlite:///{tmp_path}/m.db" and trial.fingerprint is None
    with pytest.raises(ValueError, match="--command pipeline needs --static"):
        sweep_trials(argparse.Namespace(**{**vars(args), "static": []}))


@pytest.mark.slow
def test_stopped_sweep_stops_its_trials_and_goes_on_from_their_checkpoints(tmp_path, monkeypatch):
    """SIGTERM (``kill``, SLURM's ``scancel``) stops the sweep, its trials, Ray and the tracking
    server (exit code 143), its fit stopping as a stopped fit does (MLflow run KILLED); the same
    sweep again resumes the stopped fit from its last.ckpt."""
    pytest.importorskip("ray")
    import os
    import signal
    import subprocess
    import sys
    import time

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    words = [*QUICKSTART, *TINY, "--trainer.max_steps=800", "--trainer.val_check_interval=800"]
    words += ["--checkpoint_every=50", f"--mlflow.tracking_uri={uri}", "--grid", "seed=0"]
    sweep = subprocess.Popen(
        [sys.executable, "-m", "fgat", "sweep", *words, "--parallel", "auto"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "MLFLOW_TRACKING_URI": "", "PYTHONPATH": str(CONFIGS.parent)},
    )
    deadline = time.monotonic() + 300
    while not list(tmp_path.glob("runs/quickstart/*/checkpoints/last.ckpt")):
        assert sweep.poll() is None and time.monotonic() < deadline, sweep.communicate()[0]
        time.sleep(0.5)
    sweep.send_signal(signal.SIGTERM)
    output = sweep.communicate(timeout=120)[0]
    assert sweep.returncode == 143, output
    assert "fgat sweep: stopped by SIGTERM (trials stopped: seed0-" in output
    client = mlflow.MlflowClient(uri)
    (stopped,) = client.search_runs([client.get_experiment_by_name("sweep").experiment_id])
    assert stopped.info.status == "KILLED"  # by the trial, given the time to stop
    time.sleep(2)
    if os.path.isdir("/proc"):  # no process of this sweep is left (trials, server)
        left = []
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                command = open(f"/proc/{pid}/cmdline", "rb").read().decode(errors="replace")
            except OSError:
                continue
            if str(tmp_path) in command and int(pid) != os.getpid():
                left.append(command.replace("\0", " "))
        assert not left, left
    monkeypatch.chdir(tmp_path)
    assert main(["sweep", *words, "--parallel", "1"]) == 0  # in this process, no Ray
    client = mlflow.MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("sweep").experiment_id])
    assert sorted(run.info.status for run in runs) == ["FINISHED", "KILLED"]
    (finished,) = [run for run in runs if run.info.status == "FINISHED"]
    (killed,) = [run for run in runs if run.info.status == "KILLED"]
    assert finished.data.tags["fgat.resumed_from"] == killed.info.run_id  # resumed, not redone
