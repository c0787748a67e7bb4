"""A pack folder: the seeds one :class:`~adarl.runtime.trainers.packed.SeedPack` process trains, named in
``pack.json``, so that ``adarl resume PACK`` continues them together after a stop or a kill.

Two layouts. ``adarl run RECIPE --pack-seeds 0 1 -o PACK`` keeps the seeds' run folders inside the pack folder
(``PACK/seed=0``...). ``adarl experiment --pack N`` keeps each run folder where the experiment plans it
(``OUT/<run id>``) and the pack folder in ``OUT/packs/<pack id>``; its ``pack.json`` names the runs as
``../../<run id>`` and how to start each one (recipe and overrides, as ``adarl run`` would), since a pack may be killed
before a seed's first checkpoint. Nothing else is accepted: a ``pack.json`` naming a folder elsewhere is refused.

A seed with a checkpoint resumes from it (its RNGs as the checkpoint saved them); a seed without one starts afresh
(its folder cleared, as ``adarl experiment`` clears a start that never checkpointed); a finished seed is left alone.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

from adarl.errors import AdaRLError, AdaRLValueError
from adarl.runtime.config import load_recipe
from adarl.runtime.continuing import already_complete
from adarl.runtime.run_folder._file_safety import atomic_write_text
from adarl.runtime.run_folder.run_dir import RunDir
from adarl.runtime.signals import RunInterrupted

if TYPE_CHECKING:  # torch and TorchRL: imported where a pack is built, so that reading a pack folder needs neither
    from adarl.runtime.trainers.packed import PackedSeedTrainer, SeedPack

__all__ = [
    "PACK_FILE",
    "create_pack",
    "finish",
    "is_pack_folder",
    "pack_runs",
    "relative_run",
    "resume_pack",
    "seed_folder",
    "write_pack_file",
]

#: the file naming a pack's seeds and run folders, in the pack folder (``adarl resume PACK`` reads it)
PACK_FILE = "pack.json"


def seed_folder(seed: int) -> str:
    """A seed's run folder inside its pack folder (``adarl run --pack-seeds``)."""
    return f"seed={int(seed)}"


def is_pack_folder(path) -> bool:
    return (Path(path) / PACK_FILE).is_file()


def write_pack_file(
    folder,
    runs: Sequence[str],
    seeds: Sequence[int],
    starts: Sequence[dict] | None = None,
    names: Sequence[str] | None = None,
) -> None:
    """``folder/pack.json``: the runs (paths relative to ``folder``), their seeds, and (experiment packs) how to start
    each one: ``{"recipe": name or file, "overrides": [...]}``, and what each run's ``packed_with`` calls it (``names``:
    a run at an fsspec URL trains in a scratch folder and is named by its URL; default its folder)."""
    data: dict = {"seeds": [int(s) for s in seeds], "runs": [str(r) for r in runs]}
    if starts is not None:
        data["starts"] = [{"recipe": str(s["recipe"]), "overrides": [str(o) for o in s["overrides"]]} for s in starts]
    if names is not None:
        data["names"] = [str(n) for n in names]
    Path(folder).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(folder) / PACK_FILE, json.dumps(data, indent=1) + "\n")


def _checked(entry, folder: Path) -> Path:
    """A run named in ``pack.json``: inside the pack folder, or ``../../<name>`` (an experiment's run folder)."""
    if not isinstance(entry, str) or not entry or "\\" in entry:
        raise ValueError(f"not a relative path: {entry!r}")
    parts = PurePosixPath(entry).parts
    plain = [p for p in parts if p not in ("..", ".")]
    inside = not PurePosixPath(entry).is_absolute() and len(plain) == len(parts)
    sibling = len(parts) == 3 and parts[:2] == ("..", "..") and plain == [parts[2]]
    if not (inside or sibling):
        raise ValueError(f"{entry!r} is neither inside the pack folder nor an experiment's run (../../<run id>)")
    return Path(os.path.normpath(folder.joinpath(*parts)))


def _read(folder: Path) -> tuple[list[Path], list[int], list[dict | None], list[str]]:
    path = folder / PACK_FILE
    try:
        data = json.loads(path.read_text())
        runs = [_checked(r, folder) for r in data["runs"]]
        seeds = [int(s) for s in data["seeds"]]
        starts = data.get("starts") or [None] * len(runs)
        names = data.get("names") or [str(r) for r in runs]
        if not all(isinstance(n, str) and n for n in names):
            raise ValueError(f"names must be non-empty strings, got {names!r}")
        for s in starts:
            if s is not None and not (isinstance(s.get("recipe"), str) and isinstance(s.get("overrides"), list)):
                raise ValueError(f"a start must name a recipe and a list of overrides, got {s!r}")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise AdaRLValueError(f"{str(path)!r} does not name a pack's runs: {err}") from None
    if not runs or len(set(runs)) != len(runs) or any(len(x) != len(runs) for x in (seeds, starts, names)):
        raise AdaRLValueError(
            f"{str(path)!r} must name distinct run folders, one seed (and start, name) each: {len(runs)} runs, "
            f"{len(seeds)} seeds, {len(starts)} starts, {len(names)} names"
        )
    return runs, seeds, starts, names


def pack_runs(folder) -> list[Path]:
    """The run folders of a pack folder, as its ``pack.json`` names them (checked)."""
    return _read(Path(folder))[0]


