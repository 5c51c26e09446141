"""``python -m fgat pipeline`` refuses bad input with one line (exit 2) before any stage runs."""

import pytest
import yaml

from fgat.app.cli import main

STATIC = {"model": {"class_path": "fgat.modules.StaticModule", "init_args": {"n_gaussians": 10}}}


@pytest.fixture
def configs(tmp_path, monkeypatch):
    """A dynamic config on a (never simulated) phantom, a static one, and broken variants."""
    monkeypatch.chdir(tmp_path)
    dynamic = {
        "trainer": {"default_root_dir": str(tmp_path / "run")},
        "model": {"class_path": "fgat.modules.DynamicModule", "init_args": {"static": "later"}},
        "data": {
            "class_path": "fgat.datamodules.PhantomDataModule",
            "init_args": {"simulation": {"frames": 3, "phantom": {"kind": "moving_beads"}}},
        },
    }
    (tmp_path / "dynamic.yaml").write_text(yaml.safe_dump(dynamic))
    (tmp_path / "static.yaml").write_text(yaml.safe_dump(STATIC))
    (tmp_path / "broken.yaml").write_text("trainer:\n  max_steps: [1, 2\nmodel: x\n")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    return tmp_path


CASES = [
    (["--config", "missing.yaml"], "config missing.yaml does not exist"),
    (
        ["--config", "broken.yaml"],
        "config broken.yaml: invalid YAML at line 3, column 6: expected ',' or ']'",
    ),
    (["--static", "broken.yaml"], "config broken.yaml: invalid YAML at line 3"),
    (
        ["--config", "list.yaml"],
        "config list.yaml: expected a mapping of LightningCLI fields, got list",
    ),
    (["--channels", "3"], "--channels '3': the data has channels 0..0"),
    (["--trainer.default_root_dir"], "--trainer.default_root_dir needs a folder"),
    (
        ["--model.init_args.n_gaussiansx=3"],
        "--model.init_args.n_gaussiansx: unknown option of "
        "fgat.modules.StaticModule; did you mean n_gaussians?",
    ),
]


@pytest.mark.parametrize(("change", "expected"), CASES, ids=[c[1][:40] for c in CASES])
def test_bad_pipeline_input_fails_with_one_line(change, expected, configs, capsys, monkeypatch):
    ran = []
    monkeypatch.setattr("fgat.app.lightning_cli.run", ran.append)  # no stage may start
    words = {"--config": "dynamic.yaml", "--static": "static.yaml"}
    extra = []
    for option, value in zip(change[::2], change[1::2] + [None]):
        if option in words:
            words[option] = value
        else:
            extra += [option] + ([value] if value is not None else [])
    argv = ["pipeline", *[w for pair in words.items() for w in pair], *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fgat pipeline: error: ") and expected in err[0], err
    assert ran == []
