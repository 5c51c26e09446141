"""``python -m fgat sweep``: a grid of runs (fit or pipeline), in parallel on Ray or one by one.

A sweep is the cartesian product of ``--grid`` overrides (``KEY=V1,V2,...`` or, for integers,
``KEY=START:STOP[:STEP]`` with ``STOP`` excluded as in Python), each point one ``fit`` (or
``pipeline``) of the same configs with its overrides. ``seed`` is the trial's seed: it sets
``seed_everything``, the model's ``seed`` and, for simulated data, the simulation's (scene, optics
and noise; :func:`seed_options`). A fit trial that finished before with the same fingerprint (its
resolved configuration and input files, ``fgat.app.fingerprint``; the ``fgat.app.fingerprint`` tag
of its MLflow run) is skipped before anything starts (``--refit`` runs it again); a changed
override runs again. A pipeline trial skips its own finished stages. A trial runs in
``<root>/<name>-<fingerprint[:8]>`` (fit) or ``<root>/<name>`` (pipeline), where ``<root>`` is
the configs' ``trainer.default_root_dir`` (else ``runs/<experiment>``) and ``<name>`` says the
point (``lr_means0.5-seed1``; also the fit's MLflow run name).

The trials run as :mod:`fgat.app.trials` says: one after another by default (``--parallel 1``),
on a local Ray with ``--parallel N`` or ``auto``, on a Ray cluster with ``--address``; each failed
one is run once more, and the exit code is 1 when one failed twice, 130 or 143 when Ctrl-C or
SIGTERM stopped the sweep. A grid is counted before it is listed: more than ``--max-trials``
points (default 1000) is refused, and from 20 points on the sweep says how many it resolves, and
how far it got.
"""

from __future__ import annotations

import argparse
import itertools
import math
import re
import time
from collections.abc import Sequence

from fgat.app import trials
from fgat.app.signals import StopSignals
from fgat.app.trials import (
    Trial,
    add_fanout_arguments,
    add_refit_argument,
    fanout_from,
    fit_trial,
    run_trials,
)

SEED = "seed"


RANGE = re.compile(r"-?\d+:-?\d+(:-?\d+)?")


def parse_grid(text: str) -> tuple[str, range | list[str]]:
    """``"KEY=V1,V2"`` or ``"KEY=START:STOP[:STEP]"`` (integers, ``STOP`` excluded) as the
    option name and its values, in order: a ``range`` for a range (its length known without
    listing it), else the texts. Commas inside brackets or braces belong to the value
    (``aberrations={terms: 17, rms: 0.5},{terms: 17, rms: 1}``).

    Raises
    ------
    ValueError
        Naming ``--grid``, the text and the expected form.
    """
    key, equals, values = text.partition("=")
    key = key.strip().removeprefix("--")
    expected = "expected KEY=V1,V2,... or KEY=START:STOP[:STEP], e.g. seed=0:5"
    if not equals or not key or " " in key:
        raise ValueError(f"--grid {text!r}: {expected}")
    if RANGE.fullmatch(values.strip()):
        bounds = [int(bound) for bound in values.split(":")]
        if len(bounds) == 3 and bounds[2] == 0:
            raise ValueError(f"--grid {text!r}: a range's step cannot be 0")
        chosen = range(*bounds)
        if not chosen:
            raise ValueError(f"--grid {text!r}: no value, or an empty one; {expected}")
        return key, chosen
    items = [value.strip() for value in _top_level_items(values)]
    if any(not value for value in items):
        raise ValueError(f"--grid {text!r}: no value, or an empty one; {expected}")
    if len(set(items)) < len(items):
        raise ValueError(f"--grid {text!r}: a value is given twice")
    return key, items


def _top_level_items(text: str) -> list[str]:
    """``text`` split at the commas outside brackets and braces."""
    items, depth, start = [], 0, 0
    for index, character in enumerate(text):
        depth += (character in "[{") - (character in "]}")
        if character == "," and depth == 0:
            items.append(text[start:index])
            start = index + 1
    return [*items, text[start:]]


