"""Bad input to fit / validate / predict: one line, exit code 2, before anything is computed.

Every case runs ``fgat.app.cli.main`` in-process on a tiny config. While it runs, simulating a
phantom, setting up any datamodule and an SHB deconvolution in the static stage raise
``AssertionError``, so a case that got that far fails loudly; afterwards the MLflow store must hold
no run.
"""

import pickle
import types
from pathlib import Path

import matplotlib
import mlflow
import numpy as np
import pytest
import torch
import yaml

import fgat.app.datamodules.scene
import fgat.recon.scene
import fgat.recon.static
from fgat.app.callbacks.artifacts import fit_summary
from fgat.app.cli import main
from fgat.app.datamodules import FLFMDataModule
from fgat.gaussians.cloud import GaussianCloud
from fgat.recon import load_static
from fgat.sim.simulation import SimulationConfig, simulate, write_simulation
from fgat.viz.volumes import mip_series_figure, mips_figure

BEADS = {"kind": "beads", "n_beads": 4, "sigma": 1.0, "min_spacing": 6, "margin": [1, 5, 5]}
MOVING = {
    "kind": "moving_beads",
    "n_beads": 3,
    "sigma": 1.0,
    "velocity": [0.0, 6.0, 0.0],
    "rotation_deg": 0.0,
    "min_spacing": 5.0,
    "margin": [2, 9, 5],
}
TRAINER = {
    "max_steps": 20,
    "accelerator": "cpu",
    "val_check_interval": 10,
    "check_val_every_n_epoch": None,
    "num_sanity_val_steps": 0,
    "enable_progress_bar": False,
    "enable_model_summary": False,
}


class Payload:
    """Unpickling this creates ``target``: proof that a loader ran code from a file."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):
        return open, (str(self.target), "w")


def write_yaml(path: Path, content: dict) -> str:
    path.write_text(yaml.safe_dump(content))
    return str(path)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Configs (static phantom, dynamic phantom, measured data), a simulation folder and
    checkpoint files; the checkpoints hold only what the set-up checks read."""
    root = tmp_path_factory.mktemp("inputs")
    simulation = {"system": "small", "depths_um": "-9:9:7", "view_size": 32, "photons": None}
    write_simulation(simulate(SimulationConfig(**simulation, phantom=BEADS)), root / "sim")
    files = {
        name: root / name
        for name in ("static.ckpt", "dynamic.ckpt", "garbage.ckpt", "a_file", "existing.tif")
    }
    for name, model in (("static.ckpt", "StaticModule"), ("dynamic.ckpt", "DynamicModule")):
        torch.save(
            {
                "state_dict": {},
                "pytorch-lightning_version": "2.6.6",
                "hyper_parameters": {"_class_path": f"fgat.modules.{model}"},
                "reconstruction": {},
            },
            files[name],
        )
    files["garbage.ckpt"].write_text("not a checkpoint\n")
    files["truncated.ckpt"] = root / "truncated.ckpt"
    files["truncated.ckpt"].write_bytes(files["static.ckpt"].read_bytes()[:300])
    files["a_file"].write_text("a file\n")
    files["existing.tif"].write_bytes(b"already there")
    base = {"seed_everything": 0, "trainer": TRAINER}
    static = {
        "class_path": "fgat.modules.StaticModule",
        "init_args": {"n_gaussians": 100, "init_iterations": 5, "baseline_iterations": 5},
    }
    configs = {
        "static": write_yaml(
            root / "static.yaml",
            {
                **base,
                "model": static,
                "data": {
                    "class_path": "fgat.datamodules.PhantomDataModule",
                    "init_args": {"simulation": {**simulation, "phantom": BEADS}},
                },
            },
        ),
        "dynamic": write_yaml(
            root / "dynamic.yaml",
            {
                **base,
                "model": {
                    "class_path": "fgat.modules.DynamicModule",
                    "init_args": {"static": str(root / "no_static_run"), "width": 16},
                },
                "data": {
                    "class_path": "fgat.datamodules.PhantomDataModule",
                    "init_args": {"simulation": {**simulation, "frames": 5, "phantom": MOVING}},
                },
            },
        ),
        "flfm": write_yaml(
            root / "flfm.yaml",
            {
                **base,
                "model": static,
                "data": {
                    "class_path": "fgat.datamodules.FLFMDataModule",
                    "init_args": {
                        "measurement": str(root / "sim" / "sensor.ome.tif"),
                        "centers": str(root / "sim" / "centers.csv"),
                        "psf": str(root / "sim" / "psf.ome.tif"),
                        "truth": str(root / "sim" / "truth.ome.tif"),
                    },
                },
            },
        ),
    }
    paths = {name.split(".")[0]: path for name, path in files.items()}
    return types.SimpleNamespace(root=root, configs=configs, **paths)


