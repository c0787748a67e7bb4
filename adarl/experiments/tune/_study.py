"""Hyperparameter search: ``adarl tune SPEC`` (:func:`run_tune`), Optuna underneath.

The study lives in ``<output>/study.db`` (SQLite through Optuna's RDB storage); each trial is a normal run folder,
``<output>/trials/trial-NNNN`` (with several ``seeds``, one per seed: ``trial-NNNN/seed=S``, trained at the same
time), run by the experiment machinery (:func:`~adarl.experiments.execute.execute_run`: ``adarl run`` in a child
process, ``adarl resume`` when the folder has a checkpoint) on this machine or through a launcher (Ray, submitit:
:meth:`~adarl.experiments.launchers.Launcher.run_watched`). While a trial trains, its nominal evaluations
(``eval.csv``, the mean over seeds) are reported to Optuna (``trial.report(score, step=frames)``) and the pruner
asked; a pruned trial is stopped with SIGTERM (it checkpoints: the folder stays resumable; on a worker, asked
through a stop file beside its folder) and marked (``tune_trial.json``). Its value is the mean over seeds of each
seed's objective.

Killed at any moment (``kill -9``) and started again, the study continues: finished trials are kept, and a trial
still RUNNING in the database (no ``adarl tune`` holds the output folder: its lock says so) is re-attached (same
number, same parameters) and its run resumed from its checkpoint; a trial is told its result once, so it is never
counted twice. The budget counts every trial the study holds (complete, pruned, failed, interrupted-and-resumed).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shlex
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import optuna
import yaml
from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution
from optuna.trial import TrialState

from adarl.errors import AdaRLError, AdaRLValueError, RecipeError, is_storage_failure
from adarl.experiments.execute import clear_stop, run_is_finished
from adarl.experiments.launchers import Launcher, LocalLauncher, make_launcher
from adarl.experiments.spec import PlannedRun
from adarl.experiments.sweep import parse_sweep, sweep_run
from adarl.experiments.tune._outputs import write_outputs
from adarl.experiments.tune._records import (
    TRIAL_FILE,
    check_trial,
    mean_scores,
    read_records,
    rebuild,
    rebuild_plan,
    trial_dir,
    trial_run_dir,
    write_record,
)
from adarl.experiments.tune._records import scores as _scores
from adarl.experiments.tune._records import write_trial_file as _write_trial_file
from adarl.experiments.tune._spec import (
    Param,
    TuneSpec,
    check_space,
    grid_values,
    load_tune_spec,
    resolve_space,
    trial_overrides,
)
from adarl.runtime.config import load_recipe
from adarl.runtime.fingerprint import recipe_values, revalidated
from adarl.runtime.run_folder.run_dir import exclusive_lock
from adarl.runtime.run_folder.verdicts import Watcher, watching

__all__ = [
    "run_tune",
    "TuneResult",
    "STUDY_FILE",
    "distributions",
]

STUDY_FILE = "study.db"
_LOCK_FILE = ".tune.lock"
_FINISHED = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)


@dataclass
class TuneResult:
    """What :func:`run_tune` did: the output folder, the trials' states, the best trial (None: none complete)."""

    output: Path
    states: dict[str, int] = field(default_factory=dict)
    best_number: int | None = None
    best_value: float | None = None
    best_params: dict = field(default_factory=dict)
    resumed: list[int] = field(default_factory=list)


def distributions(spec: TuneSpec) -> dict:
    """The search space as Optuna distributions (one per recipe key)."""
    out = {}
    for key, p in spec.space.items():
        if p.type == "categorical":
            out[key] = CategoricalDistribution(list(p.choices))
        elif p.type == "int":
            out[key] = IntDistribution(int(p.low), int(p.high), log=p.log, step=int(p.step or 1))
        else:
            out[key] = FloatDistribution(p.low, p.high, log=p.log, step=p.step)
    return out


