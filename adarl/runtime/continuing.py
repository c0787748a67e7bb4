"""Continuing a run to more frames: ``adarl resume RUN collector.total_frames=M`` (SB3's
``learn(..., reset_num_timesteps=False)``, rl-zoo's ``-i``).

Only keys that change nothing of what a checkpoint holds, and nothing of the work done so far, may be changed on
resume (:data:`RESUMABLE_KEYS`); every other key is refused by name (a new run is the way to change it). The frame
budget may only be raised. The run folder's ``recipe.yaml`` then records the new total, so a later ``adarl resume``,
``adarl report`` or an experiment (which skips finished runs) sees the run as it now is.

What continuing does to the schedules that depend on the total (docs/resuming.md, "Continuing a finished run"):
the learning-rate cosine of ``lr_schedule.cosine`` (over the planned updates) and PPO's linear decay
(``algorithm.ppo.lr_decay``, over the planned iterations) are re-planned for the new total from the step the run
is at (:func:`retarget_schedules`); the perturbation schedules run per episode and do not depend on the total. A
run continued from N to M frames is therefore the very run started with M frames when neither of those two is on
(and N is a multiple of ``collector.frames_per_batch``, ``eval.interval`` and ``logging.log_interval``, so that
the first run's last batch, evaluation and metric rows fall where the longer run's do); with one of them on, the
learning rate followed the N-frame schedule until N and follows the M-frame one from there.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

from adarl.errors import RecipeError, command, did_you_mean, one_of
from adarl.runtime.config import load_recipe
from adarl.runtime.run_folder.run_dir import RunDir, recipe_fingerprint

__all__ = [
    "RESUMABLE_KEYS",
    "open_continued",
    "continued_recipe",
    "already_complete",
    "schedule_totals",
    "retarget_schedules",
]

#: the recipe keys ``adarl resume RUN key=value`` may change: the frame budget (raised only) and the callbacks (what
#: a run stopped early by one needs to train on: docs/callbacks.md), the whole list or a key under it
RESUMABLE_KEYS = ("collector.total_frames", "callbacks")

#: the attributes of a learning-rate lambda that hold its schedule's length over the run (``WarmupCosine``'s
#: ``total_steps``, PPO's ``LinearDecay.total``)
_TOTAL_ATTRIBUTES = ("total_steps", "total")


def _key(override: str) -> str:
    return override.split("=", 1)[0].strip().lstrip("+~")


def open_continued(path: str | os.PathLike, overrides: Sequence[str] = ()) -> tuple[RunDir, object, object]:
    """The run folder ``path``, its recorded recipe and the recipe it continues with (``overrides`` applied by
    :func:`continued_recipe`): what a resume or an evaluation refuses before it loads anything (no folder, not a run
    folder, a recipe that no longer validates, an override resume does not take), without torch, so the CLI can
    say it at once, before the trainer's imports."""
    run_dir = RunDir.open(path)
    recorded = run_dir.load_recipe()  # refuses, naming the package, a run whose algorithm is not installed
    return run_dir, recorded, continued_recipe(run_dir, recorded, overrides)


def continued_recipe(run_dir: RunDir, recipe, overrides: Sequence[str]):
    """The run's ``recipe`` with ``overrides`` applied, each key checked against :data:`RESUMABLE_KEYS` first
    (a :class:`~adarl.errors.RecipeError` names any other, and the allowed ones); the frame budget may only be
    raised. Returns ``recipe`` itself when ``overrides`` is empty."""
    if not overrides:
        return recipe
    refused = [o for o in overrides if _key(o).split(".")[0] != "callbacks" and _key(o) not in RESUMABLE_KEYS]
    if refused:
        key = _key(refused[0])
        raise RecipeError(
            f"adarl resume cannot change {key!r}{did_you_mean(key, RESUMABLE_KEYS)}: a resumed run keeps its recipe "
            f"(exact resume); allowed: {one_of(RESUMABLE_KEYS)}. To change it, start a new run: "
            f"`{command('adarl', 'run', run_dir.recipe_path, *refused)} -o NEW_DIR`"
        )
    new = load_recipe(str(run_dir.recipe_path), list(overrides))
    old_total, new_total = recipe.collector.total_frames, new.collector.total_frames
    if new_total < old_total:
        raise RecipeError(
            f"collector.total_frames: {new_total} is below the run's {old_total}; adarl resume may only raise the "
            f"frame budget (allowed: an integer >= {old_total})"
        )
    if recipe_fingerprint(new) != recipe_fingerprint(recipe):  # nothing else changed: a safeguard
        raise RecipeError(f"adarl resume may change only {one_of(RESUMABLE_KEYS)}; {list(overrides)} changes more")
    return new


