"""Running an experiment: :func:`run_experiment` plans the spec's runs, skips finished ones, flags runs whose recipe
does not exist (yet), hands the rest to a launcher (one after another, ``workers`` at a time, Ray or SLURM), shows
their progress, sweeps each finished run if the spec asks, and writes the aggregate report
(:mod:`adarl.experiments.report`). ``experiment.json`` in the output folder records what ran (the last budget's runs,
and under ``earlier`` those of the other budgets or specs run into the same folder, which a report reads too).

A finished (or resumable) run folder is reused only while it is what the spec plans now: its recipe, re-validated with
today's schema, equal to the planned one in every training key, and its plugin modules the same
(:func:`adarl.runtime.fingerprint.differences`). Otherwise the experiment is refused by name before anything is
written, listing the keys that changed; with ``rerun_changed`` those runs train again into new folders beside the old
ones (``<run id>.rerun1``, ``.rerun2``...), which are kept, and ``experiment.json`` points to the new ones. A later
call reuses whichever folder of a run matches the spec (the original first).

The output may be an fsspec URL (``s3://bucket/exp``): runs then train in a local scratch folder and are copied to
``<URL>/<run id>`` after each checkpoint (:mod:`adarl.runtime.run_folder.results`); the finished-run check,
``experiment.json``,
the attempt records, the progress board and the report read and write the URL.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import re
import shlex
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

from adarl.errors import AdaRLError, AdaRLValueError, RecipeError
from adarl.experiments.execute import OutputFolderGone, holds_training, run_is_finished
from adarl.experiments.launchers import ExperimentInterrupted, Launcher, make_launcher
from adarl.experiments.packing import PlannedPack, check_packable_launch, members, plan_packs
from adarl.experiments.progress import LiveBoard, ProgressBoard
from adarl.experiments.report import write_aggregate_report
from adarl.experiments.spec import (
    ExperimentSpec,
    PlannedRun,
    SweepSpec,
    default_output,
    load_experiment,
    plan_runs,
    resolve_budget,
)
from adarl.experiments.sweep import parse_sweep, sweep_run
from adarl.runtime.config import load_recipe
from adarl.runtime.fingerprint import differences
from adarl.runtime.run_folder.results import (
    RunMirror,
    exists,
    filesystem,
    is_url,
    join,
    makedirs,
    read_text,
    upload_tree,
    write_atomic,
)
from adarl.runtime.run_folder.run_dir import RunDir, exclusive_lock
from adarl.runtime.signals import silence_stdout, stdout_reader_gone, stop_as_on_a_signal

__all__ = ["run_experiment", "EXPERIMENT_FILE"]

EXPERIMENT_FILE = "experiment.json"
#: held by the ``adarl experiment`` running on a local output folder: a second one on the same folder is refused (it
#: would start the same pending runs, and clear the folder of a run the first had just started)
EXPERIMENT_LOCK = ".adarl-experiment.lock"


def _busy(out: Path):
    def refused(who: str) -> AdaRLError:
        return AdaRLError(
            f"another `adarl experiment` is running on {out} ({who}); wait for it to end, or stop it (kill -INT "
            f"<pid>: its runs checkpoint) and run this command again. `--dry-run` shows the runs' state meanwhile"
        )

    return refused


def _check_recipes(runs: list[PlannedRun]) -> dict[str, Any]:
    """Validate every run's recipe before anything runs: a missing recipe flags its runs, a bad one stops all.
    Returns each validated recipe by run id."""
    problems, recipes = [], {}
    for run in runs:
        try:
            recipes[run.run_id] = load_recipe(run.recipe, run.overrides)
            run.total_frames = recipes[run.run_id].collector.total_frames
        except RecipeError as err:
            if str(err).startswith(f"no recipe named {run.recipe!r}") or "not found" in str(err).split("\n")[0]:
                run.status, run.message = "missing-recipe", str(err).split(";")[0]
            else:
                problems.append(f"{run.run_id}: {err}")
    if problems:
        raise RecipeError("experiment runs do not validate (nothing was run):\n" + "\n".join(problems[:10]))
    return recipes


RERUN_SUFFIX = ".rerun"  # <run id>.rerun<N>: a run trained again after its spec changed (--rerun-changed)


def _folders(run: PlannedRun) -> list[str]:
    """The run's folders: the planned one, then its reruns (``<run id>.rerun1``...) in order, those that exist."""
    pattern = re.compile(re.escape(run.run_id + RERUN_SUFFIX) + r"(\d+)$")
    if is_url(run.path):
        fs, root = filesystem(run.path.rsplit("/", 1)[0])
        try:
            names = [n.rstrip("/").rsplit("/", 1)[-1] for n in fs.ls(root, detail=False)]
        except FileNotFoundError:
            names = []
        parent = run.path.rsplit("/", 1)[0]
        found = [(int(m.group(1)), f"{parent}/{n}") for n in names if (m := pattern.match(n))]
    else:
        parent = Path(run.path).parent
        found = [
            (int(m.group(1)), str(f))
            for f in parent.glob(glob.escape(run.run_id + RERUN_SUFFIX) + "*")
            if (m := pattern.match(f.name))
        ]
    return [run.path] + [f for _, f in sorted(found)]