class _GridSampler(optuna.samplers.GridSampler):
    """Optuna's grid sampler, without its ``study.stop()`` once the grid is covered (that works only inside
    ``study.optimize``; ``adarl tune`` asks and tells itself and caps the budget at the grid's size)."""

    def after_trial(self, study, trial, state, values) -> None:
        return None


def _grid_size(space: dict[str, Param]) -> int:
    return math.prod(len(grid_values(p)) for p in space.values())


def _sampler(spec: TuneSpec, seed: int):
    s = spec.sampler
    if s.name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    if s.name == "grid":
        return _GridSampler({k: grid_values(p) for k, p in spec.space.items()}, seed=seed)
    kwargs = {} if s.n_startup_trials is None else {"n_startup_trials": s.n_startup_trials}
    return optuna.samplers.TPESampler(seed=seed, **kwargs)


def _pruner(spec: TuneSpec):
    p = spec.pruner
    if p.name == "none":
        return optuna.pruners.NopPruner()
    return optuna.pruners.MedianPruner(n_startup_trials=p.n_startup_trials, n_warmup_steps=p.n_warmup_steps)


class _Study:
    """The driver: asks (or re-attaches) trials, runs each as a run folder, reports, prunes and tells."""

    def __init__(self, spec: TuneSpec, out: Path, n_trials: int, workers: int, log, launcher=None) -> None:
        self.spec, self.out, self.n_trials, self.workers, self.log = spec, out, n_trials, workers, log
        # the runs of `workers` trials at a time, each trial's seeds at once (local: one torch thread each when > 1)
        self.launcher = launcher or LocalLauncher(workers * len(spec.trial_seeds))
        self.dists = distributions(spec)
        optuna.logging.set_verbosity(optuna.logging.WARNING)  # adarl prints one line per trial itself
        self.mutex = threading.RLock()  # ask, tell and the budget count happen one thread at a time
        self.stopping = threading.Event()
        self.base = self._base_values()
        self.made = self._settings()
        storage, n_before = self._open_storage()
        self.storage = storage
        self.rebuilt = 0
        if n_before == 0 and any(read_records(out)):  # study.db lost or emptied, the trial folders left
            trials = rebuild_plan(spec, out, self.dists, self.made)  # checked before anything is written
            if spec.name not in optuna.study.get_all_study_names(storage):
                optuna.create_study(study_name=spec.name, storage=storage, direction=spec.direction)
            empty = optuna.load_study(study_name=spec.name, storage=storage)
            for key, value in self._attrs().items():
                empty.set_user_attr(key, value)
            self.rebuilt = rebuild(empty, trials)
            n_before = len(trials)
            log(
                f"note: the study was not in {out / STUDY_FILE} (lost or emptied): rebuilt the study from the "
                f"records of {self.rebuilt} trial(s) in {out / 'trials'}"
            )
        if spec.name in optuna.study.get_all_study_names(storage):
            # a restarted study draws from seed + trials so far: a random sampler does not repeat its first points
            sampler = _sampler(spec, spec.sampler.seed + n_before)
            self.study = optuna.load_study(study_name=spec.name, storage=storage, sampler=sampler, pruner=_pruner(spec))
        else:
            self.study = optuna.create_study(
                study_name=spec.name,
                storage=storage,
                direction=spec.direction,
                sampler=_sampler(spec, spec.sampler.seed),
                pruner=_pruner(spec),
            )
        self._check_same_space()
        self.orphans: deque = deque()
        for t in self.study.get_trials(deepcopy=False):
            if t.state != TrialState.RUNNING:
                continue
            if set(t.params) != set(self.dists):  # killed inside ask(), before all its parameters were drawn
                self.study.set_user_attr(f"discarded_{t.number}", "interrupted before its parameters were drawn")
                self.study.tell(t.number, state=TrialState.FAIL)
            else:
                self.orphans.append(t)
        self.resumed: list[int] = []
        self.storage_failed: list[int] = []  # trials the disk failed (full, read-only): left to resume, exit 1

    def _open_storage(self):
        """The study's storage and how many trials it holds; a study.db that is no readable Optuna study (corrupt,
        another program's file) is refused by name, never a database traceback."""
        db = self.out / STUDY_FILE
        try:
            storage = optuna.storages.RDBStorage(
                f"sqlite:///{db.resolve()}", engine_kwargs={"connect_args": {"timeout": 60}}
            )
            if self.spec.name not in optuna.study.get_all_study_names(storage):
                return storage, 0
            return storage, len(storage.get_all_trials(storage.get_study_id_from_name(self.spec.name), deepcopy=False))
        except Exception as err:  # noqa: BLE001 - sqlalchemy's and sqlite's errors, whatever the damage
            why = str(err).splitlines()[0] if str(err) else type(err).__name__
            aside = shlex.join(["mv", str(db), f"{db}.bad"])
            raise AdaRLError(
                f"{db} is not a readable Optuna study ({why}); nothing was run. Move it aside ({aside}) "
                f"and run the same command again: the study is rebuilt from the records of its trials in "
                f"{self.out / 'trials'}/"
            ) from None

    def _base_values(self) -> dict:
        """The base recipe's fingerprinted keys (:func:`~adarl.runtime.fingerprint.recipe_values`), without the
        keys every trial sets itself (its point of the space, its seed): what pins the study's recipe by content."""
        base = load_recipe(self.spec.recipe, [*self.spec.overrides, f"seed={self.spec.trial_seeds[0]}"])
        return {
            k: v
            for k, v in recipe_values(base).items()
            if k != "seed" and not any(k == key or k.startswith(key + ".") for key in self.spec.space)
        }

    def _settings(self) -> dict:
        """What a study is made with and every later ``adarl tune`` on its folder must give again (and the base
        recipe's content, :meth:`_check_base`: its name or path may change)."""
        made = {
            "space": {k: p.model_dump() for k, p in self.spec.space.items()},
            "overrides": list(self.spec.overrides),
            "seeds": self.spec.trial_seeds,
            "objective": self.spec.objective.model_dump(),
            "direction": self.spec.direction,
        }
        return json.loads(json.dumps(made))

    def _attrs(self) -> dict:
        """The study's user attributes as a new study records them."""
        sha = hashlib.sha256(json.dumps(self.base, sort_keys=True).encode()).hexdigest()
        return {**self.made, "recipe": self.spec.recipe, "base_recipe": {"sha256": sha, "values": self.base}}

    def _check_base(self, recorded) -> None:
        """Refuse a base recipe whose content differs from the study's (its values validated again by today's
        schema, so a key added since at its default is no change), naming the keys."""
        values = recorded.get("values") if isinstance(recorded, dict) else None
        then = revalidated(values) if isinstance(values, dict) else None
        if then is not None:
            then = {k: v for k, v in then.items() if k in self.base or k in values}
        if then == self.base:
            return
        then = then or {}
        keys = sorted(k for k in set(then) | set(self.base) if then.get(k, "?") != self.base.get(k, "?"))
        shown = "; ".join(
            f"{k}: {json.dumps(then.get(k))} in the study, {json.dumps(self.base.get(k))} in the spec" for k in keys[:6]
        )
        raise RecipeError(
            f"the study in {self.out} was made with another base recipe (by content: {self.spec.recipe} now makes "
            f"other runs): {shown or 'it no longer validates'}; restore the recipe to continue it, or give another "
            "output folder (-o)"
        )

    def _check_old_trials_base(self) -> None:
        """A study made before its base recipe was pinned by content: each trial's run (finished or resumable) must
        be what its parameters make from the recipe now (:func:`~adarl.experiments.tune._records.check_trial`)."""
        for t in self.study.get_trials(deepcopy=False):
            if set(t.params) == set(self.dists):
                check_trial(self.spec, self.out, t.number, dict(t.params))

    def _check_same_space(self) -> None:
        made = self.made
        attrs = dict(self.study.user_attrs)
        if "space" not in attrs:
            for key, value in self._attrs().items():
                self.study.set_user_attr(key, value)
            return
        if "seeds" not in attrs and "seed" in attrs:  # a study made before `seeds` existed: one seed per trial
            attrs["seeds"] = [attrs["seed"]]
        changed = [key for key, value in made.items() if attrs.get(key) != value]
        if changed:
            named = [
                f"seeds ({attrs.get('seeds')} in the study, {made['seeds']} in the spec)" if key == "seeds" else key
                for key in changed
            ]
            raise RecipeError(
                f"the study in {self.out} was made with another {', '.join(named)}; continue it with the same "
                "spec, or give another output folder (-o)"
            )
        if "base_recipe" not in attrs:  # made before the recipe was pinned by content: its trials' runs say
            self._check_old_trials_base()
            self.study.set_user_attr("base_recipe", self._attrs()["base_recipe"])
            return
        self._check_base(attrs["base_recipe"])

    # ------------------------------------------------------------------ scheduling
    def _next(self):
        """The next trial to run: an interrupted one first (re-attached), else a new one while the budget lasts."""
        with self.mutex:
            if self.stopping.is_set():
                return None
            if self.orphans:
                frozen = self.orphans.popleft()
                self.resumed.append(frozen.number)
                return optuna.trial.Trial(self.study, frozen._trial_id)
            discarded = {k for k in self.study.user_attrs if k.startswith("discarded_")}
            held = [
                t
                for t in self.study.get_trials(deepcopy=False)
                if t.state != TrialState.WAITING and f"discarded_{t.number}" not in discarded
            ]
            if len(held) >= self.n_trials:
                return None
            return self.study.ask(self.dists)

    def run(self) -> None:
        if self.workers == 1:
            while (trial := self._next()) is not None:
                self._run_trial(trial)
            return

        def worker():
            while (trial := self._next()) is not None:
                self._run_trial(trial)

        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            futures = [pool.submit(worker) for _ in range(self.workers)]
            try:
                for f in futures:
                    f.result()
            except BaseException:
                self.stopping.set()  # every watched trial is stopped (checkpointed) and left to resume
                raise

    # ------------------------------------------------------------------ one trial
    def _planned(self, number: int, params: dict) -> list[PlannedRun]:
        """The trial's runs: one per seed (``trial-NNNN`` itself with one seed, ``trial-NNNN/seed=S`` with more)."""
        seeds = self.spec.trial_seeds
        runs = []
        for seed in seeds:
            path = trial_run_dir(self.out, number, seed, seeds)
            runs.append(
                PlannedRun(
                    run_id=path.name,
                    axes={"trial": str(number), "seed": str(seed)},
                    seed=seed,
                    recipe=self.spec.recipe,
                    overrides=trial_overrides(self.spec, params, seed),
                    path=str(path),
                    output=str(self.out),
                )
            )
        return runs

    def _run_trial(self, trial) -> None:
        number, params = trial.number, dict(trial.params)
        folder = trial_dir(self.out, number)
        runs = self._planned(number, params)
        paths = [Path(r.path) for r in runs]
        check_trial(self.spec, self.out, number, params)  # its folder holds this trial, or nothing yet
        with self.mutex:
            trial.set_user_attr("run_dir", folder.relative_to(self.out).as_posix())  # in the output folder
            system_attrs = dict(self.storage.get_trial(trial._trial_id).system_attrs)
        write_record(
            self.out,
            number,
            state="RUNNING",
            params=params,
            system_attrs=json.loads(json.dumps(system_attrs, default=str)),
            study=self.made,
            **({} if number in self.resumed else {"started": time.time()}),
        )
        shown = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in params.items())
        again = " (resumed)" if number in self.resumed else ""
        seeds = self.spec.trial_seeds
        self.log(
            f"[trial {number}]{again} {shown}" + (f" (seeds {', '.join(map(str, seeds))})" if len(seeds) > 1 else "")
        )
        state = {"pruned_at": None, "failed": False}
        guard = threading.Lock()  # each seed's run asks the watcher; one report at a time

        watchers = [Watcher(p) for p in paths]  # each run holds after an evaluation until its watcher read it

        def watch() -> bool:
            if self.stopping.is_set() or state["failed"]:
                return True  # interrupted, or a seed failed: the trial fails, its other runs need not go on
            with guard:
                if state["pruned_at"] is None:
                    read: list[int] = []
                    if self._report(trial, paths, read):
                        state["pruned_at"] = self._last_step(trial)
                    else:
                        for watcher, frames in zip(watchers, read, strict=True):
                            watcher.seen(frames)  # read, and not pruned on: that run trains on
                return state["pruned_at"] is not None

        def one(run: PlannedRun) -> PlannedRun:
            run = self.launcher.run_watched(run, watch)
            if run.status == "failed":
                state["failed"] = True
            return run

        marker = folder / TRIAL_FILE
        if marker.is_file() and json.loads(marker.read_text()).get("state") == "PRUNED":
            state["pruned_at"] = json.loads(marker.read_text()).get("pruned_at_frames")  # killed before the tell
        elif not all(run_is_finished(p) for p in paths) and self._report(trial, paths):
            state["pruned_at"] = self._last_step(trial)  # its evaluations so far already prune it
        if state["pruned_at"] is None:
            for p in paths:
                clear_stop(p)  # a stop asked of an earlier attempt (killed before it was told)
            with watching(watchers):
                if len(runs) == 1:
                    runs = [one(runs[0])]
                else:
                    with ThreadPoolExecutor(max_workers=len(runs)) as pool:
                        try:
                            runs = list(pool.map(one, runs))
                        except BaseException:
                            self.stopping.set()  # the other seeds' runs are stopped (checkpointed), left to resume
                            raise
            for run in runs:
                if run.status == "stopped" and run_is_finished(run.path):
                    run.status = "finished"  # it trained to the end before the stop reached it
            if all(r.status in ("finished", "skipped-finished") for r in runs):
                state["pruned_at"] = None  # complete, whatever the pruner said after its last evaluation
            elif state["pruned_at"] is None and not any(r.status == "failed" for r in runs):
                for r in runs:
                    if r.status == "interrupted":  # a signal from outside, not this study: said, not hidden
                        self.log(f"[trial {number}] {r.message.split(' (log:')[0]}")
                return  # interrupted (stopping, or a signal): left RUNNING, resumed by the next `adarl tune`
        self._finish(trial, runs, folder, params, state["pruned_at"])

    def _last_step(self, trial) -> int | None:
        with self.mutex:
            steps = self.storage.get_trial(trial._trial_id).intermediate_values
        return max(steps) if steps else None

    def _report(self, trial, paths: list[Path], read: list[int] | None = None) -> bool:
        """Report the evaluations not reported yet (the mean over the trial's seeds); whether the pruner stops it.
        ``read`` gets each run's last evaluation read (its frames; -1 for none): the verdict covers those."""
        per_seed = [_scores(p, self.spec.objective.score_last) for p in paths]
        if read is not None:
            read[:] = [s[-1][0] if s else -1 for s in per_seed]
        scores = mean_scores(per_seed)
        with self.mutex:
            known = self.storage.get_trial(trial._trial_id).intermediate_values
            new = [(f, s) for f, s in scores if f not in known]
            for frames, score in new:
                trial.report(score, step=frames)
            return bool(known or new) and bool(trial.should_prune())

    def _report_rest(self, trial, paths: list[Path]) -> None:
        """Report the evaluations the watcher had not seen when the runs ended (the last one, at the end of training,
        lands after the last poll), so that the trial's reported steps are the evaluations its value used (issue
        48.6: trials.csv said last_step 1750, evaluations 2 of a value that included the evaluation at 2000). The
        pruner is not asked: a trial that trained to its end is complete."""
        scores = mean_scores([_scores(p, self.spec.objective.score_last) for p in paths])
        with self.mutex:
            known = self.storage.get_trial(trial._trial_id).intermediate_values
            for frames, score in scores:
                if frames not in known:
                    trial.report(score, step=frames)

    def _finish(self, trial, runs: list[PlannedRun], folder: Path, params: dict, pruned_at) -> None:
        number = trial.number
        if pruned_at is not None:
            _write_trial_file(folder, number, params, "PRUNED", pruned_at_frames=pruned_at)
            write_record(self.out, number, state="PRUNED", pruned_at_frames=pruned_at, completed=time.time())
            with self.mutex:
                self.study.tell(number, state=TrialState.PRUNED)
            self.log(f"[trial {number}] pruned at {pruned_at} frames")
            return
        failed = [r for r in runs if r.status not in ("finished", "skipped-finished")]
        if not failed:
            values = {}
            for r in runs:
                try:
                    values[r.seed] = self._objective(Path(r.path))
                except (AdaRLError, ValueError, OSError) as err:
                    r.status, r.message = "failed", f"objective: {err}"
                    failed.append(r)
                    break
        if not failed:
            value = sum(values.values()) / len(values)  # the mean over seeds
            self._report_rest(trial, [Path(r.path) for r in runs])
            extra = {}
            if len(runs) > 1:
                extra["seed_values"] = {str(s): v for s, v in values.items()}
                with self.mutex:
                    trial.set_user_attr("seed_values", extra["seed_values"])
            _write_trial_file(folder, number, params, "COMPLETE", value, **extra)
            write_record(self.out, number, state="COMPLETE", value=value, completed=time.time(), **extra)
            with self.mutex:
                self.study.tell(number, value)
            per_seed = ", ".join(f"seed {s}: {v:.4g}" for s, v in values.items())
            self.log(f"[trial {number}] value {value:.4g}" + (f" (mean of {per_seed})" if len(runs) > 1 else ""))
            return
        message = "; ".join(
            (f"seed {r.seed}: " if len(runs) > 1 else "") + r.message for r in failed if r.status == "failed"
        ) or "; ".join(r.message for r in failed)
        if is_storage_failure(message):  # the disk failed, not the trial: never FAIL, resumed by the next `adarl tune`
            with self.mutex:
                self.storage_failed.append(number)
            self.stopping.set()  # no other trial starts on that disk; running ones checkpoint, left to resume
            self.log(f"[trial {number}] stopped, to resume: {message}")
            return
        _write_trial_file(folder, number, params, "FAIL", message=message)
        write_record(self.out, number, state="FAIL", message=message, completed=time.time())
        with self.mutex:
            trial.set_user_attr("message", message[:500])
            self.study.tell(number, state=TrialState.FAIL)
        self.log(f"[trial {number}] failed: {message}")

    def _objective(self, path: Path) -> float:
        o = self.spec.objective
        if o.metric == "score":
            scores = _scores(path, o.score_last)
            if not scores:
                raise AdaRLError(f"{path} has no nominal evaluation (eval.csv)")
            return scores[-1][1]
        s = o.sweep
        name = s.name or "__".join(p.split("=")[0] for p in s.params)
        result = path / "sweeps" / f"{name}.json"
        if not result.is_file():
            sweep_run(path, [parse_sweep(p) for p in s.params], episodes=s.episodes, name=name)
        return float(json.loads(result.read_text())[o.worst])


