"""What ``adarl tune`` writes once its study has run: ``trials.csv`` (one row per trial), ``best_recipe.yaml`` (the
best trial's recipe, resolved: ``adarl run`` accepts it), the figures (optimisation history, intermediate values,
parameter importances) and ``report.md``. Private module of :mod:`adarl.experiments.tune._study`.
"""

from __future__ import annotations

import csv
import math
import shlex
from pathlib import Path

import optuna
from optuna.trial import TrialState

from adarl.experiments.tune._spec import TuneSpec, override_value, trial_overrides
from adarl.runtime.config import load_recipe, recipe_to_yaml
from adarl.runtime.report import pyplot

__all__ = ["write_outputs", "importances"]

_COLOURS = {"COMPLETE": "tab:blue", "PRUNED": "tab:orange", "FAIL": "tab:red", "RUNNING": "tab:gray"}


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def _write_trials_csv(trials, spec: TuneSpec, path: Path) -> None:
    """One row per trial; with several seeds ``value`` is the mean over seeds and ``value_seed_S`` each seed's."""
    keys = list(spec.space)
    seeds = spec.trial_seeds if len(spec.trial_seeds) > 1 else []
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "number",
                "state",
                "value",
                *(f"value_seed_{s}" for s in seeds),
                *keys,
                "last_step",
                "evaluations",
                "seconds",
                "run_dir",
            ]
        )
        for t in trials:
            steps = t.intermediate_values
            seconds = t.duration.total_seconds() if t.duration is not None else ""
            per_seed = t.user_attrs.get("seed_values", {})
            w.writerow(
                [
                    t.number,
                    t.state.name,
                    "" if t.value is None else t.value,
                    *(per_seed.get(str(s), "") for s in seeds),
                    *(t.params.get(k, "") for k in keys),
                    max(steps) if steps else "",
                    len(steps),
                    seconds,
                    t.user_attrs.get("run_dir", ""),
                ]
            )


def _write_best_recipe(study, spec: TuneSpec, path: Path) -> optuna.trial.FrozenTrial | None:
    complete = [t for t in study.trials if t.state == TrialState.COMPLETE]
    if not complete:
        return None
    best = study.best_trial
    recipe = load_recipe(spec.recipe, trial_overrides(spec, best.params))
    head = (
        f"# adarl tune {spec.name}: the best of {len(complete)} complete trials: trial {best.number}, "
        f"{spec.objective.metric} {best.value:.6g} ({spec.direction})\n"
        f"# base recipe {spec.recipe} with: {' '.join(trial_overrides(spec, best.params))}\n"
        + (
            f"# the value is the mean over seeds {', '.join(map(str, spec.trial_seeds))} (this file: seed "
            f"{spec.trial_seeds[0]}; seed=N for another)\n"
            if len(spec.trial_seeds) > 1
            else ""
        )
        + f"# run it: {shlex.join(['adarl', 'run', str(path)])} (more frames: collector.total_frames=N)\n"
    )
    path.write_text(head + recipe_to_yaml(recipe))
    return best


def importances(study) -> tuple[dict[str, float] | None, str]:
    """Optuna's parameter importances (its default evaluator, PED-ANOVA), or None and why not."""
    complete = [t for t in study.trials if t.state == TrialState.COMPLETE]
    if len(complete) < 2:
        return None, f"needs at least 2 complete trials ({len(complete)} so far)"
    if len({t.value for t in complete}) < 2:
        return None, "every complete trial has the same value"
    varied = [k for k in complete[0].params if len({repr(t.params.get(k)) for t in complete}) > 1]
    if not varied:
        return None, "no parameter varies across the complete trials"
    try:
        return dict(optuna.importance.get_param_importances(study, params=varied)), ""
    except (RuntimeError, ValueError, ZeroDivisionError) as err:
        return None, f"Optuna could not compute them: {err}"