@pytest.fixture
def nothing_computed(monkeypatch):
    """Fail the test if a case simulates, sets up data or runs SHB."""

    def refuse(*args, **kwargs):
        raise AssertionError(
            "computation started: the bad input was not refused at parse or set-up time"
        )

    monkeypatch.setattr(fgat.recon.scene, "simulate", refuse)
    monkeypatch.setattr(fgat.app.datamodules.scene.SceneDataModule, "setup", refuse)
    monkeypatch.setattr(fgat.recon.static, "deconvolve", refuse)


def run_cli(subcommand, config, overrides, tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    args = [
        subcommand,
        "--config",
        config,
        f"--mlflow.tracking_uri={uri}",
        f"--trainer.default_root_dir={tmp_path / 'run'}",
        *overrides,
    ]
    return main(args), uri


def assert_one_line_and_no_run(capsys, code, expected, uri, tmp_path):
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert "Traceback" not in err and "usage:" not in err, err
    assert lines[-1].startswith("fgat ") and expected in lines[-1], err
    if (tmp_path / "mlflow.db").exists():
        client = mlflow.MlflowClient(uri)
        experiments = [e.experiment_id for e in client.search_experiments()]
        assert not experiments or client.search_runs(experiments) == []


CASES = [
    # wrong fields and types: jsonargparse's report in one line
    (
        "fit",
        "static",
        ["--model.init_args.n_gaussiansx=3"],
        "--model.init_args.n_gaussiansx: unknown option of fgat.modules.StaticModule; "
        "did you mean n_gaussians?",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.n_gaussians=abc"],
        "--model.init_args.n_gaussians: expected int, got abc",
    ),
    (
        "fit",
        "static",
        ["--trainer.max_stepz=5"],
        "--trainer.max_stepz: unknown option; did you mean --trainer.max_steps?",
    ),
    (
        "fit",
        "static",
        ["--model.class_path=fgat.modules.Nope"],
        "--model.class_path: cannot import fgat.modules.Nope",
    ),
    (
        "fit",
        "static",
        ["--data.init_args.simulation=5"],
        "--data.init_args.simulation: expected dot import path string: 5",
    ),
    (
        "fit",
        "static",
        ["--config", "{root}/missing.yaml"],
        "--config {root}/missing.yaml does not exist",
    ),
    # nonsense values, refused by the constructors with the field named
    (
        "fit",
        "static",
        ["--model.init_args.n_gaussians=0"],
        "model.n_gaussians must be a positive integer, got 0",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.n_gaussians=10000000000"],
        "model.n_gaussians = 10000000000 Gaussians need about 48.8 TB; this machine has",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.init_iterations=-1"],
        "model.init_iterations must be a positive integer",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.lr_means=-0.01"],
        "model.lr_means must be a positive number, got -0.01",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.lr_intensities=0"],
        "model.lr_intensities must be a positive number, got 0",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.init_scale=-1"],
        "model.init_scale must be a positive number, got -1",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.init_scale=0.5"],
        "model.init_scale must be within scale_range [0.8, 20.0]",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.scale_range=[20,0.8]"],
        "model.scale_range must be [s_min, s_max] with 0 < s_min < s_max (lateral voxels), "
        "got [20.0, 0.8]",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.baseline_iterations=-3"],
        "model.baseline_iterations must be a non-negative",
    ),
    ("fit", "static", ["--model.init_args.p=3"], "model.p must be 1 (MAE) or 2 (MSE), got 3"),
    (
        "fit",
        "static",
        ["--model.init_args.lambda_ssim=-1"],
        "model.lambda_ssim must be a non-negative number, got -1",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.densification.interval=0"],
        "densification.interval must be a positive number of steps, got 0",
    ),
    (
        "fit",
        "static",
        ["--model.init_args.densification.intervall=5"],
        "densification.intervall: unknown option",
    ),
    ("fit", "static", ["--model.init_args.optics.estimte=joint"], "optics.estimte: unknown option"),
    (
        "fit",
        "static",
        ["--data.init_args.simulation.system=tiny"],
        "data.simulation: unknown system 'tiny'",
    ),
    (
        "fit",
        "static",
        ["--data.init_args.simulation.viewsize=64"],
        "simulation.init_args.viewsize: unknown option of fgat.sim.simulation.SimulationConfig; "
        "did you mean view_size?",
    ),
    (
        "fit",
        "static",
        ["--data.init_args.simulation.view_size=-3"],
        "data.simulation: view_size must be a positive integer, got -3",
    ),
    (
        "fit",
        "static",
        ["--data.init_args.psf=best"],
        "data.psf must be 'true', 'ideal' or a PSF TIFF path, got 'best'",
    ),
    (
        "fit",
        "static",
        ["--data.init_args.psf=missing.tif"],
        "data.psf: file missing.tif does not exist",
    ),
    (
        "fit",
        "flfm",
        ["--data.init_args.measurement=missing.tif"],
        "data.measurement: file missing.tif does not exist",
    ),
    (
        "fit",
        "flfm",
        [
            "--data.init_args.psf=null",
            "--data.init_args.system=tiny",
            "--data.init_args.depths_um=0",
        ],
        "data.system: unknown system 'tiny'",
    ),
    (
        "fit",
        "flfm",
        ["--data.init_args.view_size=-3"],
        "data.view_size must be a positive number of pixels",
    ),
    (
        "fit",
        "flfm",
        ["--data.init_args.background=-5"],
        "data.background must be a camera offset >= 0 (counts), or null (the camera model's), "
        "got -5",
    ),
    (
        "fit",
        "flfm",
        ["--data.init_args.frame=-1"],
        "data.frame must be an index >= 0, or null, got -1",
    ),
    (
        "fit",
        "dynamic",
        ["--model.init_args.lr_planes=0"],
        "model.lr_planes must be a positive number, got 0",
    ),
    (
        "fit",
        "dynamic",
        ["--model.init_args.width=0"],
        "model.width must be a positive integer (MLP width), got 0",
    ),
    (
        "fit",
        "dynamic",
        ["--model.init_args.hexplane.levels=0"],
        "hexplane.levels must be a positive integer, got 0",
    ),
    (
        "fit",
        "dynamic",
        ["--data.init_args.reference_frame=9"],
        "data.reference_frame: reference frame 9 is outside",
    ),
    # trainer settings
    (
        "fit",
        "static",
        ["--trainer.max_steps=-5"],
        "trainer.max_steps must be a positive number of steps, or -1",
    ),
    (
        "fit",
        "static",
        ["--trainer.max_steps=0"],
        "trainer.max_steps must be a positive number of steps, or -1",
    ),
    (
        "fit",
        "static",
        ["--trainer.max_epochs=-3"],
        "trainer.max_epochs must be a positive number of epochs, or -1",
    ),
    (
        "fit",
        "static",
        ["--trainer.max_steps=-1", "--trainer.max_epochs=0"],
        "trainer.max_epochs must be a positive",
    ),
    (
        "fit",
        "static",
        ["--trainer.default_root_dir={a_file}/run"],
        "{a_file} is a file, not a folder",
    ),
    (
        "validate",
        "static",
        ["--trainer.max_steps=-5"],
        "`max_steps` must be a non-negative integer or -1",
    ),
    ("fit", "static", ["--times", "0:1:3"], "--times, --out and --overwrite belong to 'predict'"),
    # checkpoints
    (
        "fit",
        "static",
        ["--ckpt_path={garbage}"],
        "--ckpt_path: {garbage} is not a readable PyTorch file",
    ),
    (
        "fit",
        "static",
        ["--ckpt_path={truncated}"],
        "--ckpt_path: {truncated} is not a readable PyTorch file "
        "(PytorchStreamReader failed reading zip archive",
    ),
    ("fit", "static", ["--ckpt_path=missing.ckpt"], "--ckpt_path: missing.ckpt does not exist"),
    (
        "fit",
        "static",
        ["--weights_only=false"],
        "--weights_only false: fgat reads checkpoints as weights only",
    ),
    (
        "validate",
        "static",
        ["--ckpt_path={garbage}"],
        "--ckpt_path: {garbage} is not a readable PyTorch file",
    ),
    (
        "validate",
        "static",
        ["--ckpt_path={dynamic}"],
        "--ckpt_path {dynamic} holds a fgat.modules.DynamicModule run, but the config's model is "
        "fgat.modules.StaticModule",
    ),
    # predict
    ("predict", "dynamic", [], "predict needs --ckpt_path"),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={static}"],
        "--ckpt_path {static} holds a fgat.modules.StaticModule run, but the config's model is "
        "fgat.modules.DynamicModule",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={garbage}"],
        "--ckpt_path: {garbage} is not a readable PyTorch file",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={dynamic}", "--times", "1:0:0"],
        "--times '1:0:0': expected normalised times",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={dynamic}", "--times", "abc"],
        "--times 'abc': expected normalised times",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={dynamic}", "--times", "0:2:3"],
        "--times '0:2:3': expected normalised times",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={dynamic}", "--out", "{root}/missing/v.ome.tif"],
        "--out {root}/missing/v.ome.tif: folder {root}/missing does not exist",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={dynamic}", "--out", "{root}"],
        "--out {root}: is a folder; expected a file name",
    ),
    (
        "predict",
        "dynamic",
        ["--ckpt_path={dynamic}", "--out", "{existing}"],
        "--out {existing}: the file exists; choose another name or pass --overwrite to replace it",
    ),
]