def run_tune(
    spec_path: str | os.PathLike | TuneSpec,
    *,
    output: str | os.PathLike | None = None,
    workers: int | None = None,
    log=print,
    launcher: str | Launcher = "local",
    launcher_options: dict | None = None,
) -> TuneResult:
    """Run (or continue) the study of the tune spec ``spec_path``; write ``best_recipe.yaml``, ``trials.csv`` and
    ``report.md`` in the output folder (default: the spec's ``output``, else ``runs/tune/<name>``). ``spec_path``:
    a spec file or shipped name, or a :class:`TuneSpec` (:func:`~adarl.experiments.tune.tune_target` makes one of a
    recipe); a spec without a space searches the default one (:func:`~adarl.experiments.tune.resolve_space`).

    ``workers`` trials at a time (default: the spec's), each trial's seeds at once. ``launcher``: where the runs
    train, as for ``adarl experiment``: ``local`` (default), ``ray``, ``submitit`` (``launcher_options`` go to
    :func:`~adarl.experiments.launchers.make_launcher`) or a :class:`~adarl.experiments.launchers.Launcher`; the
    output folder must then be one the workers see at the same path (this process reads the trials' ``eval.csv``).

    The spec and its search space are validated before anything is written (:class:`RecipeError`; a launcher whose
    extra is not installed: :class:`~adarl.errors.MissingExtraError`)."""
    spec = resolve_space(spec_path) if isinstance(spec_path, TuneSpec) else load_tune_spec(spec_path)
    check_space(spec)
    if workers is not None and workers < 1:
        raise AdaRLValueError(f"workers must be >= 1, got {workers}")
    workers = workers or spec.workers
    out = Path(output if output is not None else spec.output or f"runs/tune/{spec.name}")
    if not isinstance(launcher, Launcher):  # first: a launcher whose extra is missing leaves no folder behind
        launcher = make_launcher(
            launcher, workers=workers * len(spec.trial_seeds), output=out, **(launcher_options or {})
        )
    n_trials = spec.n_trials
    if spec.sampler.name == "grid" and _grid_size(spec.space) < n_trials:
        n_trials = _grid_size(spec.space)
        log(f"note: the grid has {n_trials} points; the study stops there (n_trials {spec.n_trials})")
    out.mkdir(parents=True, exist_ok=True)

    def refused(who: str) -> AdaRLError:
        return AdaRLError(
            f"another `adarl tune` is running on {out} ({who}); wait for it to end, or stop it and run this command "
            f"again"
        )

    with exclusive_lock(out / _LOCK_FILE, refused):
        driver = _Study(spec, out, n_trials, workers, log, launcher)  # refuses another study's folder first
        dumped = spec.model_dump(mode="json")
        dumped.pop("seed" if spec.seeds is not None else "seeds")  # the file is a spec `adarl tune` accepts
        head = f"# space: {spec._space_from}\n" if spec._space_from else ""
        (out / "tune_spec.yaml").write_text(head + yaml.safe_dump(dumped, sort_keys=False))
        finished = sum(t.state in _FINISHED for t in driver.study.trials)
        where = "" if launcher.name == "local" else f" (runs on {launcher.name})"
        if spec._space_from:
            log(f"space: {spec._space_from}: {', '.join(spec.space)} ({out / 'tune_spec.yaml'})")
        log(
            f"tune {spec.name}: {finished} of {n_trials} trials done, {len(driver.orphans)} interrupted to resume "
            f"-> {out}{where}"
        )
        with launcher.session():
            driver.run()
        study = driver.study
        write_outputs(study, spec, out, log=log)
        result = TuneResult(output=out, resumed=driver.resumed)
        for t in study.trials:
            result.states[t.state.name] = result.states.get(t.state.name, 0) + 1
        complete = [t for t in study.trials if t.state == TrialState.COMPLETE]
        if complete:
            best = study.best_trial
            result.best_number, result.best_value, result.best_params = best.number, best.value, dict(best.params)
        if driver.storage_failed:  # before: told FAIL for good, and `adarl tune` exited 0
            raise AdaRLError(
                f"tune {spec.name}: trial {', '.join(map(str, sorted(driver.storage_failed)))} stopped on a storage "
                f"failure (see its line above); free space (or make {str(out)!r} writable) and run the same command "
                "again: it resumes from its last checkpoint"
            )
        return result
