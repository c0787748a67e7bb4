"""``adarl experiment --pack N``: the runs of one arm that differ only in the seed, trained N at a time in one process
(:class:`~adarl.runtime.trainers.packed.SeedPack`, each seed's SAC update one batched program).

:func:`plan_packs` groups the runs to start: runs whose validated recipes are equal but for ``seed`` form an arm; an
arm whose recipe cannot be packed (:func:`~adarl.runtime.trainers.packed.pack_refusal`: TorchRL's update path, a
loss term such as Parseval's, another training loop) runs solo, said by name before anything runs. Each pack is a
:class:`PlannedPack` the launcher runs as one unit; :func:`execute_pack` starts ``adarl resume OUT/packs/<pack id>``
(its ``pack.json`` names the runs, :mod:`~adarl.runtime.trainers.pack_folder`) and sets each run's status as
:func:`~adarl.experiments.execute.execute_run` sets a solo run's. Every run keeps its own folder ``OUT/<run id>``, file
for file a solo run's; ``experiment.json`` records the pack a run trained in (``pack``) and its summary.json the runs it
was packed with (``packed_with``).

Every launcher runs packs (a pack is one Ray task, one submitit job). At an fsspec URL a pack trains as a solo run
there does: its runs in local scratch folders, each uploaded after each of its checkpoints
(:func:`~adarl.experiments.execute.prepare_url_run`, :func:`~adarl.experiments.execute.settle_url_run`).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from adarl.errors import AdaRLValueError
from adarl.experiments.execute import (
    OutputFolderGone,
    _cli,
    _live,
    _make_below,
    _record_attempt,
    _set_unfinished,
    _wait,
    execute_run,
    prepare_url_run,
    run_is_finished,
    settle_url_run,
    settled_before_start,
    start_training,
    wait_uploading,
)
from adarl.experiments.spec import PlannedRun
from adarl.runtime.run_folder.results import is_url, join
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = [
    "PACKS_DIR",
    "PlannedPack",
    "check_packable_launch",
    "execute_pack",
    "execute_unit",
    "members",
    "plan_packs",
    "settle",
]

PACKS_DIR = "packs"  # OUT/packs/<pack id>/pack.json, OUT/packs/<pack id>.log


@dataclass
class PlannedPack:
    """Runs of one arm trained in one process: what a launcher runs as one unit (its ``run_id`` is the pack's id,
    its ``path`` the pack folder, whose stop file stops every seed), ``members`` the runs, each set as it ends."""

    run_id: str
    members: list[PlannedRun]
    path: str
    output: str | None = None
    status: str = "pending"
    message: str = ""
    wall_time_s: float = 0.0
    member_ids: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.member_ids = [r.run_id for r in self.members]


def pack_id(runs: list[PlannedRun]) -> str:
    """A pack's id, from its runs' ids: the same runs make the same pack folder when the experiment resumes."""
    digest = hashlib.sha1("\n".join(sorted(r.run_id for r in runs)).encode()).hexdigest()[:10]
    return f"pack-{digest}"


def check_packable_launch(pack: int) -> None:
    """Refuse, by name, a ``--pack`` that is not a number of seeds per process (before anything is written)."""
    if pack < 1:
        raise AdaRLValueError(f"--pack takes a number of seeds per process >= 1, got {pack}")


def plan_packs(
    runs: list[PlannedRun], recipes: dict, pack: int, output, log: Callable[[str], None] = print
) -> list[PlannedRun | PlannedPack]:
    """``runs`` as the units a launcher runs: packs of up to ``pack`` runs of one arm (in seed order), and solo runs
    (an arm of one run to start, or one whose recipe cannot be packed: logged with why)."""
    if pack <= 1:
        return list(runs)
    from adarl.runtime.trainers.packed import pack_refusal, recipe_without_seed  # torch: only when packing

    arms: dict[str, list[PlannedRun]] = {}
    for r in runs:
        key = json.dumps(recipe_without_seed(recipes[r.run_id]), sort_keys=True, default=str)
        arms.setdefault(key, []).append(r)
    units: list[PlannedRun | PlannedPack] = []
    for arm in arms.values():
        arm.sort(key=lambda r: r.seed)
        first = arm[0]
        if len(arm) == 1:
            units.append(first)
            continue
        reason = pack_refusal(recipes[first.run_id])
        if reason is not None:
            log(f"[solo] {_arm(first)}: {len(arm)} runs, each in its own process (cannot pack: {reason})")
            units.extend(arm)
            continue
        for i in range(0, len(arm), pack):
            members = arm[i : i + pack]
            if len(members) == 1:
                units.append(members[0])
                continue
            pid = pack_id(members)
            path = join(str(output), PACKS_DIR, pid) if is_url(output) else str(Path(output) / PACKS_DIR / pid)
            units.append(PlannedPack(pid, members, path, output=first.output))
            log(f"[pack] {pid}: {_arm(first)}, seeds {', '.join(str(r.seed) for r in members)}")
    return units


def _arm(run: PlannedRun) -> str:
    """An arm as a reader names it: its axes' values (the recipe when the spec has no axes)."""
    return ", ".join(f"{k}={v}" for k, v in run.axes.items()) or f"recipe {run.recipe}"