MAX_TRIALS = 1000
"""The most grid points a sweep takes unless ``--max-trials`` raises it: each point's
configuration is resolved and checked before any trial starts (about a second each)."""

RESOLVING_NOTICE = 20
"""From this many points on, the sweep says how many it resolves, and its progress."""


def grid_points(grids: Sequence[str], max_trials: int = MAX_TRIALS) -> list[dict[str, str]]:
    """The cartesian product of the ``--grid`` texts (:func:`parse_grid`), the last grid varying
    fastest: one ``{option: value}`` per trial.

    Raises
    ------
    ValueError
        A key swept twice, or more than ``max_trials`` points (counted before any is listed).
    """
    parsed = [parse_grid(text) for text in grids]
    keys = [key for key, _ in parsed]
    repeated = sorted({key for key in keys if keys.count(key) > 1})
    if repeated:
        raise ValueError(f"--grid: {repeated[0]} is swept twice; give its values in one --grid")
    count = math.prod(len(values) for _, values in parsed)
    if count > max_trials:
        sizes = " x ".join(str(len(values)) for _, values in parsed)
        raise ValueError(
            f"--grid: {count} trials ({sizes}) is more than --max-trials {max_trials}; give "
            f"--max-trials {count} to run them all"
        )
    return [
        {key: str(value) for key, value in zip(keys, values)}
        for values in itertools.product(*(values for _, values in parsed))
    ]


def point_name(point: dict[str, str]) -> str:
    """A folder and run name for a grid point: ``rms0.5-seed0`` (the last part of each option's
    name and its value, without characters a file name should not hold)."""
    parts = [f"{key.rsplit('.', 1)[-1]}{value}" for key, value in point.items()]
    return re.sub(r"[^\w.+-]", "", "-".join(parts)) or "trial"


def seed_options(config: dict) -> list[str]:
    """What ``seed`` sets in a resolved configuration: ``seed_everything``, the model's ``seed``
    and, when the data are simulated, every ``seed`` of the simulation (its own, and those of
    its aberrations or phantom where a config gives them: the scene, optics and noise drawn)."""
    options = ["seed_everything"]
    model = (config.get("model") or {}).get("init_args") or {}
    if "seed" in model:
        options.append("model.init_args.seed")
    data = (config.get("data") or {}).get("init_args") or {}
    return options + _seed_keys(data.get("simulation"), "data.init_args.simulation")


def _seed_keys(node, prefix: str) -> list[str]:
    """The dotted paths of the ``seed`` keys in nested mappings."""
    if not isinstance(node, dict):
        return []
    keys = [f"{prefix}.seed"] if "seed" in node else []
    for key, value in node.items():
        keys += _seed_keys(value, f"{prefix}.{key}")
    return keys


def overrides(point: dict[str, str], seeds: Sequence[str] = ("seed_everything",)) -> list[str]:
    """A grid point as command-line overrides (``--KEY=VALUE``); ``seed`` sets every option of
    ``seeds`` (:func:`seed_options`)."""
    words = []
    for key, value in point.items():
        words += [f"--{option}={value}" for option in (seeds if key == SEED else [key])]
    return words


