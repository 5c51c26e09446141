"""The shipped configs: every command in a config's header runs the configuration it says, and
``fgat pipeline`` lays several config files in order."""

import inspect
import shlex
from pathlib import Path

import pytest
import yaml

from fgat.app.cli import main
from fgat.app.crossinfo_tables import CrossInfoConfig
from fgat.app.lightning_cli import resolved_config
from fgat.app.pipeline import merged_config, run_pipeline
from fgat.app.recipes.optics import recipe_configs
from fgat.sim.simulation import SimulationConfig

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
FILES = sorted(str(path.relative_to(ROOT)) for path in CONFIGS.rglob("*.yaml"))


def header_commands(path: Path) -> list[list[str]]:
    """The commands in a config's leading comment: lines that start with ``python`` or
    ``reproduce/``, continued over the next comment line by a trailing backslash."""
    commands, pending = [], None
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        text = line[1:].strip()
        if pending is None and not text.startswith(("python ", "reproduce/")):
            continue
        pending = text if pending is None else f"{pending} {text}"
        if pending.endswith("\\"):
            pending = pending[:-1].rstrip()
        else:
            commands.append(shlex.split(pending))
            pending = None
    return commands


def option_values(words: list[str], option: str) -> list[str]:
    return [value for word, value in zip(words, words[1:]) if word == option]


def compositions(command: list[str]) -> list[list[str]]:
    """The lists of config files a documented command resolves (one per stage it fits)."""
    if command[:3] == ["python", "-m", "fgat"] and command[3] in ("simulate", "analyze"):
        return [option_values(command, "--config")]
    if command[:3] == ["python", "-m", "fgat"] or command[:2] == ["python", "reproduce/figS12.py"]:
        configs = option_values(command, "--config")
        statics = option_values(command, "--static")
        dynamics = option_values(command, "--dynamic")
        if not statics:
            return [configs]
        return [configs + dynamics, configs + statics]
    if command[:2] == ["python", "reproduce/optics.py"]:
        return [recipe_configs(command[2], "--quick" in command)]
    if command[0] == "reproduce/figS9.sh":
        return [recipe_configs("figS9", "--quick" in command)]
    raise AssertionError(f"unknown command in a config header: {shlex.join(command)}")


def check_composition(files: list[str]) -> None:
    """Resolve ``files`` as ``fit`` does and build the model and data settings from them
    (validates the fields; nothing is simulated or fitted)."""
    from fgat.app.datamodules import FLFMDataModule, PhantomDataModule
    from fgat.app.modules import DynamicModule, StaticModule

    if files[0].startswith("configs/simulate/"):
        SimulationConfig.from_yaml(files[0])
        return
    if files[0].startswith("configs/crossinfo"):  # python -m fgat analyze crossinfo
        CrossInfoConfig.from_yaml(files[0])
        return
    config = resolved_config(["fit", *(word for path in files for word in ("--config", path))])
    modules = {
        "fgat.modules.StaticModule": StaticModule,
        "fgat.modules.DynamicModule": DynamicModule,
    }
    modules[config["model"]["class_path"]](**config["model"]["init_args"])
    if config["data"]["class_path"] == "fgat.datamodules.FLFMDataModule":
        # Measured data: the files come from the recipe's earlier commands, so only the fields
        # are checked here.
        fields = set(inspect.signature(FLFMDataModule).parameters)
        assert set(config["data"]["init_args"]) <= fields, set(config["data"]["init_args"]) - fields
        return
    PhantomDataModule(**config["data"]["init_args"])


@pytest.mark.parametrize("name", FILES)
def test_header_commands_run_the_config(name, monkeypatch):
    monkeypatch.chdir(ROOT)  # the commands are run from the repository root
    commands = header_commands(ROOT / name)
    assert commands, f"{name}: no command in its header"
    used = [compositions(command) for command in commands]
    assert any(name in files for stages in used for files in stages), (
        f"{name}: its header's commands do not use it"
    )
    for stages in used:
        for files in stages:
            missing = [path for path in files if not (ROOT / path).is_file()]
            assert not missing, f"{name}: its header names missing configs {missing}"
            check_composition(files)


def test_every_config_is_part_of_a_recipe():
    named = {
        path
        for name in FILES
        for command in header_commands(ROOT / name)
        for stages in [compositions(command)]
        for files in stages
        for path in files
    }
    assert named == set(FILES)


def test_pipeline_lays_several_configs_in_order(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    files = {
        "base.yaml": {
            "trainer": {"default_root_dir": "first", "max_steps": 5},
            "data": {"init_args": {}},
        },
        "recipe.yaml": {"trainer": {"default_root_dir": "second"}},
        "static.yaml": {"trainer": {"max_steps": 3}},
        "static_more.yaml": {"model": {"init_args": {}}},
    }
    for name, content in files.items():
        (tmp_path / name).write_text(yaml.safe_dump(content))
    assert merged_config(["base.yaml", "recipe.yaml"])["trainer"] == {
        "default_root_dir": "second",
        "max_steps": 5,
    }
    stages = []
    monkeypatch.setattr(
        "fgat.app.pipeline.run_stage",
        lambda label, base, args: stages.append((label, base, args)) or base,
    )
    monkeypatch.setattr("fgat.app.pipeline.stage_result", lambda folder, *names: folder / names[0])
    result = run_pipeline(
        ["base.yaml", "recipe.yaml"],
        ["static.yaml", "static_more.yaml"],
        None,
        ["--seed_everything=1"],
    )
    (static_label, static_root, static_args), (dynamic_label, dynamic_root, dynamic_args) = stages
    assert static_root == Path("second/static") and dynamic_root == Path(
        "second/dynamic"
    )  # the later root
    assert static_args[:9] == [
        "--config",
        "base.yaml",
        "--config",
        "recipe.yaml",
        "--config",
        "static.yaml",
        "--config",
        "static_more.yaml",
        "--seed_everything=1",
    ]
    assert dynamic_args[:4] == ["--config", "base.yaml", "--config", "recipe.yaml"]
    assert "--config" not in dynamic_args[4:]
    assert result.volumes == Path("second/dynamic/volumes.ome.tif")
    ran = []
    monkeypatch.setattr("fgat.app.lightning_cli.run", ran.append)
    assert (
        main(
            [
                "pipeline",
                "--config",
                "base.yaml",
                "--config",
                "missing.yaml",
                "--static",
                "static.yaml",
            ]
        )
        == 2
    )
    assert "config missing.yaml does not exist" in capsys.readouterr().err
    assert ran == []