def settle(pack: PlannedPack) -> None:
    """The pack's own status, from its runs' (what a launcher's loop reads)."""
    states = [r.status for r in pack.members]
    for worst in ("failed", "interrupted", "stopped", "changed", "pending"):
        if worst in states:
            pack.status = worst
            pack.message = "; ".join(f"{r.run_id}: {r.message}" for r in pack.members if r.status == worst)
            return
    pack.status, pack.message = "finished", "every run finished"


def execute_pack(pack: PlannedPack, threads: int | None, watch: Callable[[], bool] | None = None) -> PlannedPack:
    """Train the pack's runs that need it in one ``adarl resume OUT/packs/<pack id>`` process; set each run's status
    as :func:`~adarl.experiments.execute.execute_run` would (finished, failed, interrupted, stopped, changed,
    skipped-finished), and the pack's from them."""
    from adarl.runtime.trainers.pack_folder import relative_run, write_pack_file

    todo = [run for run in pack.members if not settled_before_start(run)]
    if todo and watch is not None and watch():
        for run in todo:
            run.status, run.message = "pending", "asked to stop before it started"
        todo = []
    if not todo:
        settle(pack)
        return pack
    if is_url(todo[0].path):
        return _execute_pack_at_url(pack, todo, threads, watch)
    folder = Path(pack.path)
    _make_below(todo[0], folder)
    write_pack_file(
        folder,
        [relative_run(r.path, folder) for r in todo],
        [r.seed for r in todo],
        [{"recipe": r.recipe, "overrides": r.overrides} for r in todo],
    )
    log = folder.parent / f"{pack.run_id}.log"
    actions = {r.run_id: "resumed" if RunDir(r.path).latest_checkpoint_frames() is not None else "ran" for r in todo}
    for r in todo:
        _record_attempt(r, event="start", action=actions[r.run_id], pack=pack.run_id)
    start = time.perf_counter()
    with log.open("w") as fh:
        proc = start_training(_cli("resume", str(folder), "--quiet"), fh, threads)
        with _live(proc) as sent:
            try:
                stopped, interrupted = _wait(proc, watch), None
            except KeyboardInterrupt as err:
                stopped, interrupted = False, err
    wall = time.perf_counter() - start
    if not Path(pack.output or folder.parent.parent).is_dir():  # deleted or moved under the runs (which stopped)
        raise OutputFolderGone(pack.output or folder.parent.parent)
    tail = log.read_text().strip().splitlines()[-1:] if log.is_file() else []
    for r in todo:
        r.wall_time_s, r.pack = wall, pack.run_id
        if run_is_finished(r.path):  # its budget spent (the pack's exit status may be another seed's failure)
            r.status, r.message = "finished", f"{actions[r.run_id]} in {pack.run_id}"
        elif stopped:
            r.status, r.message = "stopped", f"stopped by its watcher (exit {proc.returncode}) (log: {log})"
        else:
            _set_unfinished(r, proc.returncode, tail, log, sent=sent[0])
        _record_attempt(r, event="end", action=actions[r.run_id], status=r.status, pack=pack.run_id)
    pack.wall_time_s = wall
    settle(pack)
    if pack.status == "finished":
        log.unlink(missing_ok=True)
    if interrupted is not None:
        raise interrupted
    return pack