def create_pack(recipe, seeds: Sequence[int], folder, *, overwrite: bool = False, quiet: bool = False) -> SeedPack:
    """A new pack folder ``folder`` (``pack.json`` and one run folder per seed, ``seed=S``) and its pack."""
    from adarl.runtime.trainers.packed import SeedPack

    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds):
        raise AdaRLValueError(f"--pack-seeds takes distinct seeds, got {seeds}")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise AdaRLValueError(f"{str(folder)!r} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise AdaRLValueError(f"the pack folder {str(folder)!r} is not empty (--overwrite replaces it)")
    folder.mkdir(parents=True, exist_ok=True)
    run_dirs = []
    try:
        for s in seeds:
            run_dirs.append(RunDir.create(folder / seed_folder(s), overwrite=overwrite))
        for run_dir, s in zip(run_dirs, seeds, strict=True):
            run_dir.save_recipe(recipe.model_copy(update={"seed": s}))
        write_pack_file(folder, [seed_folder(s) for s in seeds], seeds)
        return SeedPack.build(recipe, seeds, run_dirs, quiet=quiet)
    except BaseException:
        for run_dir in run_dirs:
            run_dir.discard()
        (folder / PACK_FILE).unlink(missing_ok=True)
        raise


def finish(report: dict) -> dict[str, dict]:
    """The pack's outcome: every seed's summary, or the first signal's stop (every seed then saved a checkpoint),
    or an error naming each seed that failed (after the others finished)."""

    stops = [r for r in report.values() if isinstance(r, RunInterrupted)]
    failed = {p: r for p, r in report.items() if isinstance(r, BaseException) and not isinstance(r, RunInterrupted)}
    if stops:
        folder = Path(next(iter(report))).parent
        raise RunInterrupted(
            f"stopped on a signal: every seed saved a checkpoint; continue them with `adarl resume {folder}`"
            + (f" (failed before: {sorted(failed)})" if failed else ""),
            signum=stops[0].signum,
            checkpoint=stops[0].checkpoint,
        )
    if failed:
        lines = "; ".join(
            f"{p}: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}" for p, e in failed.items()
        )
        raise AdaRLError(f"{len(failed)} of {len(report)} packed seeds failed (the others finished): {lines}")
    return {p: r for p, r in report.items()}


def _fresh(run: Path, seed: int, start: dict | None) -> PackedSeedTrainer:
    """A seed that never checkpointed, started afresh in its folder (cleared) as ``adarl run`` starts it."""
    from adarl.runtime.trainers.packed import PackedSeedTrainer

    if start is not None:
        recipe = load_recipe(start["recipe"], start["overrides"])
    elif (run / "recipe.yaml").is_file():  # `adarl run --pack-seeds` wrote it before training
        recipe = RunDir(run).load_recipe()
    else:
        raise AdaRLValueError(f"{str(run)!r} has neither a checkpoint nor a recipe.yaml: nothing to start it from")
    if recipe.seed != seed:
        raise AdaRLValueError(f"{str(run)!r}: pack.json names seed {seed}, its recipe seed {recipe.seed}")
    run_dir = RunDir.create(run, overwrite=True)  # refused while another process trains in it
    try:
        run_dir.save_recipe(recipe)
        return PackedSeedTrainer(recipe, run_dir, quiet=True)
    except BaseException:
        run_dir.discard(keep_folder=True)
        raise


def resume_pack(folder, *, checkpoint=None, quiet: bool = False) -> tuple[SeedPack | None, list[str]]:
    """The pack of a pack folder's seeds that have not finished (each from its latest checkpoint, its RNGs as the
    checkpoint saved them; afresh without one), and a line for each seed already complete (None: every seed is)."""
    from adarl.runtime.trainers.packed import PackedSeedTrainer, SeedPack, SeedRNG

    runs, seeds, starts, names = _read(Path(folder))
    trainers, rngs, kept, said = [], [], [], []
    try:
        for run, seed, start, name in zip(runs, seeds, starts, names, strict=True):
            if checkpoint is None and RunDir(run).latest_checkpoint_frames() is None:
                trainers.append(_fresh(run, seed, start))
                rngs.append(SeedRNG())  # as its build left them, as in its own process
                kept.append(name)
                continue
            trainer = PackedSeedTrainer.resume(run, quiet=True, checkpoint=checkpoint)
            done = already_complete(
                run, trainer.frames, trainer.recipe.collector.total_frames, stopped=trainer.stopped_early
            )
            if done is not None:
                trainer.close()
                said.append(done)
                continue
            trainers.append(trainer)
            rngs.append(SeedRNG())
            kept.append(name)
        return (SeedPack(trainers, rngs, quiet=quiet, names=kept) if trainers else None), said
    except BaseException:
        for t in trainers:
            try:
                t.close()
            except Exception:  # noqa: BLE001 - releasing what was built is all that is asked
                pass
        raise


def relative_run(run_path: str | os.PathLike, pack_folder: str | os.PathLike) -> str:
    """How ``pack.json`` in ``pack_folder`` (``OUT/packs/<id>``) names the run folder ``OUT/<run id>``."""
    run, folder = Path(run_path), Path(pack_folder)
    if folder.parent.parent != run.parent:
        raise AdaRLValueError(f"{run} is not beside {folder.parent} (an experiment pack's run folders are)")
    return f"../../{run.name}"