def sweep_trials(args: argparse.Namespace) -> list[Trial]:
    """The trials of ``fgat sweep``'s options (grid points not finished before), each resolved
    and checked before any runs."""
    from fgat._core.validation import check_number  # imported when used: keeps start-up fast
    from fgat.app.lightning_cli import resolved_config  # imported when used: keeps start-up fast
    from fgat.app.pipeline import (  # imported when used: keeps start-up fast
        merged_config,
        option_words,
        pipeline_tracking,
        pipeline_trial,
        split_root,
    )

    points = grid_points(
        args.grid, check_number("--max-trials", args.max_trials, minimum=1, integer=True)
    )
    if args.command == "fit" and (args.static or args.dynamic):
        raise ValueError("--static and --dynamic belong to --command pipeline")
    if args.command == "pipeline" and not args.static:
        raise ValueError("--command pipeline needs --static (the static stage's config)")
    layers = option_words("--config", args.config)
    statics = option_words("--config", args.static)
    seeds = seed_options(resolved_config(["fit", *layers, *statics, *args.extra]))
    root, forwarded = split_root(list(args.extra), merged_config(args.config))
    trials = []
    progress = Progress(len(points))
    for point in points:
        progress.step()
        name = point_name(point)
        if args.command == "pipeline":  # the pipeline names its runs static and dynamic
            extra = [*forwarded, *overrides(point, seeds)]
            tracking = pipeline_tracking(args.config, args.static, extra)  # checks the point
            trial = pipeline_trial(
                name, args.config, args.static, args.dynamic, extra, root / name, tracking
            )
        else:
            extra = [*args.extra, *overrides(point, seeds)]
            words = ["fit", *layers, f"--mlflow.run_name={name}", *extra]
            trial = fit_trial(words, name=name, refit=args.refit)
        if trial is not None:
            trials.append(trial)
    return trials


class Progress:
    """Says how many grid points are resolved when there are many (at least
    :data:`RESOLVING_NOTICE`), and how far it got every :attr:`every_s` seconds."""

    every_s = 10.0

    def __init__(self, total: int) -> None:
        self.total, self.done = total, 0
        self.started = self.said = time.monotonic()
        if total >= RESOLVING_NOTICE:
            print(
                f"fgat sweep: resolving and checking the configurations of {total} grid points "
                "before any trial starts",
                flush=True,
            )

    def step(self) -> None:
        """One more point is being resolved."""
        now = time.monotonic()
        if self.total >= RESOLVING_NOTICE and self.done and now - self.said >= self.every_s:
            left = (self.total - self.done) * (now - self.started) / self.done
            print(
                f"fgat sweep: resolved {self.done} of {self.total} grid points (about {left:.0f} s "
                "left)",
                flush=True,
            )
            self.said = now
        self.done += 1


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "sweep",
        help="a grid of fit or pipeline runs, on Ray or one by one",
        description=__doc__.split("\n\n")[1] + "\n\n" + trials.__doc__.split("\n\n")[1],
        epilog="Other options (e.g. --trainer.max_steps=500) are passed to every trial. "
        "Example: python -m fgat sweep --config configs/base/common.yaml --config "
        'configs/quickstart.yaml --grid "model.init_args.lr_means=0.5,1" --grid seed=0:2',
    )
    parser.add_argument(
        "--grid",
        action="append",
        required=True,
        metavar="KEY=VALUES",
        help="an override and its values: KEY=V1,V2 or KEY=START:STOP[:STEP]; repeat it for a "
        "cartesian product",
    )
    parser.add_argument(
        "--config", action="append", required=True, help="a LightningCLI config, laid in order"
    )
    parser.add_argument(
        "--command",
        choices=("fit", "pipeline"),
        default="fit",
        help="what each point runs: a fit (default) or a pipeline (--static, --dynamic)",
    )
    parser.add_argument(
        "--static", action="append", default=[], help="pipeline: the static stage's config"
    )
    parser.add_argument(
        "--dynamic", action="append", default=[], help="pipeline: the dynamic stage's config"
    )
    add_refit_argument(parser)
    parser.add_argument(
        "--max-trials",
        default=MAX_TRIALS,
        metavar="N",
        help=f"refuse a grid of more points (default {MAX_TRIALS}); each point is resolved and "
        "checked before any trial starts",
    )
    add_fanout_arguments(parser)
    parser.set_defaults(run=_run, forwards_unknown=True)


def _run(args) -> int:
    """Resolve the trials and run them; SIGINT or SIGTERM ends it with
    :class:`fgat.app.signals.Interrupted` (exit code 130 or 143), no trial started after it."""
    fanout = fanout_from(args)
    with StopSignals():
        outcomes = run_trials(sweep_trials(args), fanout)
    return 0 if all(outcome.finished for outcome in outcomes) else 1