def _execute_pack_at_url(
    pack: PlannedPack, todo: list[PlannedRun], threads: int | None, watch: Callable[[], bool] | None
) -> PlannedPack:
    """:func:`execute_pack` for runs at a URL, as a solo run at a URL trains (``execute_run``): each run in its local
    scratch folder (downloaded first when it lacks the URL's latest checkpoint), the pack folder beside them
    (``<scratch>/<experiment hash>/packs/<pack id>``), each run uploaded after each of its checkpoints and at its
    end."""
    from adarl.runtime.trainers.pack_folder import relative_run, write_pack_file

    prepared = {}
    for r in todo:
        got = prepare_url_run(r)  # None: the URL could not be read (the run failed; the others go on)
        if got is not None:
            prepared[r.run_id] = got
    train = [r for r in todo if r.run_id in prepared and prepared[r.run_id][2] != "uploaded"]
    trained = {r.run_id for r in train}
    for r in todo:
        if r.run_id in prepared:
            local, _, action = prepared[r.run_id]
            in_pack = pack.run_id if r.run_id in trained else None
            _record_attempt(r, event="start", action=action, scratch=str(local), pack=in_pack)
    returncode, sent, stopped, interrupted, wall = 0, None, False, None, 0.0
    log = None
    if train:
        local_root = prepared[train[0].run_id][0].parent  # every run of an experiment URL shares it
        folder = local_root / "packs" / pack.run_id
        write_pack_file(
            folder,
            [relative_run(prepared[r.run_id][0], folder) for r in train],
            [r.seed for r in train],
            [{"recipe": r.recipe, "overrides": r.overrides} for r in train],
            names=[r.path for r in train],  # packed_with names each run by its URL, not its scratch folder
        )
        log = local_root / f"{pack.run_id}.log"
        start = time.perf_counter()
        with log.open("w") as fh:
            proc = start_training(_cli("resume", str(folder), "--quiet"), fh, threads)
            uploads = [(prepared[r.run_id][1], r.path) for r in train]
            with _live(proc) as sent_box:  # every seed checkpoints on a stop; uploaded below
                returncode, stopped, interrupted = wait_uploading(proc, watch, uploads, fh)
            sent = sent_box[0]
        wall = time.perf_counter() - start
    for r in todo:
        if r.run_id not in prepared:
            continue
        local, mirror, action = prepared[r.run_id]
        r.wall_time_s = wall
        if r.run_id in trained:
            r.pack = pack.run_id
        # finished when its budget is spent (the pack's exit status may be another seed's failure)
        run_log = log if log is not None else local.with_name(f"{r.run_id}.log")
        done = f"{action} in {pack.run_id}" if r.run_id in trained else action
        settle_url_run(r, local, mirror, run_is_finished(local), returncode, run_log, done, stopped=stopped, sent=sent)
        _record_attempt(r, event="end", action=action, status=r.status, pack=r.pack if r.run_id in trained else None)
    pack.wall_time_s = wall
    settle(pack)
    if pack.status == "finished" and log is not None:
        log.unlink(missing_ok=True)
        shutil.rmtree(log.with_name("packs") / pack.run_id, ignore_errors=True)
    if interrupted is not None:
        raise interrupted
    return pack


def execute_unit(unit, threads: int | None, watch: Callable[[], bool] | None = None):
    """What a launcher runs: a :class:`PlannedPack` (:func:`execute_pack`) or one run (``execute_run``)."""
    if isinstance(unit, PlannedPack):
        return execute_pack(unit, threads, watch)
    return execute_run(unit, threads, watch=watch)


def members(unit) -> list[PlannedRun]:
    """The runs of a unit a launcher ran: a pack's runs, or the run itself."""
    return list(unit.members) if isinstance(unit, PlannedPack) else [unit]
