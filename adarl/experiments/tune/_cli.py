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
    "Run (or continue) the hyperparameter search of the tune SPEC (a YAML file with kind: tune, or a shipped spec "
    "name, see recipes/tune/): each trial a run folder under DIR/trials/, the study in DIR/study.db; killed and "
    "started again it continues; the trials' runs train here (-j N trials at a time) or on Ray or SLURM (--launcher). "
    "Writes DIR/best_recipe.yaml, DIR/trials.csv and DIR/report.md."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec")
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
    try:
        from adarl.experiments.tune._study import run_tune
    except ImportError as err:
        if getattr(err, "name", "") != "optuna":
            raise
        print("adarl: error: adarl tune needs Optuna: pip install 'adarl[tune]'", file=sys.stderr)
        return 1
    result = run_tune(
        args.spec,
        output=args.output,
        workers=args.workers,
        launcher=args.launcher,
        launcher_options=launcher_options(args),
    )
    print("tune done: " + ", ".join(f"{n} {k.lower()}" for k, n in sorted(result.states.items())))
    return 0