def _rerun_number(folder: str, run: PlannedRun) -> int:
    """N of a folder ``<run id>.rerun<N>`` (0: the planned folder)."""
    tail = folder.rstrip("/").rsplit("/", 1)[-1][len(run.run_id + RERUN_SUFFIX) :]
    return int(tail) if tail.isdigit() else 0


def _place(runs: list[PlannedRun], recipes: dict, rerun_changed: bool) -> list[tuple[PlannedRun, str, list[str]]]:
    """Point each run at its folder that holds the training the spec plans now (the planned one, else a rerun),
    or at one to train in. A run whose folders hold only other training is returned with the folder and what
    differs (its status ``changed``); with ``rerun_changed`` it gets a new folder beside them instead."""
    changed = []
    for run in runs:
        if run.status == "missing-recipe":
            continue
        folders = _folders(run)
        held = [f for f in folders if holds_training(f)]
        first: tuple[str, list[str]] | None = None
        for folder in held:
            diff = differences(folder, recipes[run.run_id])
            if not diff:
                run.path = folder
                break
            first = first or (folder, diff)
        else:
            if first is None:
                continue  # nothing trained yet (or a start that never checkpointed): the planned folder
            free = [f for f in folders if f not in held]
            if rerun_changed:
                run.path = free[0] if free else f"{run.path}{RERUN_SUFFIX}{_rerun_number(folders[-1], run) + 1}"
            else:
                run.status, run.message = "changed", f"made from another recipe ({first[0]}): " + "; ".join(first[1])
                changed.append((run, *first))
    return changed


def _refuse_changed(spec: ExperimentSpec, out, changed: list[tuple[PlannedRun, str, list[str]]]) -> AdaRLError:
    lines = [
        f"  {run.run_id} ({folder}): " + "; ".join(diff[:6]) + (f"; and {len(diff) - 6} more" if len(diff) > 6 else "")
        for run, folder, diff in changed[:20]
    ]
    more = [f"  and {len(changed) - 20} more runs"] if len(changed) > 20 else []
    return AdaRLError(
        f"experiment {spec.name}: {len(changed)} run(s) in {out} were made from another recipe than the spec plans "
        f"now (nothing was run, no folder changed):\n"
        + "\n".join(lines + more)
        + "\nRestore the spec to reuse them, give another output folder (-o), or pass --rerun-changed to train them "
        f"again into new folders beside the old ones (<run id>{RERUN_SUFFIX}1; the old folders are kept)"
    )