def already_complete(path: str | os.PathLike, frames: int, total: int, *, stopped: dict | None = None) -> str | None:
    """The line ``adarl resume`` prints for a run whose latest loadable checkpoint is at ``frames`` >= its budget
    ``total`` (the one the overrides set, when given), or that a callback stopped early (``stopped``: the trainer's
    :attr:`~adarl.runtime.trainers.base.BaseTrainer.stopped_early`, a stop that still holds), and whose end was
    written (``summary.json`` at those frames), or None when there is something left to do: training, or the end of a
    run stopped after its last checkpoint (its final evaluation, summary and report, which resuming it writes)."""
    if stopped is not None:
        return _stopped_line(path, frames, total, stopped)
    if frames < total:
        return None
    try:
        if int(json.loads((Path(path) / "summary.json").read_text())["frames"]) < total:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (
        f"run {str(path)!r} is already complete: {frames} frames of collector.total_frames={total} "
        f"(its report: {Path(path) / 'report.md'}); to train it further, raise the budget: "
        f"`{command('adarl', 'resume', path)} collector.total_frames=N` with N > {frames}"
    )


def _stopped_line(path: str | os.PathLike, frames: int, total: int, stop: dict) -> str | None:
    try:
        summary = json.loads((Path(path) / "summary.json").read_text())
        if int(summary["frames"]) != frames or summary.get("stopped_early") != stop:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (
        f"run {str(path)!r} is complete: callback {stop.get('callback')!r} stopped it early at {stop.get('frames')} "
        f"frames of collector.total_frames={total} ({stop.get('reason')}; its report: {Path(path) / 'report.md'}); "
        f"to train it further, raise the budget (`{command('adarl', 'resume', path)} collector.total_frames=N`, N > "
        f"{total}) or drop or change the callbacks (`{command('adarl', 'resume', path)} callbacks=[]`)"
    )


def schedule_totals(schedulers) -> dict:
    """``{(scheduler name, lambda index, attribute): value}``: the length over the run of every learning-rate
    schedule in ``schedulers`` (a ``LambdaLR``'s callable objects), as the recipe's total makes it."""
    out = {}
    for name, sched in schedulers.items():
        for i, fn in enumerate(getattr(sched, "lr_lambdas", ())):
            for attr in _TOTAL_ATTRIBUTES:
                if isinstance(getattr(fn, attr, None), int):
                    out[(name, i, attr)] = getattr(fn, attr)
    return out


def retarget_schedules(schedulers, totals: dict) -> bool:
    """Give the schedules the lengths ``totals`` (:func:`schedule_totals` of schedulers built for the recipe) where
    a checkpoint loaded others (a run continued to a new total), and set each optimiser's learning rate to the
    re-planned schedule's value at the step the run is at. Returns whether anything changed."""
    changed = False
    for (name, i, attr), value in totals.items():
        sched = schedulers[name]
        fn = sched.lr_lambdas[i]
        if getattr(fn, attr) != value:
            setattr(fn, attr, value)
            changed = True
            sched.optimizer.param_groups[i]["lr"] = sched.base_lrs[i] * fn(int(sched.last_epoch))
    return changed
