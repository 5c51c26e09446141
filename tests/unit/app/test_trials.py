"""Trials: fingerprint skips, resumes, retries, the serial fallback and Ray."""

import argparse
from pathlib import Path

import mlflow
import pytest

from fgat.app.callbacks.mlflow import FINGERPRINT, check_tracking_uri
from fgat.app.fingerprint import fingerprint, write_record
from fgat.app.lightning_cli import resolved_config
from fgat.app.process import TrialsFailed
from fgat.app.trials import (
    LOG,
    Fanout,
    Trial,
    add_fanout_arguments,
    fanout_from,
    fit_trial,
    require_finished,
    run_trials,
)

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def quickstart_words(uri: str, *extra: str) -> list[str]:
    return [
        "fit",
        "--config",
        str(CONFIGS / "base" / "common.yaml"),
        "--config",
        str(CONFIGS / "quickstart.yaml"),
        f"--mlflow.tracking_uri={uri}",
        "--mlflow.experiment=recipe",
        *extra,
    ]


def finish_run(uri: str, experiment: str, digest: str) -> None:
    """A finished MLflow run tagged with ``digest``, as a finished fit leaves."""
    check_tracking_uri(uri, experiment)
    client = mlflow.MlflowClient(uri)
    run = client.create_run(
        client.get_experiment_by_name(experiment).experiment_id, tags={FINGERPRINT: digest}
    )
    client.set_terminated(run.info.run_id, "FINISHED")


