"""The record ``adarl tune`` keeps of each trial beside its run, and what it is for: rebuilding a study whose
``study.db`` was lost, emptied or replaced, and refusing a trial folder made with other settings. Private module of
:mod:`adarl.experiments.tune._study`.

``<output>/trials/trial-NNNN.json`` is written when the trial is asked, before its run starts (number, parameters,
the sampler's attributes, the study's settings), and again when it ends (state, value, per-seed values, where it was
pruned, why it failed); ``trial-NNNN/tune_trial.json`` inside the trial's folder says the same at its end (as before
the records existed). A study missing from ``study.db`` (the file deleted, emptied) while trial folders or records
are there is rebuilt from the records, in trial order, each trial's folder checked against the recipe its
parameters make now (:func:`adarl.runtime.fingerprint.differences`); a folder without a record, a record whose
study settings or run differ from the spec now, is refused by name. Intermediate values (what the pruner compares)
are read again from the trials' ``eval.csv``.
"""

from __future__ import annotations

import csv
import datetime
import json
import os
import re
from pathlib import Path

import optuna
from optuna.trial import TrialState

from adarl.errors import RecipeError
from adarl.experiments.execute import run_is_finished
from adarl.experiments.tune._spec import TuneSpec, override_value, trial_overrides
from adarl.runtime.config import load_recipe
from adarl.runtime.fingerprint import differences
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = [
    "TRIAL_FILE",
    "trial_dir",
    "trial_run_dir",
    "scores",
    "mean_scores",
    "write_trial_file",
    "write_record",
    "read_records",
    "check_trial",
    "rebuild",
]

TRIAL_FILE = "tune_trial.json"  # in each trial's run folder: its number, parameters, state and value
_TRIAL_NAME = re.compile(r"^trial-(\d{4,})$")


def trial_dir(output: str | os.PathLike, number: int) -> Path:
    """Trial ``number``'s folder: its run folder with one seed, the folder of its runs (``seed=S``) with more."""
    return Path(output) / "trials" / f"trial-{number:04d}"


def trial_run_dir(output: str | os.PathLike, number: int, seed: int, seeds: list[int]) -> Path:
    """The run folder of one seed of a trial: ``trial-NNNN`` with one seed (as studies made before ``seeds``
    existed), ``trial-NNNN/seed=S`` with more."""
    folder = trial_dir(output, number)
    return folder if len(seeds) == 1 else folder / f"seed={seed}"


def record_path(output: str | os.PathLike, number: int) -> Path:
    """``trials/trial-NNNN.json``: the record of trial ``number`` beside its folder."""
    return Path(output) / "trials" / f"trial-{number:04d}.json"


def scores(run: Path, last: int) -> list[tuple[int, float]]:
    """``(frames, score)`` after each complete line of the run's ``eval.csv``: the mean of the last ``last``
    evaluations' means so far (the experiment reports' score of a run that stopped there)."""
    path = run / "eval.csv"
    try:
        text = path.read_text()
    except (FileNotFoundError, OSError):
        return []
    lines = text.splitlines(keepends=True)
    complete = "".join(line for line in lines if line.endswith("\n"))
    means, out = [], []
    for row in csv.DictReader(complete.splitlines()):
        try:
            frames, mean = int(row["frames"]), float(row["mean"])
        except (KeyError, TypeError, ValueError):
            continue
        means.append(mean)
        out.append((frames, sum(means[-last:]) / len(means[-last:])))
    return out


def mean_scores(per_seed: list[list[tuple[int, float]]]) -> list[tuple[int, float]]:
    """What the pruner sees of a trial with several seeds: ``(frames, score)`` at each frame count F that some seed
    evaluated at and every seed reached (evaluated at F or later), the mean over seeds of each one's score at its
    last evaluation at or before F (a seed not evaluated by F yet leaves F out). With one seed: its own scores."""
    if len(per_seed) == 1:
        return list(per_seed[0])
    if not per_seed or not all(per_seed):
        return []
    reached = min(s[-1][0] for s in per_seed)
    out = []
    for frames in sorted({f for s in per_seed for f, _ in s if f <= reached}):
        at = [[v for f, v in s if f <= frames] for s in per_seed]
        if all(at):
            out.append((frames, sum(v[-1] for v in at) / len(at)))
    return out


