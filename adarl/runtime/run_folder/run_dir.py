"""The run folder: one directory per run with everything it produced.

::

    <run>/recipe.yaml            resolved recipe (what ran; `adarl resume` rebuilds from it)
    <run>/fingerprint.json       sha256 of the recipe's training keys and of its plugin modules (what made the run:
                                 adarl.runtime.fingerprint); plugins.json: where its algorithm, env, rule came from
    <run>/.adarl.lock            claimed when the folder is created; locked while a process trains in it
    <run>/metrics/scalars/       TorchRL CSVLogger scalars, one file per metric (header "step,value", step =
                                 frames), SB3's names: rollout/ep_rew_mean.csv, eval/mean_reward.csv,
                                 train/actor_loss.csv, rank/actor.layer0.csv (adarl.runtime.metrics)
    <run>/wandb_run_id           the wandb run this folder logs to (with logging.backends: [wandb]), for resume
    <run>/eval.csv               nominal-dynamics evaluations (frames, updates, mean, std, ci95, episodes, ranks)
    <run>/ranks.json, ranks.csv  rank history: per event and layer, old/new rank, spectrum, energy, error
    <run>/checkpoints/           ckpt-<frames>.pt (torch.save, loaded with weights_only=True) [+ rb-<frames>/buffer.pt]
    <run>/summary.json           final counters, ranks and evaluation
    ---------------------------  the training records above; what other commands write beside them:
    <run>/report.md, plots/      the report (training return with rank events, rank over time): `adarl report`
    <run>/eval_nominal.json      `adarl eval`;  <run>/sweeps/  `adarl eval --sweep`

Only training (``adarl run``, ``adarl resume``) writes the training records; evaluation and reports read them.
Checkpoints are written to a temporary file, fsync'ed and renamed, so a crash or a full disk mid-write leaves the
previous one intact; the last ``keep_last`` are kept. Each names the recipe fingerprint it was written under
(:func:`recipe_fingerprint`), checked before any of its tensors is used.

One class, :class:`RunDir`, is the whole layout above; it keeps the folder itself (creating, claiming, locking,
the recipe) and takes the rest from private modules behind it, as TorchRL's transforms hub does:
:mod:`adarl.runtime.run_folder._records` (loggers, ``eval.csv``, rank history, JSON files),
:mod:`adarl.runtime.run_folder._checkpoints` (checkpoints, replay buffer, ``best.pt``, the recipe fingerprint),
:mod:`adarl.runtime.run_folder._file_safety` (atomic renames, fsync, free-space checks, loads of tensors only),
:mod:`adarl.runtime.run_folder._lock` (the kernel lock) and :mod:`adarl.runtime.run_folder._loggers` (a scalar to
each logger).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import uuid
import warnings
from pathlib import Path

import yaml

from adarl import plugins
from adarl.envs.registry import env_provenance, supported_envs
from adarl.errors import (
    AdaRLError,
    AdaRLValueError,
    AdaRLWarning,
    RecipeError,
    command,
    describe_os_error,
)
from adarl.runtime import metrics
from adarl.runtime.config import load_recipe, local_plugins, save_resolved
from adarl.runtime.fingerprint import read_fingerprint, write_fingerprint
from adarl.runtime.run_folder._checkpoints import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    RunCheckpoints,
    recipe_fingerprint,
)
from adarl.runtime.run_folder._file_safety import (
    atomic_write_text,
    os_why,
)
from adarl.runtime.run_folder._lock import HELD_LOCKS, KERNEL_LOCKS, exclusive_lock, hold_lock, holder, release_lock
from adarl.runtime.run_folder._loggers import logging_backends, null_logger
from adarl.runtime.run_folder._records import RunRecords

__all__ = [
    "RunDir",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "TRAINING_RECORDS",
    "OTHER_OUTPUTS",
    "RunFolderGone",
    "exclusive_lock",
    "recipe_fingerprint",
    "null_logger",
    "logging_backends",
]

LOCK_FILE = ".adarl.lock"
# What only training writes (`adarl eval` and `adarl report` must leave these byte-for-byte unchanged); the other
# files of a run folder are report.md, plots/, eval_nominal.json and sweeps/.
TRAINING_RECORDS = (
    "recipe.yaml",
    "plugins.json",
    "fingerprint.json",
    LOCK_FILE,
    "metrics/",
    "eval.csv",
    "ranks.json",
    "ranks.csv",
    "checkpoints/",
    "summary.json",
    "tensorboard/",
    "wandb/",
    "replay_storage/",
)
# What the other commands write into a run folder; with TRAINING_RECORDS, every name adarl puts at its top level.
# `--overwrite` replaces only a folder that holds nothing else (a thesis.tex in it is refused by name).
# written by other adarl commands into a run folder (report, eval, export's default files): `--overwrite` replaces them
OTHER_OUTPUTS = (
    "wandb_run_id",
    "report.md",
    "plots/",
    "eval_nominal.json",
    "sweeps/",
    "policy.pt",
    "policy.pt2",
    "policy.onnx",
)


class RunFolderGone(AdaRLError):
    """The run folder was deleted or moved while a process trained in it: the run stops instead of writing on (it
    would recreate a folder without its recipe or records, which neither resume nor eval can read)."""


class RunDir(RunRecords, RunCheckpoints):
    """A run folder; see the module docstring for its layout."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._buffer_cache: tuple[Path, dict] | None = None  # (rb folder, its buffer.pt) read by load_checkpoint

    # ------------------------------------------------------------------ creation and locking
    @classmethod
    def create(cls, path: str | os.PathLike, *, overwrite: bool = False) -> RunDir:
        """Make a new run folder and claim it; refuse an existing non-empty one unless ``overwrite`` (then it is
        replaced, unless another process is training in it).

        Why a claim: checking that the folder is empty and then writing into it lets two processes started at the
        same instant (`adarl run -o SAME` twice) both pass the check. The claim is ``.adarl.lock`` created with
        ``O_EXCL``: exactly one process creates it, the other is refused. It stays locked until training ends.
        """
        p = Path(path)
        try:
            p.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise AdaRLError(f"run folder {str(p)!r} exists and is not a folder; choose another output.dir") from None
        except OSError as err:
            raise AdaRLError(
                f"cannot create run folder {str(p)!r}: {os_why(err, p)}; choose a writable place "
                f"with -o/--output or output.root"
            ) from None
        entries = list(p.iterdir())
        if entries and KERNEL_LOCKS and all(_claim_leftover(e.name) for e in entries):
            return cls._reclaim(p, entries)  # `adarl run` was stopped before it wrote its recipe: nothing ran
        if entries:
            foreign = _foreign_entries(entries)
            is_run = not foreign and any(e.name in (LOCK_FILE, "recipe.yaml") for e in entries)
            if not overwrite and is_run:
                raise AdaRLError(
                    f"run folder {str(p)!r} already exists and is not empty; choose another output.dir, "
                    f"resume it with `{command('adarl', 'resume', p)}`, or pass --overwrite to replace it"
                )
            if not is_run:
                what = (
                    f"holds {_names(foreign)}, which adarl did not write" if foreign else "is not an adarl run folder"
                )
                raise AdaRLError(
                    f"{'--overwrite refused: ' if overwrite else ''}run folder {str(p)!r} already exists and {what}"
                    f"{' (nothing was deleted)' if overwrite else ''}; choose another output folder with -o/--output "
                    f"or output.dir (--overwrite replaces only an adarl run folder that holds nothing else)"
                )
            cls(p).lock()  # refuses when another process trains in it
            release_lock(p / LOCK_FILE)
            aside = p.with_name(f".{p.name}.replaced-{uuid.uuid4().hex[:8]}")
            with contextlib.suppress(FileNotFoundError):  # another --overwrite moved it first
                os.rename(p, aside)
            shutil.rmtree(aside, ignore_errors=True)
            p.mkdir(parents=True, exist_ok=True)
        run = cls(p)
        try:
            fd = os.open(p / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise AdaRLError(
                f"run folder {str(p)!r} was just claimed by another process ({holder(p / LOCK_FILE)}); "
                f"choose another output.dir"
            ) from None
        except OSError as err:
            raise AdaRLError(
                f"cannot create run folder {str(p)!r}: {os_why(err, p)}; choose a writable place "
                f"with -o/--output or output.root"
            ) from None
        if not hold_lock(p / LOCK_FILE, fd):  # a stale claim's reclaimer (below) took it between our open and lock
            raise AdaRLError(
                f"run folder {str(p)!r} was just claimed by another process ({holder(p / LOCK_FILE)}); "
                f"choose another output.dir"
            )
        return run

    @classmethod
    def _reclaim(cls, p: Path, entries: list[Path]) -> RunDir:
        """Take over a folder that holds only the claim of an ``adarl run`` stopped before it wrote its recipe
        (``kill -9`` in its first moments): nothing ran there, so it is this run's folder now. Refused while the
        process that claimed it is alive (it holds the lock: two runs started at once)."""
        lock = p / LOCK_FILE
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise AdaRLError(
                f"cannot create run folder {str(p)!r}: {os_why(err, p)}; choose a writable place "
                f"with -o/--output or output.root"
            ) from None
        if not hold_lock(lock, fd):
            raise AdaRLError(
                f"run folder {str(p)!r} was just claimed by another process ({holder(lock)}); choose another output.dir"
            )
        for e in entries:  # a half-written recipe's temporary file
            if e.name != LOCK_FILE:
                e.unlink(missing_ok=True)
        return cls(p)

    @classmethod
    def open(cls, path: str | os.PathLike) -> RunDir:
        p = Path(path)
        if not (p / "recipe.yaml").is_file():
            if p.is_dir() and (p / LOCK_FILE).exists() and all(_claim_leftover(e.name) for e in p.iterdir()):
                raise AdaRLError(
                    f"{str(p)!r} holds no recipe.yaml: `adarl run` was stopped before it wrote one, so nothing ran "
                    f"there; start the run again with `adarl run RECIPE -o {command(p)}`"
                )
            if not p.exists():  # a mistyped path is bad input, not a broken folder (issue 48.6)
                raise AdaRLValueError(f"run folder {str(p)!r} does not exist")
            raise AdaRLError(f"{str(p)!r} is not an adarl run folder (no recipe.yaml in it)")
        return cls(p)

    def starts_over(self) -> bool:
        """Whether resuming this run means starting it from frame 0, with a warning saying so: it was stopped
        (``kill -9`` in its first moments) before its first checkpoint was complete, so nothing of its training is
        in the folder, only its recipe (and perhaps a checkpoint's partial ``*.tmp``). Starting again is then the
        same run, bit for bit, as one never stopped."""
        ckpts = self.checkpoint_dir
        if ckpts.is_dir() and any(not e.name.endswith(".tmp") for e in ckpts.iterdir()):
            return False  # checkpoints (or damaged ones, or buffers): resume from them, or say why not
        if any((self.path / name).exists() for name in ("eval.csv", "ranks.json", "summary.json")):
            return False
        scalars = self.path / "metrics" / "scalars"
        header = len(metrics.CSV_HEADER) + 1  # a file with only its header row holds no training
        if scalars.is_dir() and any(f.stat().st_size > header for f in scalars.rglob("*.csv") if f.is_file()):
            return False
        warnings.warn(
            f"run folder {str(self.path)!r} has no checkpoint: it was stopped before its first one was complete, "
            f"so none of its training was kept; starting it from frame 0",
            AdaRLWarning,
            stacklevel=3,
        )
        return True

    def ensure_present(self) -> None:
        """Raise :class:`RunFolderGone` when the folder this process trains in was deleted or moved (its lock file
        is gone or is another file): writing on would recreate a folder without its recipe or records.
        Does nothing where this process holds no lock on it (evaluation)."""
        lock = self.path / LOCK_FILE
        fd = HELD_LOCKS.get(str(lock.absolute()))
        if fd is None:
            return
        try:
            here, held = os.stat(lock), os.fstat(fd)
            if (here.st_ino, here.st_dev) == (held.st_ino, held.st_dev):
                return
        except OSError:
            pass
        raise RunFolderGone(
            f"run folder {str(self.path)!r} was deleted or moved while this process trained in it; the run "
            f"stopped and recreated nothing. If it was moved, `adarl resume NEW_PLACE` continues it from its last "
            f"checkpoint"
        )

    def lock(self) -> None:
        """Lock the folder for this process until :meth:`unlock` (a trainer's ``close()``) or the process ends: another
        process that would train in it (`adarl resume` while `adarl run` still runs, two resumes) is refused.
        Re-entrant in one process."""
        lock = self.path / LOCK_FILE
        key = str(lock.absolute())
        fd = HELD_LOCKS.get(key)
        if fd is not None:
            try:
                if os.fstat(fd).st_ino == os.stat(lock).st_ino:
                    return
            except OSError:
                pass
            release_lock(lock)
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise AdaRLError(f"cannot lock run folder {str(self.path)!r} to train in it: {os_why(err, lock)}") from None
        if not hold_lock(lock, fd):
            raise AdaRLError(
                f"run folder {str(self.path)!r} is in use by another process ({holder(lock)}); wait "
                f"for it to finish or stop it first"
            )

    def unlock(self) -> None:
        """Release this process's lock (training ended); another process may train in the folder again."""
        release_lock(self.path / LOCK_FILE)

    def discard(self, *, keep_folder: bool = False) -> None:
        """Undo :meth:`create` when nothing ran (a recipe that fails to build): the folder goes (or only its contents,
        ``keep_folder``, when it existed before) and the lock is released."""
        self.unlock()
        if not keep_folder:
            shutil.rmtree(self.path, ignore_errors=True)
            return
        for child in self.path.iterdir() if self.path.is_dir() else []:
            shutil.rmtree(child, ignore_errors=True) if child.is_dir() else child.unlink(missing_ok=True)

    @property
    def recipe_path(self) -> Path:
        return self.path / "recipe.yaml"

    @property
    def plugins_path(self) -> Path:
        """``plugins.json``: where the run's registered algorithm came from (package, version, loss)."""
        return self.path / "plugins.json"

    def save_recipe(self, recipe) -> None:
        """Write the resolved recipe.yaml and plugins.json (what :meth:`load_recipe` needs to rebuild the run, or
        to name the package it is missing), and fingerprint.json (what made the run:
        :mod:`adarl.runtime.fingerprint`)."""
        save_resolved(recipe, self.recipe_path)
        record = {
            "algorithm": plugins.algorithm(recipe.algorithm.name).provenance(),
            "env": {"name": recipe.env.id, **env_provenance(recipe.env.id)},
            "rank_rule": {"name": recipe.rank.rule, **plugins.RANK_RULES.provenance(recipe.rank.rule)},
            "callbacks": [{**plugins.callback(c.name).provenance(), "options": c.options} for c in recipe.callbacks],
            "modules": local_plugins.record(recipe.plugins),
        }
        try:
            atomic_write_text(self.plugins_path, json.dumps(record, indent=2) + "\n")
        except OSError as err:
            raise AdaRLError(f"cannot write {str(self.plugins_path)!r}: {describe_os_error(err)}") from None
        write_fingerprint(self.path, recipe)

    def load_recipe(self):
        """The run's recipe.yaml, validated. A run whose algorithm, env, rank rule or callback is no longer registered
        (its plugin package is not installed here) is refused, naming the package and version plugins.json recorded; a
        run whose local plugin module (the recipe's ``plugins``) is missing or changed, naming the module."""
        recorded = self.recorded_plugins()
        local_plugins.check_recorded(self.plugin_modules(recorded), str(self.path))
        try:
            return load_recipe(str(self.recipe_path))
        except RecipeError as err:
            callbacks = recorded.get("callbacks") if isinstance(recorded.get("callbacks"), list) else []
            for what, names, used in (
                ("algorithm", plugins.algorithm_names, recorded.get("algorithm")),
                ("env", supported_envs, recorded.get("env")),
                ("rank rule", plugins.rank_rule_names, recorded.get("rank_rule")),
                *(("callback", plugins.callback_names, c) for c in callbacks),
            ):
                used = used if isinstance(used, dict) else {}
                if used.get("package") in (None, "adarl") or used.get("name") in names():
                    continue
                version = f" {used['version']}" if used.get("version") else ""
                loss = f" (loss {used['loss']})" if used.get("loss") else ""
                raise RecipeError(
                    f"run folder {str(self.path)!r} was trained with {what} {used.get('name')!r}{loss} from the "
                    f"package {used['package']!r}{version}, which is not installed here: pip install "
                    f"{used['package']} to resume, evaluate or report it. ({err})"
                ) from None
            raise

    def plugin_modules(self, recorded: dict | None = None) -> list:
        """The local plugin modules the run recorded (plugins.json, else fingerprint.json). A recipe.yaml that names
        ``plugins`` with neither record is refused: its code could have changed unseen (issue 46.6)."""
        modules = (self.recorded_plugins() if recorded is None else recorded).get("modules")
        if isinstance(modules, list):
            return modules
        try:
            named = (yaml.safe_load(self.recipe_path.read_text()) or {}).get("plugins")
        except (OSError, yaml.YAMLError, AttributeError):
            named = None  # an unreadable recipe.yaml is load_recipe's to name
        fp = read_fingerprint(self.path)
        if fp is not None and isinstance(fp.get("plugins"), list):  # the content, and recipe.yaml's entries: where
            return local_plugins.located(named if isinstance(named, list) else [], fp["plugins"])
        if named:
            raise RecipeError(
                f"run folder {str(self.path)!r} was trained with the local plugin modules {named} but holds no record "
                f"of their content (plugins.json and fingerprint.json are missing or unreadable): adarl cannot check "
                f"that the code it would import is the code that trained the run; restore plugins.json (e.g. from a "
                f"copy of the folder) to resume, evaluate or report it"
            )
        return []

    def recorded_plugins(self) -> dict:
        """plugins.json as a dict ({} for runs made before it existed, or when it is unreadable)."""
        try:
            out = json.loads(self.plugins_path.read_text())
        except (OSError, ValueError):
            return {}
        return out if isinstance(out, dict) else {}


def _adarl_name(name: str) -> bool:
    """Whether a top-level entry of a run folder is one adarl writes (or a write's leftover ``*.tmp``)."""
    known = {n.rstrip("/") for n in (*TRAINING_RECORDS, *OTHER_OUTPUTS)}
    leftover = re.fullmatch(r"\.?(.+?)\.tmp\d*", name)  # `f.tmp` (atomic writes), `.recipe.yaml.tmp<pid>`
    return name in known or (leftover is not None and leftover.group(1) in known)


def _claim_leftover(name: str) -> bool:
    """What ``adarl run`` leaves when stopped before its recipe is written: the claim, a recipe's temporary file."""
    return name == LOCK_FILE or (_adarl_name(name) and name.startswith((".recipe.yaml.tmp", "recipe.yaml.tmp")))


def _foreign_entries(entries: list[Path]) -> list[Path]:
    return sorted((e for e in entries if not _adarl_name(e.name)), key=lambda e: e.name)


def _names(entries: list[Path], most: int = 5) -> str:
    """``thesis.tex, figures/ and 3 more``: what a folder holds, for a message."""
    shown = [e.name + ("/" if e.is_dir() else "") for e in entries[:most]]
    more = f" and {len(entries) - most} more" if len(entries) > most else ""
    return ", ".join(shown) + more