def _sweep(run: PlannedRun, sweeps: list[SweepSpec]) -> None:
    """Run the spec's sweeps missing from a finished run; a URL run is swept in a local copy, then uploaded."""
    names: dict[str, SweepSpec] = {}
    for s in sweeps:
        names.setdefault(s.name or "__".join(p.split("=")[0] for p in s.params), s)
    if not is_url(run.path):
        for name, s in names.items():
            if not (Path(run.path) / "sweeps" / f"{name}.csv").is_file():
                sweep_run(run.path, [parse_sweep(p) for p in s.params], episodes=s.episodes, name=name)
        return
    todo = {n: s for n, s in names.items() if not exists(join(run.path, "sweeps", f"{n}.csv"))}
    if not todo:
        return
    with tempfile.TemporaryDirectory(prefix="adarl-sweep-") as tmp:
        mirror = RunMirror(Path(tmp) / run.run_id, run.path)
        latest = mirror.remote_latest()
        if latest is None:
            raise AdaRLError(f"cannot sweep {run.path}: it has no checkpoint (checkpoints/LATEST is missing)")
        mirror.download(latest)
        for name, s in todo.items():
            sweep_run(mirror.local, [parse_sweep(p) for p in s.params], episodes=s.episodes, name=name)
        upload_tree(mirror.local / "sweeps", join(run.path, "sweeps"))


RECORD_KEYS = ("name", "description", "budget", "command", "axes", "report", "runs")


def _earlier_records(previous: str | None, spec: ExperimentSpec, budget: str | None) -> list[dict]:
    """The records of the other budgets (or specs) that ran into this folder before, oldest first: kept in
    ``experiment.json`` under ``earlier`` so that a report over the folder still finds their runs (the record of
    this spec's budget is replaced)."""
    try:
        state = json.loads(previous) if previous is not None else {}
    except json.JSONDecodeError:
        return []
    if not isinstance(state, dict):
        return []
    records = [*(state.get("earlier") or []), {k: state.get(k) for k in RECORD_KEYS}] if state.get("runs") else []
    return [e for e in records if isinstance(e, dict) and (e.get("name"), e.get("budget")) != (spec.name, budget)]


def _keep_unreadable(out: Path | str, previous: str | None, log) -> None:
    """An ``experiment.json`` that does not read as adarl's record (a hand edit, another program's file) is kept
    beside the new one as ``experiment.json.unreadable-<UTC time>`` and named, never silently overwritten."""
    if previous is None:
        return
    try:
        if isinstance(json.loads(previous), dict):
            return
    except json.JSONDecodeError:
        pass
    name = f"{EXPERIMENT_FILE}.unreadable-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
    if is_url(out):
        write_atomic(join(out, name), previous)
    else:
        (out / name).write_text(previous)
    log(f"note: {EXPERIMENT_FILE} in {out} did not read as an experiment record; kept as {name}, a new one written")