@pytest.mark.parametrize(
    "subcommand,config,overrides,expected",
    CASES,
    ids=[f"{c[0]}:{c[1]}:{' '.join(c[2])[:60]}" for c in CASES],
)
def test_bad_input_fails_fast_with_one_line(
    subcommand, config, overrides, expected, inputs, tmp_path, capsys, nothing_computed
):
    names = {
        "root": inputs.root,
        "a_file": inputs.a_file,
        "garbage": inputs.garbage,
        "truncated": inputs.truncated,
        "static": inputs.static,
        "dynamic": inputs.dynamic,
        "existing": inputs.existing,
    }
    overrides = [word.format(**names) for word in overrides]
    code, uri = run_cli(subcommand, inputs.configs[config], overrides, tmp_path)
    assert_one_line_and_no_run(capsys, code, expected.format(**names), uri, tmp_path)


def test_read_only_run_root_is_refused(inputs, tmp_path, capsys, nothing_computed):
    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        (folder / "probe").write_text("")
    except OSError:
        pass
    else:
        pytest.skip(
            "this user writes into read-only folders (root); "
            "a root that is a file is tested instead"
        )
    try:
        code, uri = run_cli(
            "fit", inputs.configs["static"], [f"--trainer.default_root_dir={folder}/run"], tmp_path
        )
        assert_one_line_and_no_run(
            capsys,
            code,
            f"trainer.default_root_dir {folder}/run: cannot write in folder {folder}",
            uri,
            tmp_path,
        )
    finally:
        folder.chmod(0o755)


