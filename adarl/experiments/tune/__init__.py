"""Hyperparameter search (``adarl tune SPEC``): the spec, the Optuna study and the command.

The hub of the tuning wing; the work is done in private modules, one job each: ``_spec`` (the ``kind: tune`` spec
and its validation against the recipe: :func:`load_tune_spec`, :func:`check_space`; a spec or a bare recipe as a
study: :func:`tune_target`), ``_defaults`` (the default search spaces, after rl-zoo's: :func:`default_space`),
``_study`` (the study driver: :func:`run_tune`, Optuna underneath), ``_records`` (trial records and scores),
``_outputs`` (``trials.csv``, ``best_recipe.yaml``, plots and ``report.md``), ``_cli`` (the command's arguments and
entry).

The ``adarl`` parser imports this hub at its top, so only the command's arguments load with it; the other names
load on first use (PEP 562, by name): Optuna, pydantic and torch are imported when the search runs.
"""

from __future__ import annotations

from adarl.experiments.tune._cli import DESCRIPTION, HELP, add_arguments, cli

#: name -> the private module that holds it (loaded on first use)
_LAZY = {
    **dict.fromkeys(
        [
            "run_tune",
            "TuneResult",
            "STUDY_FILE",
            "distributions",
        ],
        "_study",
    ),
    **dict.fromkeys(["TRIAL_FILE", "trial_dir", "trial_run_dir", "mean_scores"], "_records"),
    **dict.fromkeys(
        [
            "SAMPLERS",
            "PRUNERS",
            "Param",
            "Objective",
            "SamplerSpec",
            "PrunerSpec",
            "TuneSpec",
            "load_tune_spec",
            "resolve_space",
            "tune_target",
            "shipped_tune_specs",
            "check_space",
            "override_value",
            "trial_overrides",
            "grid_values",
        ],
        "_spec",
    ),
    **dict.fromkeys(["ALGORITHM_SPACES", "RANK_KEYS", "default_space"], "_defaults"),
}

__all__ = ["HELP", "DESCRIPTION", "add_arguments", "cli", *_LAZY]


def __getattr__(name: str):
    where = _LAZY.get(name)
    if where == "_study":
        from adarl.experiments.tune import _study as module
    elif where == "_records":
        from adarl.experiments.tune import _records as module
    elif where == "_spec":
        from adarl.experiments.tune import _spec as module
    elif where == "_defaults":
        from adarl.experiments.tune import _defaults as module
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(module, name)
    globals()[name] = value  # later reads skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