def _write_json(path: Path, payload: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    os.replace(tmp, path)


def write_trial_file(path: Path, number: int, params: dict, state: str, value=None, **extra) -> None:
    """``tune_trial.json`` in the trial's folder (when it exists): its state at its end."""
    if path.is_dir():
        _write_json(path / TRIAL_FILE, {"trial": number, "state": state, "value": value, "params": params, **extra})


def write_record(output: str | os.PathLike, number: int, **fields) -> None:
    """Write (or update: the fields given replace theirs) the record of trial ``number`` beside its folder."""
    path = record_path(output, number)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        record = {}
    record = {**(record if isinstance(record, dict) else {}), "trial": number, **fields}
    _write_json(path, record)


def _read(path: Path) -> dict | None:
    try:
        out = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return out if isinstance(out, dict) and isinstance(out.get("params"), dict) else None


def read_records(output: str | os.PathLike) -> tuple[dict[int, dict], list[int]]:
    """The trials' records by number (beside the folder; else, for a study made before they existed, the folder's
    ``tune_trial.json``), and the numbers of trial folders that have neither."""
    root = Path(output) / "trials"
    records: dict[int, dict] = {}
    folders: set[int] = set()
    for entry in sorted(root.iterdir()) if root.is_dir() else []:
        name = entry.name.removesuffix(".json") if entry.suffix == ".json" else entry.name
        m = _TRIAL_NAME.match(name)
        if m is None:
            continue
        number = int(m.group(1))
        if entry.is_dir():
            folders.add(number)
            if number not in records and (inside := _read(entry / TRIAL_FILE)) is not None:
                records[number] = inside
        elif (beside := _read(entry)) is not None:
            records[number] = beside  # the record beside the folder is the fuller one
    return dict(sorted(records.items())), sorted(folders - set(records))


def _shown(params: dict) -> str:
    return ", ".join(f"{k}={override_value(v)}" for k, v in params.items())


def check_trial(spec: TuneSpec, output: Path, number: int, params: dict) -> None:
    """Refuse, by name, trial ``number`` of the study whose folder holds another trial: a record with other
    parameters, or a run (finished or resumable) made from another recipe than these parameters make now."""
    record = _read(record_path(output, number)) or _read(trial_dir(output, number) / TRIAL_FILE)
    folder = trial_dir(output, number).relative_to(output)
    if record is not None and record["params"] != params:
        raise RecipeError(
            f"trial {number} of the study in {output} has the parameters {_shown(params)}, but its folder {folder} "
            f"holds a trial of {_shown(record['params'])} (study.db and the trial folders are not of one study); "
            f"move {folder} aside, or give another output folder (-o)"
        )
    for seed in spec.trial_seeds:
        run = trial_run_dir(output, number, seed, spec.trial_seeds)
        if not (run_is_finished(run) or RunDir(run).latest_checkpoint_frames() is not None):
            continue
        diff = differences(run, load_recipe(spec.recipe, trial_overrides(spec, params, seed)), ours="the trial")
        if diff:
            raise RecipeError(
                f"trial {number} of the study in {output}: its run {run.relative_to(output)} was made from another "
                f"recipe than the trial's now: {'; '.join(diff[:6])}; move {folder} aside, or give another output "
                f"folder (-o)"
            )


def _time(value) -> datetime.datetime | None:
    try:
        return datetime.datetime.fromtimestamp(float(value))
    except (TypeError, ValueError, OverflowError, OSError):
        return None


def _intermediate(spec: TuneSpec, output: Path, number: int, until) -> dict[int, float]:
    paths = [trial_run_dir(output, number, s, spec.trial_seeds) for s in spec.trial_seeds]
    found = mean_scores([scores(p, spec.objective.score_last) for p in paths])
    return {f: v for f, v in found if until is None or f <= int(until)}


def rebuild_plan(spec: TuneSpec, output: Path, dists: dict, made: dict) -> list[optuna.trial.FrozenTrial]:
    """The trials of a lost study, from their records, in number order (a missing number: a trial discarded before
    its parameters were drawn); :class:`RecipeError` naming what does not fit the spec now. Nothing is written."""
    records, bare = read_records(output)
    if bare:
        names = ", ".join(trial_dir(output, n).name for n in bare[:5])
        raise RecipeError(
            f"the study in {output} is not in its study.db (lost or emptied) and the trial folder(s) {names} have no "
            f"record to rebuild it from (trials/trial-NNNN.json or tune_trial.json); move them aside, or give "
            f"another output folder (-o)"
        )
    states = {s.name: s for s in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL, TrialState.RUNNING)}
    trials = []
    for number in range(max(records, default=-1) + 1):
        record = records.get(number)
        if record is None:
            trials.append(None)  # discarded: asked, killed before its record
            continue
        where = f"trial {number} ({record_path(output, number).name})"
        settings = record.get("study")
        if isinstance(settings, dict):
            changed = [k for k in made if k in settings and settings[k] != made[k]]
            if changed:
                raise RecipeError(
                    f"the study in {output} is lost from study.db, and {where} was made with another "
                    f"{', '.join(changed)} than the spec now; continue it with the same spec, or give another output "
                    f"folder (-o)"
                )
        params = record["params"]
        if set(params) != set(dists):
            raise RecipeError(
                f"the study in {output} is lost from study.db, and {where} has the parameters {sorted(params)}, not "
                f"the spec's space {sorted(dists)}; continue it with the same spec, or give another output folder (-o)"
            )
        check_trial(spec, output, number, params)
        state = states.get(str(record.get("state")), TrialState.RUNNING)
        value = record.get("value") if state == TrialState.COMPLETE else None
        if state == TrialState.COMPLETE and not isinstance(value, (int, float)):
            state = TrialState.RUNNING  # killed between its run's end and its tell: re-attached and told again
        user_attrs = {"run_dir": trial_dir(output, number).relative_to(output).as_posix()}
        if isinstance(record.get("seed_values"), dict):
            user_attrs["seed_values"] = record["seed_values"]
        if record.get("message"):
            user_attrs["message"] = str(record["message"])[:500]
        try:
            trial = optuna.trial.create_trial(
                state=state,
                value=float(value) if value is not None else None,
                params=params,
                distributions=dists,
                user_attrs=user_attrs,
                system_attrs=record.get("system_attrs") if isinstance(record.get("system_attrs"), dict) else None,
                intermediate_values=_intermediate(spec, output, number, record.get("pruned_at_frames")),
            )
        except ValueError as err:
            raise RecipeError(
                f"the study in {output} is lost from study.db, and {where} does not fit the spec's space now: {err}; "
                f"continue it with the same spec, or give another output folder (-o)"
            ) from None
        started, ended = _time(record.get("started")), _time(record.get("completed"))
        if started is not None:
            trial.datetime_start = started
        if ended is not None and trial.datetime_complete is not None and (started is None or ended >= started):
            trial.datetime_complete = ended
        trials.append(trial)
    return trials


def rebuild(study: optuna.Study, trials: list) -> int:
    """Add :func:`rebuild_plan`'s trials to the (new, empty) study in order; returns how many have records."""
    for trial in trials:
        if trial is None:
            number = len(study.get_trials(deepcopy=False))
            study.add_trial(optuna.trial.create_trial(state=TrialState.FAIL))
            study.set_user_attr(f"discarded_{number}", "asked, but stopped before its record was written")
        else:
            study.add_trial(trial)
    return sum(t is not None for t in trials)