def _plot_history(study, spec: TuneSpec, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    best, xs, ys = None, [], []
    sign = 1 if spec.direction == "maximize" else -1
    for t in study.trials:
        value = t.value
        if value is None and t.state == TrialState.PRUNED and t.intermediate_values:
            value = t.intermediate_values[max(t.intermediate_values)]  # its last reported score
        if value is None:
            continue
        ax.scatter([t.number], [value], color=_COLOURS.get(t.state.name, "k"), zorder=3)
        if t.state == TrialState.COMPLETE:
            best = value if best is None or sign * value > sign * best else best
            xs.append(t.number)
            ys.append(best)
    if xs:
        ax.step(xs, ys, where="post", color="tab:green", label="best so far")
    for state, colour in _COLOURS.items():
        ax.scatter([], [], color=colour, label=state.lower())
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # trials are numbered: no 0.5 ticks (issue 48.6)
    ax.set_xlabel("trial")
    ax.set_ylabel(f"objective ({spec.objective.metric})")
    ax.set_title(f"{spec.name}: optimisation history")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_intermediate(study, spec: TuneSpec, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for t in study.trials:
        if not t.intermediate_values:
            continue
        steps = sorted(t.intermediate_values)
        style = "--" if t.state == TrialState.PRUNED else "-"
        colour = _COLOURS.get(t.state.name, "k")
        ax.plot(steps, [t.intermediate_values[s] for s in steps], style, marker=".", color=colour, alpha=0.7)
        ax.annotate(str(t.number), (steps[-1], t.intermediate_values[steps[-1]]), fontsize=7)
    ax.set_xlabel("frames")
    ax.set_ylabel(f"score (mean of the last {spec.objective.score_last} evaluations)")
    ax.set_title("intermediate values (what the pruner sees; dashed: pruned)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_importances(imp: dict[str, float], path: Path) -> None:
    plt = pyplot()
    names = sorted(imp, key=imp.get)
    fig, ax = plt.subplots(figsize=(6.4, 0.6 + 0.45 * len(names)))
    ax.barh(names, [imp[n] for n in names], color="tab:blue")
    ax.set_xlabel("importance (Optuna, PED-ANOVA; sums to 1)")
    ax.set_title("parameter importances")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(study, spec: TuneSpec, out: Path, log=print) -> Path:
    """Write ``trials.csv``, ``best_recipe.yaml``, the figures and ``report.md`` into ``out``; returns the report."""
    trials = study.trials
    _write_trials_csv(trials, spec, out / "trials.csv")
    best = _write_best_recipe(study, spec, out / "best_recipe.yaml")
    _plot_history(study, spec, out / "optimization_history.png")
    has_steps = any(t.intermediate_values for t in trials)
    if has_steps:
        _plot_intermediate(study, spec, out / "intermediate_values.png")
    imp, why = importances(study)
    if imp is not None:
        _plot_importances(imp, out / "param_importances.png")
    else:
        (out / "param_importances.png").unlink(missing_ok=True)
    counts: dict[str, int] = {}
    for t in trials:
        counts[t.state.name.lower()] = counts.get(t.state.name.lower(), 0) + 1
    o = spec.objective
    what = (
        f"the mean of the last {o.score_last} nominal evaluation(s)"
        if o.metric == "score"
        else f"the {o.worst} of the sweep {', '.join(o.sweep.params)}"
    )
    if len(spec.trial_seeds) > 1:
        seeds = f"seeds {', '.join(map(str, spec.trial_seeds))} (a run each)"
        what += " of each seed, the mean over seeds (what the pruner sees too: the mean over seeds at each frame count)"
    else:
        seeds = f"seed {spec.trial_seeds[0]}"
    lines = [
        f"# Hyperparameter search: {spec.name}",
        "",
        *([spec.description, ""] if spec.description else []),
        f"Base recipe `{spec.recipe}` with `{' '.join(spec.overrides)}`, {seeds}; objective: {what} "
        f"({spec.direction}); sampler {spec.sampler.name} (seed {spec.sampler.seed}), pruner {spec.pruner.name}.",
        f"Trials: {len(trials)} of {spec.n_trials} ({', '.join(f'{n} {k}' for k, n in sorted(counts.items()))}).",
        "",
    ]
    if best is not None:
        shown = " ".join(f"{k}={override_value(v)}" for k, v in best.params.items())
        lines += [
            f"**Best: trial {best.number}, value {best.value:.4g}**: `{shown}` "
            "(recipe: [best_recipe.yaml](best_recipe.yaml), run folder: "
            f"`{best.user_attrs.get('run_dir', '')}`).",
            "",
        ]
    else:
        lines += ["No trial has completed yet: no best recipe.", ""]
    lines += ["## Optimisation history", "", "![optimisation history](optimization_history.png)", ""]
    if has_steps:
        lines += ["![intermediate values](intermediate_values.png)", ""]
    lines += ["## Parameter importances", ""]
    if imp is not None:
        lines += ["| parameter | importance |", "|---|---|"]
        lines += [f"| `{k}` | {v:.3f} |" for k, v in sorted(imp.items(), key=lambda kv: -kv[1])]
        lines += ["", "![parameter importances](param_importances.png)", ""]
    else:
        lines += [f"Not computed: {why}.", ""]
    keys = list(spec.space)
    several = spec.trial_seeds if len(spec.trial_seeds) > 1 else []
    note = " A trial's value is the mean of its seeds' values." if several else ""
    lines += ["## Trials", "", f"A pruned trial's value is its last reported score.{note}", ""]
    head = ["trial", "state", "value", *(f"seed {s}" for s in several), *(f"`{k}`" for k in keys), "frames"]
    lines += ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for t in trials:
        steps = t.intermediate_values
        value = "" if t.value is None or math.isnan(t.value) else f"{t.value:.4g}"
        per_seed = t.user_attrs.get("seed_values", {})
        cells = [str(t.number), t.state.name.lower(), value, *(_fmt(per_seed.get(str(s))) for s in several)]
        cells += [_fmt(t.params.get(k)) for k in keys]
        lines.append("| " + " | ".join([*cells, str(max(steps)) if steps else ""]) + " |")
    folders = "a run folder" if not several else "a folder of run folders, one per seed (`seed=S`),"
    lines += [
        "",
        f"Every trial is {folders} under `trials/` (`adarl resume`, `adarl eval`, `adarl report` work on each run).",
    ]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    if best is not None:
        log(f"best: trial {best.number}, value {best.value:.4g}: {out / 'best_recipe.yaml'}")
    log(f"report: {path}")
    return path