@pytest.mark.parametrize("form", ["--config {}", "--config={}", "-c {}"])
def test_config_with_a_yaml_error_names_file_line_and_column(form, tmp_path, capsys):
    broken = tmp_path / "broken.yaml"
    broken.write_text("trainer:\n  max_steps: [1, 2\nmodel: x\n")
    assert main(["fit", *form.format(broken).split()]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line == (
        f"fgat fit: error: --config {broken}: invalid YAML at line 3, column 6: "
        "expected ',' or ']', "
        "but got ':' (while parsing a flow sequence started at line 2, column 14)"
    )


@pytest.mark.slow
def test_config_files_are_checked_before_lightning_is_imported(tmp_path):
    """A missing ``--config`` is refused in a fresh process before Lightning is imported (seconds
    on a small machine); an inline YAML mapping, which jsonargparse takes as the options
    themselves, is let through."""
    import subprocess
    import sys

    missing = tmp_path / "missing.yaml"
    probe = (
        "import sys\n"
        "from fgat.app.cli import main\n"
        f"code = main(['fit', '--config', '{{trainer: {{max_steps: 2}}}}', '-c', '{missing}'])\n"
        "print(code, 'lightning' in sys.modules)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120
    )
    assert done.stdout.split() == ["2", "False"], done.stderr
    assert done.stderr.strip() == f"fgat fit: error: --config {missing} does not exist"


def test_help_still_prints_the_whole_help(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "--model.help" in out and "--trainer.max_steps" in out and len(out.splitlines()) > 100


# ---------------------------------------------------------------------- no code from a file runs
@pytest.fixture
def payload(tmp_path):
    """A checkpoint, a raw pickle and a results folder whose unpickling would create ``target``."""
    target = tmp_path / "payload-ran"
    checkpoint = tmp_path / "crafted.ckpt"
    torch.save(
        {"state_dict": {"cloud.means": Payload(target)}, "pytorch-lightning_version": "2.6.6"},
        checkpoint,
    )
    raw = tmp_path / "raw.ckpt"  # a plain pickle, not torch.save's zip
    raw.write_bytes(pickle.dumps({"state_dict": Payload(target)}))
    folder = tmp_path / "results"
    folder.mkdir()
    torch.save({"shape": (1, 1, 1), "state_dict": Payload(target)}, folder / "gaussians.pt")
    return types.SimpleNamespace(target=target, checkpoint=checkpoint, raw=raw, folder=folder)


REFUSED = "contains io.open, not only tensors and plain values; refused"
UNREADABLE = "is not a readable PyTorch file (weights-only unpickler: Unsupported operand"


@pytest.mark.parametrize(
    "subcommand,config,option,file,expected",
    [
        ("fit", "dynamic", "--model.init_args.static", "checkpoint", REFUSED),
        ("fit", "dynamic", "--model.init_args.static", "raw", UNREADABLE),
        ("fit", "dynamic", "--model.init_args.static", "folder", REFUSED),
        ("fit", "static", "--ckpt_path", "checkpoint", REFUSED),
        ("fit", "static", "--ckpt_path", "raw", UNREADABLE),
        ("validate", "static", "--ckpt_path", "checkpoint", REFUSED),
        ("predict", "dynamic", "--ckpt_path", "checkpoint", REFUSED),
    ],
)
def test_crafted_files_run_no_code(
    subcommand, config, option, file, expected, payload, inputs, tmp_path, capsys, nothing_computed
):
    given = getattr(payload, file)
    code, uri = run_cli(subcommand, inputs.configs[config], [f"{option}={given}"], tmp_path)
    shown = given / "gaussians.pt" if file == "folder" else given
    assert_one_line_and_no_run(capsys, code, f"{shown} {expected}", uri, tmp_path)
    assert not payload.target.exists()


def test_loaders_refuse_crafted_files_without_the_cli(payload):
    with pytest.raises(ValueError, match="model.static: .*crafted.ckpt contains io.open"):
        load_static(payload.checkpoint)
    with pytest.raises(ValueError, match="gaussians: .*gaussians.pt contains io.open"):
        GaussianCloud.load(payload.folder / "gaussians.pt")
    assert not payload.target.exists()


def test_gaussian_set_round_trips_as_weights_only(tmp_path):
    """PyTorch's weights-only reader opens the file, and every parameter and physical attribute
    comes back bit for bit."""
    cloud = GaussianCloud((5, 8, 8), (2.0, 0.5, 0.5), 12, seed=3)
    cloud.save(tmp_path / "gaussians.pt")
    payload = torch.load(tmp_path / "gaussians.pt", weights_only=True)
    loaded = GaussianCloud.load(tmp_path / "gaussians.pt")
    state = loaded.state_dict()
    assert set(state) == set(cloud.state_dict()) == set(payload["state_dict"])
    for name, value in cloud.state_dict().items():
        assert torch.equal(state[name], value) and torch.equal(payload["state_dict"][name], value)
    for name in ("means", "scales", "quaternions", "intensities"):
        assert torch.equal(getattr(loaded, name), getattr(cloud, name)), name
    assert loaded.shape == (5, 8, 8) and loaded.scale_range == cloud.scale_range


# ---------------------------------------------------------------------- view size of measured data
def test_measured_data_takes_the_simulations_view_size(tmp_path, capsys):
    config = tmp_path / "sim.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "system": "small",
                "depths_um": "-6:6:5",
                "view_size": 40,
                "photons": None,
                "phantom": BEADS,
            }
        )
    )
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim")]) == 0
    files = {
        name: str(tmp_path / "sim" / name)
        for name in ("sensor.ome.tif", "centers.csv", "psf.ome.tif", "truth.ome.tif")
    }
    data = FLFMDataModule(
        files["sensor.ome.tif"],
        centers=files["centers.csv"],
        psf=files["psf.ome.tif"],
        truth=files["truth.ome.tif"],
    )
    data.setup("fit")
    assert data.scene.volume_shape == (5, 40, 40) and data.scene.truth.shape == (5, 40, 40)
    assert data.scene.measurement.shape == (7, 40, 40)
    without_truth = FLFMDataModule(
        files["sensor.ome.tif"], centers=files["centers.csv"], psf=files["psf.ome.tif"]
    )
    without_truth.setup("fit")  # the simulation's params.yaml
    assert without_truth.scene.volume_shape == (5, 40, 40)
    (tmp_path / "sim" / "params.yaml").unlink()
    elsewhere = FLFMDataModule(
        files["sensor.ome.tif"], centers=files["centers.csv"], psf=files["psf.ome.tif"]
    )
    elsewhere.setup("fit")  # the largest square between the centres of the small system
    assert elsewhere.scene.volume_shape == (5, 76, 76)
    with pytest.raises(  # from the truth's header, as the data module is built
        ValueError,
        match=r"data.truth .*truth.ome.tif: shape \(5, 40, 40\) does not match the "
        r"reconstruction \(5, 32, 32",
    ):
        FLFMDataModule(
            files["sensor.ome.tif"],
            centers=files["centers.csv"],
            psf=files["psf.ome.tif"],
            truth=files["truth.ome.tif"],
            view_size=32,
        )


