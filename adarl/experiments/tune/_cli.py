"""The ``adarl tune`` command's arguments and its entry (:func:`cli`), light enough for the ``adarl`` parser to
import at its top: Optuna, torch and the study driver (:mod:`adarl.experiments.tune._study`) are imported when it
runs."""

from __future__ import annotations

import argparse
import sys

from adarl.experiments.launcher_args import add_launcher_arguments, launcher_options

__all__ = ["HELP", "DESCRIPTION", "add_arguments", "cli"]

HELP = "hyperparameter search over recipe keys (Optuna), resumable"
DESCRIPTION = (
    "Run (or continue) the hyperparameter search of TARGET: a tune spec (a YAML file with kind: tune, or a shipped "
    "spec's name: `adarl recipes` lists them under 'tune specs'), or a recipe (a name or a .yaml path) searched over "
    "the default space of its algorithm (sac, td3, ddpg, ppo; after rl-baselines3-zoo's) and of its rank rule, "
    "20 trials unless --n-trials. key=value overrides apply to every trial (a small budget: "
    "collector.total_frames=N); a key they set is left out of a default space. Each trial is a run folder under "
    "DIR/trials/, the study is DIR/study.db; killed and started again it continues; the trials' runs train here "
    "(-j N trials at a time) or on Ray or SLURM (--launcher). Writes DIR/best_recipe.yaml, DIR/trials.csv, "
    "DIR/report.md and DIR/tune_spec.yaml (the spec as run, its space included)."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="TARGET", help="a tune spec (file or shipped name) or a recipe (name or path)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="recipe overrides for every trial")
    p.add_argument(
        "--n-trials",
        type=int,
        default=None,
        help="the study's trial budget (default: the spec's n_trials; 20 for a recipe)",
    )
    p.add_argument("--output", "-o", default=None, help="output folder (default: the spec's, or runs/tune/<name>)")
    p.add_argument(
        "--workers",
        "-j",
        type=int,
        default=None,
        help="trials at a time, each with its seeds' runs at once (default: the spec's workers)",
    )
    add_launcher_arguments(p, what="the trials' runs", sizes="1 CPU, no GPU", urls=False)


def cli(args) -> int:
    from adarl.errors import AdaRLValueError

    if args.n_trials is not None and args.n_trials < 1:
        raise AdaRLValueError(f"--n-trials must be >= 1, got {args.n_trials}")
    bad = [o for o in args.overrides if "=" not in o]
    if bad:
        raise AdaRLValueError(f"overrides are key=value, got {' '.join(bad)!r}")
    try:
        from adarl.experiments.tune._spec import tune_target
        from adarl.experiments.tune._study import run_tune
    except ImportError as err:
        if getattr(err, "name", "") != "optuna":
            raise
        print("adarl: error: adarl tune needs Optuna: pip install 'adarl[tune]'", file=sys.stderr)
        return 1
    result = run_tune(
        tune_target(args.spec, args.overrides, args.n_trials),
        output=args.output,
        workers=args.workers,
        launcher=args.launcher,
        launcher_options=launcher_options(args),
    )
    print("tune done: " + ", ".join(f"{n} {k.lower()}" for k, n in sorted(result.states.items())))
    return 0