def _write_state(
    out: Path | str,
    spec: ExperimentSpec,
    budget: str | None,
    runs: list[PlannedRun],
    command: str = "",
    earlier: list[dict] | None = None,
) -> None:
    payload = {
        "name": spec.name,
        "description": spec.description,
        "budget": budget,
        "command": command,
        "axes": list(spec.axes),
        "report": spec.report.model_dump(),
        "runs": [r.as_dict() for r in runs],
    }
    if earlier:
        payload["earlier"] = earlier
    if is_url(out):
        write_atomic(join(out, EXPERIMENT_FILE), json.dumps(payload, indent=2) + "\n")
        return
    if not out.is_dir():  # deleted or moved while the experiment ran: never recreated half-filled
        raise OutputFolderGone(out)
    tmp = out / (EXPERIMENT_FILE + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    os.replace(tmp, out / EXPERIMENT_FILE)


def _read_previous(out: Path | str) -> str | None:
    if is_url(out):
        return read_text(join(out, EXPERIMENT_FILE))
    previous = out / EXPERIMENT_FILE
    return previous.read_text() if previous.is_file() else None


def run_experiment(
    spec_path: str | os.PathLike,
    *,
    budget: str | None = None,
    output: str | os.PathLike | None = None,
    workers: int | None = None,
    dry_run: bool = False,
    report: bool = True,
    log=print,
    launcher: str | Any = "local",
    launcher_options: dict | None = None,
    progress_interval: float = 0,
    scratch: str | os.PathLike | None = None,
    live: bool = False,
    console=None,
    rerun_changed: bool = False,
    pack: int | None = None,
) -> list[PlannedRun]:
    """Run (or continue) the experiment in ``spec_path``; returns the runs with their status.

    ``output``: a folder, or an fsspec URL (``s3://bucket/exp``, ``file:///shared/exp``; see
    :mod:`adarl.runtime.run_folder.results`), where each run then trains in ``scratch`` (default:
    ``$TMPDIR/adarl-scratch`` of the
    machine it runs on) and is uploaded after each checkpoint. ``launcher``: ``local`` (default), ``ray``, ``submitit``
    (see :mod:`adarl.experiments.launchers`; ``launcher_options`` go to
    :func:`~adarl.experiments.launchers.make_launcher`) or a :class:`~adarl.experiments.launchers.Launcher`.
    ``progress_interval`` > 0 logs one line per run and an aggregate bar that
    often (seconds); with ``live`` a table redrawn in place instead (rich, on ``console``: default stdout).

    A finished or resumable run folder made from another recipe than the spec plans now is refused by name
    (:class:`~adarl.errors.AdaRLError` listing the keys that changed, before anything is written; a dry run shows
    it as ``changed``); ``rerun_changed`` trains such runs again into new folders beside the old ones.

    ``pack`` (default: the spec's ``pack``, 1): runs of one arm that differ only in the seed train that many at a time
    in one process (:mod:`adarl.experiments.packing`; the local launcher, a local output folder)."""
    spec = load_experiment(spec_path)
    budget, _ = resolve_budget(spec, budget)
    out = output if output is not None else default_output(spec, budget)
    out = str(out).rstrip("/") if is_url(out) else Path(out)
    if is_url(out):
        filesystem(out)  # an unknown protocol or a missing backend package fails here, before anything runs
    runs = plan_runs(spec, out, budget)
    if scratch is not None:
        if is_url(out):
            for r in runs:
                r.scratch = str(scratch)
        else:
            log(f"note: --scratch is ignored: results at a local path ({out}) are written in place")
    pack = spec.pack if pack is None else pack
    check_packable_launch(pack)
    recipes = _check_recipes(runs)
    changed = _place(runs, recipes, rerun_changed)
    if changed and not dry_run:
        raise _refuse_changed(spec, out, changed)
    todo = []
    for r in runs:
        if r.status == "missing-recipe":
            log(f"[skip] {r.run_id}: {r.message}")
        elif r.status == "changed":
            continue
        elif run_is_finished(r.path):
            r.status, r.message = "skipped-finished", "already finished"
        else:
            todo.append(r)
    previous = _read_previous(out)
    earlier = _earlier_records(previous, spec, budget)
    if previous is not None:  # keep the timings of runs finished in earlier sessions
        try:
            before = {r["run_id"]: r for r in json.loads(previous).get("runs", [])}
        except (json.JSONDecodeError, AttributeError, TypeError):
            before = {}
        for r in runs:
            if r.status == "skipped-finished" and r.run_id in before:
                r.wall_time_s = float(before[r.run_id].get("wall_time_s") or 0.0)
    n_done = sum(r.status == "skipped-finished" for r in runs)
    log(
        f"experiment {spec.name} (budget {budget or 'default'}): {len(runs)} runs, {n_done} already finished, "
        f"{len(todo)} to run, {sum(r.status == 'missing-recipe' for r in runs)} with a missing recipe"
        + (f", {len(changed)} made from another recipe (refused)" if changed else "")
        + f" -> {out}"
    )
    units = plan_packs(todo, recipes, pack, out, log)  # says which arms pack, and why one cannot
    if dry_run:
        for r in runs:
            frames = RunDir(r.path).latest_checkpoint_frames() if r in todo and not is_url(r.path) else None
            state = r.status if frames is None else "resumable"
            resumes = "" if frames is None else f"  (resumes from its checkpoint at {frames} frames)"
            if r.status == "changed":
                log(f"  {state:<16} {r.run_id}: {r.message}")
                continue
            where = "" if Path(str(r.path)).name == r.run_id else f"  (in {Path(str(r.path)).name})"
            log(f"  {state:<16} {r.run_id}: {r.recipe} {' '.join(r.overrides)}{resumes}{where}")
        return runs
    if not isinstance(launcher, Launcher):  # first: a launcher whose extra is missing leaves no folder behind
        launcher = make_launcher(
            launcher, workers=workers or spec.workers, output=out, resources=spec.resources, **(launcher_options or {})
        )
    if is_url(out) and out.startswith("memory://") and launcher.name != "local":
        raise AdaRLValueError(
            f"output {out!r}: memory:// lives in one process, which the {launcher.name} launcher's "
            "workers cannot see; use a shared URL (s3://, gs://, file:///shared/...)"
        )
    if is_url(out):
        makedirs(out)
    else:
        out.mkdir(parents=True, exist_ok=True)
    with contextlib.nullcontext() if is_url(out) else exclusive_lock(out / EXPERIMENT_LOCK, _busy(out)):
        # quoted as a shell reads it: a folder named `a b;rm -rf x` stays one argument of the command it suggests
        budget_args = ["--budget", str(budget)] if budget else []
        command = shlex.join(["adarl", "experiment", str(spec_path), *budget_args, "-o", str(out)])
        _keep_unreadable(out, previous, log)
        _write_state(out, spec, budget, runs, command, earlier)
        board, last_tick = ProgressBoard(runs), [time.monotonic()]
        screen = LiveBoard(board, console=console) if live and progress_interval > 0 else None
        shown = screen.log if screen is not None else log

        def say(line: str) -> None:
            """A progress line. Once stdout's reader has gone (``| head`` exited, a killed ``tee``), nothing more is
            shown and the launcher stops the experiment as on a Ctrl-C (a checkpoint of each run), exit 141."""
            try:
                shown(line)
            except BrokenPipeError:
                if not stdout_reader_gone():
                    raise
                silence_stdout()
                if not stop_as_on_a_signal(signal.SIGPIPE, "its output was closed"):
                    raise  # no launcher's stop to ask (never in a launch): exit 141 now, never go on unseen

        def done(unit) -> None:  # a run, or a pack of runs (each said)
            for r in members(unit):
                if r.status == "pending":  # asked to stop before it started
                    continue
                said = "" if r.status == "finished" else ": " + r.message
                say(f"[{r.status}] {r.run_id} ({r.wall_time_s:.0f} s){said}")
            _write_state(out, spec, budget, runs, command, earlier)
            if screen is not None:
                screen.update()

        packs = {u.run_id: u.member_ids for u in units if isinstance(u, PlannedPack)}

        def tick(running: set) -> None:
            board.running = {m for i in running for m in packs.get(i, [i])}
            if progress_interval > 0 and time.monotonic() - last_tick[0] >= progress_interval:
                last_tick[0] = time.monotonic()
                if screen is not None:
                    screen.update()
                else:
                    for line in board.render():
                        say(line)

        if todo:
            try:
                if screen is not None:
                    with screen:
                        launcher.launch(units, done, tick=tick)
                else:
                    launcher.launch(units, done, tick=tick)
            except ExperimentInterrupted:  # SIGINT/SIGTERM: the state as it stands, no report; the same command resumes
                _write_state(out, spec, budget, runs, command, earlier)
                raise
        _, b = resolve_budget(spec, budget)
        sweeps = spec.sweeps if b.sweeps is None else b.sweeps
        if sweeps:
            for r in runs:
                if r.status in ("finished", "skipped-finished"):
                    _sweep(r, sweeps)
        _write_state(out, spec, budget, runs, command, earlier)
        failed = [r for r in runs if r.status == "failed"]
        interrupted = [r for r in runs if r.status == "interrupted"]
        if report:
            path = write_aggregate_report([out], f"{out}/report" if is_url(out) else out / "report")
            log(f"report: {path}")
        if failed or interrupted:
            said = []
            if failed:
                said.append(
                    f"{len(failed)} of {len(runs)} runs failed: "
                    + "; ".join(f"{r.run_id}: {r.message}" for r in failed[:5])
                )
            if interrupted:
                said.append(
                    f"{len(interrupted)} of {len(runs)} runs were interrupted by a signal and resume from their last "
                    f"checkpoint when this command is run again: " + ", ".join(r.run_id for r in interrupted[:5])
                )
            raise AdaRLError(". ".join(said))
        return runs