@pytest.mark.slow
def test_fit_trial_skipped_only_for_the_same_fingerprint(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    words = quickstart_words(uri)
    trial = fit_trial(words, tmp_path / "trial")
    fp = fingerprint(resolved_config(words))
    folder = tmp_path / f"trial-{fp.short}"
    assert trial.folder == folder and trial.fingerprint == fp
    assert trial.words == (*words, f"--trainer.default_root_dir={folder}")
    assert (trial.tracking_uri, trial.experiment) == (uri, "recipe")
    assert fit_trial(words, name="point").folder.parent == Path("runs/quickstart")  # the config's
    finish_run(uri, "recipe", fp.digest)
    assert fit_trial(words, tmp_path / "trial") is None  # the same trial: skipped
    assert f"finished before with this configuration (fingerprint {fp.short})" in (
        capsys.readouterr().out
    )
    assert fit_trial([*words, "--seed_everything=7"], tmp_path / "trial") is not None
    assert fit_trial(words, tmp_path / "trial", refit=True) is not None
    with pytest.raises(ValueError, match="starts with 'fit'"):
        fit_trial(["validate", *words[1:]], tmp_path / "trial")


@pytest.mark.slow
def test_a_trial_resumes_only_from_a_checkpoint_of_its_own_fingerprint(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    trial = fit_trial(quickstart_words(uri), tmp_path / "trial")
    assert trial.command() == list(trial.words)  # nothing saved yet
    checkpoint = trial.folder / "checkpoints" / "last.ckpt"
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"saved")
    write_record(trial.folder, trial.fingerprint, status="running")
    assert trial.command("--x=1") == [*trial.words, "--x=1", "--ckpt_path", str(checkpoint)]
    other = fingerprint({**trial.fingerprint.config, "seed_everything": 99})
    write_record(trial.folder, other, status="running")
    assert trial.command() == list(trial.words)


def fake_trial(tmp_path: Path, name: str, words=("fit",)) -> Trial:
    return Trial(name, tuple(words), tmp_path / name, f"sqlite:///{tmp_path}/m.db", "fake")


def test_serial_trials_failing_once_run_again_and_twice_are_reported(tmp_path, monkeypatch, capsys):
    calls = []

    def main(words):
        calls.append(words)
        if words[-1] == "--broken":
            raise RuntimeError("the fit diverged")
        if words[-1] == "--usage":
            raise SystemExit(2)  # an argument parser's error
        return 0 if calls.count(words) > 1 or words[-1] == "--fine" else 3

    trials = [
        fake_trial(tmp_path, "fine", ["fit", "--fine"]),
        fake_trial(tmp_path, "flaky", ["fit", "--flaky"]),
        fake_trial(tmp_path, "broken", ["fit", "--broken"]),
        fake_trial(tmp_path, "usage", ["pipeline", "--usage"]),
    ]
    outcomes = run_trials(trials, Fanout(run_command=main), label="t")
    assert [(o.trial.name, o.returncode, o.attempts) for o in outcomes] == [
        ("fine", 0, 1),
        ("flaky", 0, 2),
        ("broken", 1, 2),
        ("usage", 2, 2),
    ]
    assert len(calls) == 7
    out = capsys.readouterr()
    assert "t: flaky failed (exit code 3, output above): running it once more" in out.out
    assert "t [3/4] broken: failed (exit code 1)" in out.out
    assert "t: 2 of 4 trials finished" in out.out and "broken: failed twice" in out.out
    assert "RuntimeError: the fit diverged" in out.err  # the traceback is shown
    with pytest.raises(TrialsFailed, match=r"2 trial\(s\) failed twice: broken, usage"):
        require_finished(outcomes)


def test_without_ray_trials_run_one_after_another_and_say_how_to_parallelise(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr("fgat.app.trials.ray_available", lambda: False)
    fanout = Fanout(parallel=None, run_command=lambda words: 0)
    outcomes = run_trials([fake_trial(tmp_path, "a")], fanout, label="t")
    assert [o.finished for o in outcomes] == [True]
    assert (
        'Ray is not installed: the trials run one after another (pip install -e ".[cluster]"'
        in (capsys.readouterr().out)
    )
    with pytest.raises(ValueError, match="--address auto: Ray is not installed"):
        run_trials([fake_trial(tmp_path, "a")], Fanout(address="auto"))


@pytest.mark.parametrize(
    ("words", "expected"),
    [
        ([], Fanout(parallel=1)),
        (["--parallel", "auto", "--cpus-per-trial", "2"], Fanout(None, None, None, 2.0)),
        (["--parallel", "3", "--gpus-per-trial", "0.5"], Fanout(3, None, 0.5, 1.0)),
        (["--address", "ray://head:10001"], Fanout(1, "ray://head:10001")),
    ],
)
def test_fanout_options(words, expected):
    parser = argparse.ArgumentParser()
    add_fanout_arguments(parser)
    fanout = fanout_from(parser.parse_args(words))
    assert fanout == expected
    assert fanout.serial == (expected.parallel == 1 and expected.address is None)


@pytest.mark.parametrize(
    ("words", "message"),
    [
        (["--parallel", "0"], "--parallel '0': expected a whole number >= 1 or auto"),
        (["--parallel", "many"], "--parallel 'many'"),
        (["--cpus-per-trial", "0"], "--cpus-per-trial must be a finite number > 0, got '0'"),
        (["--cpus-per-trial", "nan"], "--cpus-per-trial must be a finite number > 0, got 'nan'"),
        (["--cpus-per-trial", "inf"], "--cpus-per-trial must be a finite number > 0, got 'inf'"),
        (["--cpus-per-trial", "-2"], "--cpus-per-trial must be a finite number > 0, got '-2'"),
        (["--gpus-per-trial", "-1"], "--gpus-per-trial must be a finite number >= 0, got '-1'"),
        (["--gpus-per-trial", "nan"], "--gpus-per-trial must be a finite number >= 0"),
    ],
)
def test_bad_fanout_options_are_named(words, message):
    parser = argparse.ArgumentParser()
    add_fanout_arguments(parser)
    with pytest.raises(ValueError, match=message):
        fanout_from(parser.parse_args(words))


@pytest.mark.slow
def test_ray_trial_failing_twice_is_retried_once_and_reported(tmp_path, monkeypatch, capsys):
    pytest.importorskip("ray")
    monkeypatch.chdir(tmp_path)
    broken = fake_trial(tmp_path, "broken", ["fit", "--config", "missing.yaml"])
    with pytest.raises(ValueError, match="needs more CPUs|this machine has"):
        run_trials([broken], Fanout(parallel=None, cpus_per_trial=1e6), label="t")
    outcomes = run_trials([broken], Fanout(parallel=None), label="t")
    assert [(o.returncode, o.attempts, o.log) for o in outcomes] == [(2, 2, broken.folder / LOG)]
    log = (broken.folder / LOG).read_text()
    assert log.count("$ python -m fgat fit --config missing.yaml") == 2  # both attempts
    assert log.count("missing.yaml") >= 4 and "does not exist" in log
    out = capsys.readouterr().out
    assert f"t: broken failed (exit code 2, output in {broken.folder / LOG})" in out
    assert "running it once more" in out and "broken: failed twice" in out