# --------------------------------------------------------------------- figures and the end of a fit
def test_mips_figure_has_axes_in_um_and_a_colour_bar_per_volume():
    volume = np.zeros((6, 10, 20))
    volume[3, 5, 8] = 7.0
    figure = mips_figure(
        {"4DGAT": volume, "truth": volume / 7},
        voxel_size_um=(2.0, 0.5, 0.5),
        units={"4DGAT": "counts"},
    )
    images = [
        axis for axis in figure.axes if axis.get_images() and axis.get_label() != "<colorbar>"
    ]
    bars = [axis for axis in figure.axes if axis.get_label() == "<colorbar>"]
    assert len(images) == 4 and [bar.get_ylabel() for bar in bars] == ["counts", "a.u."]
    assert [axis.get_title() for axis in images[:2]] == ["4DGAT", "truth"]
    assert (
        images[0].get_ylabel() == "x-y MIP\ny (um)" and images[2].get_ylabel() == "x-z MIP\nz (um)"
    )
    assert images[2].get_xlabel() == "x (um)" and images[3].get_xlabel() == "x (um)"
    assert images[0].get_xlim() == pytest.approx((-5.0, 5.0)) and images[
        2
    ].get_ylim() == pytest.approx((6.0, -6.0))
    assert images[0].get_images()[0].get_clim() == pytest.approx((0.0, 7.0))
    matplotlib.pyplot.close(figure)


def test_mip_series_figure_labels_rows_columns_and_colour_bars():
    series = {
        "4DGAT": np.random.default_rng(0).random((5, 3, 8, 12)),
        "truth": np.ones((5, 3, 8, 12)),
    }
    figure = mip_series_figure(
        series, np.linspace(0, 1, 5), voxel_size_um=(1.5, 0.25, 0.25), units={"4DGAT": "counts"}
    )
    images = [
        axis for axis in figure.axes if axis.get_images() and axis.get_label() != "<colorbar>"
    ]
    bars = [axis for axis in figure.axes if axis.get_label() == "<colorbar>"]
    assert len(images) == 10 and [bar.get_ylabel() for bar in bars] == ["counts", "a.u."]
    assert [axis.get_title() for axis in images[:5]] == [
        "t = 0.00",
        "t = 0.25",
        "t = 0.50",
        "t = 0.75",
        "t = 1.00",
    ]
    assert images[0].get_ylabel() == "4DGAT\ny (um)" and images[5].get_ylabel() == "truth\ny (um)"
    assert all(axis.get_xlabel() == "x (um)" for axis in images[5:])
    assert images[0].get_xlim() == pytest.approx((-1.5, 1.5))
    matplotlib.pyplot.close(figure)


def test_fit_summary_gives_scores_folder_and_mlflow_run(tmp_path):
    from lightning.pytorch.loggers import MLFlowLogger

    logger = MLFlowLogger(
        experiment_name="summary",
        run_name="fit-static-test",
        tracking_uri=f"sqlite:///{tmp_path}/mlflow.db",
    )
    metrics = {
        "val/psnr_volume": 45.634,
        "val/psnr_volume_shb": 36.571,
        "val/psnr_volume_registered": 46.018,
        "val/ssim_mip_xy": 0.9951,
        "val/ssim_mip_xy_shb": 0.8712,
        "loss": 0.01,
    }
    trainer = types.SimpleNamespace(
        callback_metrics={k: torch.tensor(v) for k, v in metrics.items()},
        global_step=800,
        loggers=[logger],
    )
    lines = fit_summary(trainer, tmp_path / "results" / "run").splitlines()
    assert lines[0] == (
        "fgat: fit finished at step 800; last validation: val/psnr_volume 45.63 dB (SHB 36.57 dB), "
        "val/psnr_volume_registered 46.02 dB, val/ssim_mip_xy 0.995 (SHB 0.871)"
    )
    assert lines[1] == f"  results: {tmp_path / 'results' / 'run'}"
    assert lines[2] == (
        f"  MLflow: run fit-static-test ({logger.run_id}) in experiment 'summary'; to browse runs: "
        f"mlflow ui --backend-store-uri sqlite:///{tmp_path}/mlflow.db"
    )
