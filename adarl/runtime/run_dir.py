"""The run folder: one directory per run with everything it produced.

::

    <run>/recipe.yaml            resolved recipe (what ran; `adarl resume` rebuilds from it)
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

Long because: one class, :class:`RunDir`, knows the whole layout above (a method per file it writes or
reads); how a file is written and read safely (atomic renames, fsync, free-space checks, loads of tensors only) is
:mod:`adarl.runtime._file_safety`'s, the folder's kernel lock :mod:`adarl.runtime._folder_lock`'s, and how a scalar
reaches each logger :mod:`adarl.runtime._run_loggers`'s.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import shutil
import uuid
import warnings
from pathlib import Path

from torchrl.record import loggers as torchrl_loggers

from adarl import __version__, plugins
from adarl.envs.registry import ENV_IDS, supported_envs
from adarl.errors import (
    AdaRLError,
    AdaRLWarning,
    CheckpointError,
    CheckpointFallbackWarning,
    RecipeError,
    describe_os_error,
)
from adarl.runtime import metrics
from adarl.runtime._file_safety import (
    NotAFile,
    atomic_torch_save,
    atomic_write_text,
    buffer_nbytes,
    check_free_space,
    fsync_dir,
    naming,
    nbytes,
    os_why,
    plain,
    safe_load,
    why_unloadable,
)
from adarl.runtime._folder_lock import HELD_LOCKS, KERNEL_LOCKS, exclusive_lock, hold_lock, holder, release_lock
from adarl.runtime._run_loggers import Fanout, logging_backends, null_logger, tensorboard_logger
from adarl.runtime.config import load_recipe, local_plugins, recipe_to_yaml, save_resolved

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

CHECKPOINT_FORMAT = "adarl.checkpoint"
CHECKPOINT_VERSION = 1
LOCK_FILE = ".adarl.lock"
REPLAY_BUFFER_FILE = "buffer.pt"  # inside rb-<frames>/; older checkpoints hold TorchRL's dumps() layout there
# What only training writes (`adarl eval` and `adarl report` must leave these byte-for-byte unchanged); the other
# files of a run folder are report.md, plots/, eval_nominal.json and sweeps/.
TRAINING_RECORDS = (
    "recipe.yaml",
    "plugins.json",
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
OTHER_OUTPUTS = ("wandb_run_id", "report.md", "plots/", "eval_nominal.json", "sweeps/")
_EVAL_FIELDS = ["frames", "updates", "mean", "std", "ci95", "episodes", "returns", "ranks"]


def recipe_fingerprint(recipe) -> dict:
    """What fixes the shapes of a run's checkpoints: env, algorithm, network layout, critics, buffer size.

    A checkpoint written under another value cannot be loaded into this run's networks and buffer; it is refused
    by name before any tensor is used (keys absent on either side, from other adarl versions, are not compared)."""
    fp = {
        "algorithm.name": recipe.algorithm.name,
        "algorithm.options": dict(recipe.algorithm.options),
        "env.id": recipe.env.id,
        "env.num_envs": recipe.env.num_envs,
        "algorithm.num_qvalue_nets": recipe.algorithm.num_qvalue_nets,
        "algorithm.fixed_alpha": recipe.algorithm.fixed_alpha,
        "algorithm.parseval.diagonal": recipe.algorithm.parseval.diagonal,
        "algorithm.parseval.input_scale": recipe.algorithm.parseval.input_scale,
        "replay.size": recipe.replay.size,
    }
    for net in ("actor", "critic"):
        m = getattr(recipe.network, net)
        fp[f"network.{net}.num_cells"] = list(m.num_cells)
        fp[f"network.{net}.low_rank_layers"] = list(m.low_rank_layers)
        fp[f"network.{net}.rank"] = m.rank
        fp[f"network.{net}.sparse"] = m.sparse.model_dump()
    if recipe.algorithm.base == "ppo":
        fp["algorithm.ppo.obs_norm"] = recipe.algorithm.ppo.obs_norm
        fp["algorithm.ppo.policy"] = recipe.algorithm.ppo.policy
    return fp


def _same_in_fingerprint(key: str, theirs: dict, ours: dict) -> bool:
    """Whether a checkpoint's fingerprint entry matches this run's. Checkpoints written before RNAC became the
    registered algorithms ``rnac_ipm``/``rnac_ds`` say ``ppo`` and have no options (their recipe.yaml's old
    ``algorithm.rnac`` section is read as the new name, :mod:`adarl.runtime.config.schema`)."""
    if theirs[key] == ours[key]:
        return True
    return (
        key == "algorithm.name"
        and theirs[key] == "ppo"
        and str(ours[key]).startswith("rnac_")
        and "algorithm.options" not in theirs
    )


class RunFolderGone(AdaRLError):
    """The run folder was deleted or moved while a process trained in it: the run stops instead of writing on (it
    would recreate a folder without its recipe or records, which neither resume nor eval can read)."""


class RunDir:
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
                    f"resume it with `adarl resume {p}`, or pass --overwrite to replace it"
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
                    f"there; start the run again with `adarl run RECIPE -o {p}`"
                )
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
        to name the package it is missing)."""
        save_resolved(recipe, self.recipe_path)
        record = {
            "algorithm": plugins.algorithm(recipe.algorithm.name).provenance(),
            "env": {"name": recipe.env.id, **ENV_IDS.provenance(recipe.env.id)},
            "rank_rule": {"name": recipe.rank.rule, **plugins.RANK_RULES.provenance(recipe.rank.rule)},
            "modules": local_plugins.record(recipe.plugins),
        }
        try:
            atomic_write_text(self.plugins_path, json.dumps(record, indent=2) + "\n")
        except OSError as err:
            raise AdaRLError(f"cannot write {str(self.plugins_path)!r}: {describe_os_error(err)}") from None

    def load_recipe(self):
        """The run's recipe.yaml, validated. A run whose algorithm, env or rank rule is no longer registered (its
        plugin package is not installed here) is refused, naming the package and version plugins.json recorded; a
        run whose local plugin module (the recipe's ``plugins``) is missing or changed, naming the module."""
        recorded = self.recorded_plugins()
        local_plugins.check_recorded(recorded.get("modules") or [], str(self.path))
        try:
            return load_recipe(str(self.recipe_path))
        except RecipeError as err:
            for kind, what, names in (
                ("algorithm", "algorithm", plugins.algorithm_names),
                ("env", "env", supported_envs),
                ("rank_rule", "rank rule", plugins.rank_rule_names),
            ):
                used = recorded.get(kind) or {}
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

    def recorded_plugins(self) -> dict:
        """plugins.json as a dict ({} for runs made before it existed, or when it is unreadable)."""
        try:
            out = json.loads(self.plugins_path.read_text())
        except (OSError, ValueError):
            return {}
        return out if isinstance(out, dict) else {}

    @property
    def checkpoint_dir(self) -> Path:
        return self.path / "checkpoints"

    # ------------------------------------------------------------------ logging
    @property
    def wandb_id_path(self) -> Path:
        """``wandb_run_id``: the wandb run this folder logs to, so that a resume continues that run."""
        return self.path / "wandb_run_id"

    def wandb_run_id(self) -> str:
        """This run folder's wandb run id (made and saved on first use)."""
        p = self.wandb_id_path
        if p.is_file():
            rid = p.read_text().strip()
            if rid:
                return rid
        rid = uuid.uuid4().hex[:16]
        atomic_write_text(p, rid + "\n")
        return rid

    def make_logger(self, recipe, *, step: int | None = None) -> Fanout:
        """TorchRL loggers from ``recipe.logging``: CSV into ``metrics/``, optional tensorboard and wandb.

        ``step``: the frames a resume continues from (None: a new run). TensorBoard then hides the events logged
        after it (the work since the checkpoint, logged again), and wandb continues the folder's run (same id,
        ``resume="allow"``) on the same step axis (frames; wandb cannot hide rows, so the lost work's rows stay).
        wandb gets the resolved recipe as the run's config, TensorBoard as text."""
        loggers = [torchrl_loggers.CSVLogger(exp_name="metrics", log_dir=str(self.path))]
        backends = logging_backends(recipe)
        config = recipe.model_dump(mode="json") if hasattr(recipe, "model_dump") else None
        if "tensorboard" in backends:
            new = not (self.path / "tensorboard").exists()
            tb = tensorboard_logger(self.path, purge_step=None if step is None else int(step) + 1)
            if new and config is not None:
                tb.experiment.add_text("recipe", "```yaml\n" + recipe_to_yaml(recipe) + "```", global_step=0)
            loggers.append(tb)
        if "wandb" in backends:
            loggers.append(
                torchrl_loggers.WandbLogger(
                    exp_name=recipe.name,
                    project=recipe.logging.wandb_project,
                    offline=recipe.logging.wandb_mode == "offline",
                    save_dir=str(self.path),
                    id=self.wandb_run_id(),
                    config=config,
                )
            )
        return Fanout(loggers, check=self.ensure_present)

    def close_logger(self, logger: Fanout) -> None:
        for lg in logger.loggers:
            exp = getattr(lg, "experiment", None)
            if not hasattr(exp, "files"):  # wandb: finish (a resume or rollback re-opens the run by its id); TB
                close = getattr(exp, "finish", None) or getattr(exp, "close", None)
                if close is not None:
                    close()
                continue
            for fd in getattr(exp, "files", {}).values():
                try:
                    fd.close()
                except OSError:
                    pass

    def scalars(self) -> dict[str, list[tuple[int, float]]]:
        """All CSV scalars as ``{name: [(step, value), ...]}``: ``rollout/ep_rew_mean`` from
        ``metrics/scalars/rollout/ep_rew_mean.csv`` (its header row skipped), and a folder's files of earlier
        versions by their own names (``train/episode_return``, ``train.episode_return``, without a header;
        :func:`adarl.runtime.metrics.series` reads any)."""
        out = {}
        root = self.path / "metrics" / "scalars"
        for f in sorted(root.rglob("*.csv")) if root.is_dir() else []:
            rows = []
            for line in f.read_text().splitlines():
                parts = line.split(",")
                if len(parts) == 2:
                    try:
                        rows.append((int(float(parts[0])), float(parts[1])))
                    except ValueError:
                        continue
            out[f.relative_to(root).with_suffix("").as_posix()] = rows
        return out

    def truncate_metrics(self, frames: int) -> None:
        """Drop metric rows logged after ``frames`` (work lost since the checkpoint being resumed)."""
        root = self.path / "metrics" / "scalars"
        for f in root.rglob("*.csv") if root.is_dir() else []:
            keep = []
            for line in f.read_text().splitlines():
                if line == metrics.CSV_HEADER:
                    keep.append(line)
                    continue
                parts = line.split(",")
                try:  # a line cut short by a crash (no value, or no number) is dropped too
                    float(parts[1])
                    if len(parts) == 2 and int(float(parts[0])) <= frames:
                        keep.append(line)
                except (ValueError, IndexError):
                    continue
            atomic_write_text(f, "".join(k + "\n" for k in keep))
        ev = self.path / "eval.csv"
        if ev.is_file():
            rows = [r for r in self.read_eval() if int(r["frames"]) <= frames]
            self._write_eval_rows(rows)

    # ------------------------------------------------------------------ evaluation and ranks
    def append_eval(self, frames: int, updates: int, result, ranks: dict) -> None:
        self.ensure_present()
        path = self.path / "eval.csv"
        new = not path.exists()
        with naming(path), path.open("a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=_EVAL_FIELDS)
            if new:
                w.writeheader()
            w.writerow(
                {
                    "frames": frames,
                    "updates": updates,
                    "mean": result.mean,
                    "std": result.std,
                    "ci95": result.ci95,
                    "episodes": len(result.returns),
                    "returns": json.dumps(result.returns),
                    "ranks": json.dumps(ranks),
                }
            )
            fh.flush()
            os.fsync(fh.fileno())

    def sync_metrics(self, logger: Fanout) -> None:
        """Flush and fsync the CSV metric files, so that what a checkpoint says was logged is on disk."""
        self.ensure_present()
        for lg in logger.loggers:
            for name, fd in list(getattr(getattr(lg, "experiment", None), "files", {}).items()):
                try:
                    with naming(Path(name)):
                        fd.flush()
                        os.fsync(fd.fileno())
                except ValueError:  # closed file; an OSError (a full disk) propagates: the checkpoint would lie
                    pass

    def read_eval(self) -> list[dict]:
        path = self.path / "eval.csv"
        if not path.is_file():
            return []
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))

    def _write_eval_rows(self, rows: list[dict]) -> None:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=_EVAL_FIELDS)
        w.writeheader()
        w.writerows(rows)
        atomic_write_text(self.path / "eval.csv", buf.getvalue())

    def last_eval(self) -> dict | None:
        rows = self.read_eval()
        if not rows:
            return None
        r = rows[-1]
        return {
            "frames": int(r["frames"]),
            "mean": float(r["mean"]),
            "std": float(r["std"]),
            "ci95": float(r["ci95"]),
            "episodes": int(r["episodes"]),
        }

    def write_rank_history(self, history: list, frames: int | None = None) -> None:
        """Rank events as JSON (with spectra) and a flat CSV, one row per event and layer.

        The CSV holds one value per cell: for a stacked critic ensemble, ``retained_energy`` is the smallest
        member's and ``truncation_error`` the largest member's, ``member_ranks`` and ``tried`` (the ranks the
        acceptance step measured, ``rank:error``) are ``;``-separated; spectra are in the JSON only.
        """
        records = [h if isinstance(h, dict) else h.as_dict() if hasattr(h, "as_dict") else vars(h) for h in history]
        self.write_json("ranks.json", records)
        flat = []
        for rec in records:
            for layer in rec.get("layers", [rec]):
                row = {"step": rec.get("step")}
                if rec.get("frames") is not None:  # recorded since issue 31: the frames at the event
                    row["frames"] = rec["frames"]
                for k, v in layer.items():
                    if k == "singular_values":
                        continue
                    if isinstance(v, list):
                        if k == "retained_energy":
                            v = min(v) if v else None
                        elif k == "truncation_error":
                            v = max(v) if v else None
                        elif k == "tried":
                            v = ";".join(f"{int(r)}:{float(e):.6g}" for r, e in v)
                        else:
                            v = ";".join(str(x) for x in v)
                    elif isinstance(v, dict):
                        continue
                    row[k] = v
                if "name" in row and "layer" in row:  # the human name beside the module path
                    keys = [k for k in row if k != "name"]
                    keys.insert(keys.index("layer") + 1, "name")
                    row = {k: row[k] for k in keys}
                flat.append(row)
        if flat:
            keys = list(dict.fromkeys(k for row in flat for k in row))
            buf = io.StringIO()
            w = csv.DictWriter(buf, fieldnames=keys)
            w.writeheader()
            w.writerows(flat)
            atomic_write_text(self.path / "ranks.csv", buf.getvalue())

    def read_rank_history(self) -> list[dict]:
        p = self.path / "ranks.json"
        return json.loads(p.read_text()) if p.is_file() else []

    def write_json(self, name: str, obj) -> None:
        """Write ``name`` atomically as strict JSON: NaN and infinities become ``null`` (JSON has no NaN)."""
        self.ensure_present()
        atomic_write_text(self.path / name, json.dumps(plain(obj), indent=2, allow_nan=False) + "\n")

    # ------------------------------------------------------------------ checkpoints
    def checkpoints(self) -> list[Path]:
        """Checkpoint files, oldest first."""
        d = self.checkpoint_dir
        return sorted(d.glob("ckpt-*.pt")) if d.is_dir() else []

    def latest_checkpoint_frames(self) -> int | None:
        """The frames of the newest checkpoint (what ``adarl resume`` starts from, if it loads), None without one."""
        return max((f for f in map(_frames_of, self.checkpoints()) if f is not None), default=None)

    @property
    def best_checkpoint_path(self) -> Path:
        """``checkpoints/best.pt``: the state at the best nominal evaluation so far (no replay buffer)."""
        return self.checkpoint_dir / "best.pt"

    def _payload(self, state: dict, frames: int, fingerprint: dict | None, **extra) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "adarl_version": __version__,
            "frames": int(frames),
            "recipe_fingerprint": fingerprint,
            **extra,
            "state": state,
        }

    def save_checkpoint(
        self, state: dict, *, frames: int, keep_last: int = 3, replay_buffer=None, fingerprint: dict | None = None
    ) -> Path:
        """Write ``ckpt-<frames>.pt`` (and the replay buffer beside it) atomically, then delete the oldest.

        Order: buffer to a temporary folder, renamed; checkpoint to a temporary file, fsync'ed, renamed; folder
        fsync'ed; only then older checkpoints are removed. A crash or a full disk at any point leaves the previous
        checkpoint loadable; on a write error the partial files are removed and :class:`CheckpointError` says so.
        The buffer is written with ordinary writes (a full disk is an ``OSError``), never memory-mapped: TorchRL's
        ``dumps()`` memory-maps its files, and a full disk then kills the process with SIGBUS, with no message.
        ``fingerprint``: :func:`recipe_fingerprint` of the run, checked when the checkpoint is loaded.
        """
        self.ensure_present()
        path = self.checkpoint_dir / f"ckpt-{int(frames):012d}.pt"
        rb_dir = self.checkpoint_dir / f"rb-{int(frames):012d}"
        rb_tmp = rb_dir.with_name(rb_dir.name + ".tmp")
        rb_old = rb_dir.with_name(rb_dir.name + ".old.tmp")
        writing = self.checkpoint_dir  # what the message names when a write fails
        try:
            self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            if replay_buffer is not None:
                shutil.rmtree(rb_tmp, ignore_errors=True)
                writing = rb_dir / REPLAY_BUFFER_FILE
                check_free_space(
                    self.checkpoint_dir,
                    buffer_nbytes(replay_buffer) + nbytes(state),
                    "the checkpoint with its replay buffer",
                )
                rb_tmp.mkdir()
                atomic_torch_save(replay_buffer.state_dict(), rb_tmp / REPLAY_BUFFER_FILE)
                if rb_dir.exists():
                    # Written again at the same frames (the run's end): the old buffer is renamed aside, not emptied
                    # in place, so that a kill meanwhile never leaves the checkpoint beside a half-deleted buffer (it
                    # then has none, and resume falls back to the previous checkpoint, saying so).
                    shutil.rmtree(rb_old, ignore_errors=True)
                    os.replace(rb_dir, rb_old)
                os.replace(rb_tmp, rb_dir)
            writing = path
            atomic_torch_save(self._payload(state, frames, fingerprint, replay_buffer=replay_buffer is not None), path)
            fsync_dir(self.checkpoint_dir)
            shutil.rmtree(rb_old, ignore_errors=True)
        except OSError as err:
            shutil.rmtree(rb_tmp, ignore_errors=True)
            if replay_buffer is not None and not path.exists():
                shutil.rmtree(rb_dir, ignore_errors=True)
            prev = [p.name for p in self.checkpoints() if p != path]
            full = err.errno in (errno.ENOSPC, errno.EDQUOT)
            remedy = "free space" if full else f"make {str(self.path)!r} writable"
            raise CheckpointError(
                f"could not write checkpoint {path.name}{' (disk full)' if full else ''}: {str(writing)!r}: "
                f"{err.strerror or err}; the run stopped. The previous checkpoint {prev[-1] if prev else '(none)'} "
                f"is intact: {remedy} and `adarl resume {self.path}`",
                path=path,
                reason=err.strerror or str(err),
            ) from None
        for old in self.checkpoints()[:-keep_last]:
            old.unlink(missing_ok=True)
            shutil.rmtree(self._replay_buffer_dir(old), ignore_errors=True)
        return path

    def save_best(self, state: dict, *, frames: int, score: float, fingerprint: dict | None = None) -> Path | None:
        """Replace ``checkpoints/best.pt`` (atomically); a write error keeps the old one and only warns."""
        self.ensure_present()
        try:
            self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            atomic_torch_save(self._payload(state, frames, fingerprint, score=float(score)), self.best_checkpoint_path)
        except OSError as err:
            warnings.warn(f"could not update {self.best_checkpoint_path}: {describe_os_error(err)}", stacklevel=2)
            return None
        return self.best_checkpoint_path

    @staticmethod
    def _replay_buffer_dir(checkpoint: Path, frames: int | None = None) -> Path:
        """``rb-<frames>/`` beside the checkpoint file (wherever that file is)."""
        if frames is None:
            frames = int(checkpoint.name.split(".")[0].removeprefix("ckpt-"))
        return checkpoint.parent / f"rb-{int(frames):012d}"

    def load_checkpoint(
        self, path: str | os.PathLike, *, fingerprint: dict | None = None, replay_buffer: bool = True
    ) -> dict:
        """Load one checkpoint safely (``weights_only=True``: no code runs from the file) and check it fits.

        ``fingerprint`` (:func:`recipe_fingerprint` of the run): a checkpoint written under another recipe is refused
        before any tensor is used. ``replay_buffer``: require the buffer it was saved with, beside the file, and read
        it (a damaged buffer refuses the checkpoint; evaluation and policies do not need it). Only regular files are
        read (a FIFO would block). The state gets ``checkpoint_file``, where the buffer is looked for."""
        path = Path(path)

        def refuse(reason: str) -> CheckpointError:
            return CheckpointError(f"checkpoint {str(path)!r} {reason}", path=path, reason=reason)

        try:
            payload = safe_load(path)
        except FileNotFoundError:
            raise refuse("does not exist") from None
        except NotAFile as err:
            raise refuse(str(err)) from None
        except Exception as err:  # truncated zip, pickle with code, garbage bytes
            raise refuse(f"cannot be loaded safely: {why_unloadable(err)}") from None
        if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
            raise refuse("is not an adarl checkpoint (format marker missing)")
        state = payload.get("state")
        try:  # the fields everything below relies on, of the right kinds (a file may hold anything plain)
            version = int(payload.get("version", 0))
            if version > CHECKPOINT_VERSION:  # a newer layout: say so before judging it by this one
                raise refuse(
                    f"was written by a newer adarl (checkpoint version {version}, this version reads up to "
                    f"{CHECKPOINT_VERSION}); upgrade adarl to load it"
                )
            frames = int(payload.get("frames", state["counters"]["frames"]))
            int(state["counters"]["frames"])
        except (TypeError, ValueError, KeyError, IndexError):
            raise refuse("is not an adarl checkpoint (no training state in it)") from None
        theirs = payload.get("recipe_fingerprint")
        if fingerprint is not None and isinstance(theirs, dict):
            differ = [k for k in fingerprint if k in theirs and not _same_in_fingerprint(k, theirs, fingerprint)]
            if differ:
                shown = "; ".join(f"{k}: {theirs[k]} in it, {fingerprint[k]} in this run" for k in differ[:3])
                raise refuse(
                    f"was written for another recipe ({shown}{'; ...' if len(differ) > 3 else ''}); it "
                    f"cannot be loaded into this run's networks"
                )
        if replay_buffer and payload.get("replay_buffer"):
            rb = self._replay_buffer_dir(path, frames)
            if not rb.is_dir():
                raise refuse(f"has lost its replay buffer: the folder {rb.name} is missing beside it")
            buffer_file = rb / REPLAY_BUFFER_FILE
            if not (buffer_file.exists() or buffer_file.is_symlink() or (rb / "storage").is_dir()):
                # (neither this version's buffer.pt nor an older one's dumps() folder: emptied by a kill mid-write)
                raise refuse(f"has lost its replay buffer: {rb.name} holds no {REPLAY_BUFFER_FILE}")
            if buffer_file.exists() or buffer_file.is_symlink():
                # Read now, not when the trainer fills its buffer: a damaged buffer makes the whole checkpoint
                # unusable, so resume falls back to the previous one as for a missing buffer (kept for
                # load_replay_buffer, which then does not read the file again).
                self._buffer_cache = None
                try:
                    self._buffer_cache = (rb.absolute(), safe_load(buffer_file))
                except NotAFile as err:
                    raise refuse(f"has lost its replay buffer: {rb.name}/{REPLAY_BUFFER_FILE} {err}") from None
                except Exception as err:  # noqa: BLE001 - any unreadable buffer file is refused the same way
                    raise refuse(
                        f"has lost its replay buffer: {rb.name}/{REPLAY_BUFFER_FILE} cannot be loaded safely: "
                        f"{why_unloadable(err)}"
                    ) from None
        state["checkpoint_file"] = str(path)
        return state

    def load_latest_checkpoint(
        self,
        *,
        quarantine: bool = False,
        fingerprint: dict | None = None,
        strict: bool = False,
        replay_buffer: bool = True,
    ) -> dict:
        """The newest checkpoint that loads. A newer one that does not (damaged, or for another recipe) is skipped
        with a :class:`~adarl.errors.CheckpointFallbackWarning` naming it and why, never silently.

        ``strict=True`` (``--checkpoint latest``): the newest or a :class:`CheckpointError`, no fallback.
        ``quarantine=True`` (resume) renames skipped ones to ``*.pt.corrupt`` (so rotation never keeps them in place
        of good checkpoints) and deletes their replay-buffer folders (useless without them, and large).
        """
        errors, bad = [], []
        for path in reversed(self.checkpoints()):
            try:
                state = self.load_checkpoint(path, fingerprint=fingerprint, replay_buffer=replay_buffer)
            except CheckpointError as err:
                if strict:
                    raise CheckpointError(
                        f"{err}; --checkpoint latest does not fall back to an older checkpoint "
                        f"(without it, the newest one that loads is used)",
                        path=err.path,
                        reason=err.reason,
                    ) from None
                errors.append(str(err))
                bad.append((path, err.reason))
                continue
            frames = int(state["counters"]["frames"])
            for b, reason in bad:
                note = ""
                if quarantine:
                    os.replace(b, b.with_name(b.name + ".corrupt"))
                    shutil.rmtree(self._replay_buffer_dir(b), ignore_errors=True)
                    note = f" (renamed {b.name}.corrupt)"
                lost = _frames_of(b) - frames if _frames_of(b) is not None else None
                warnings.warn(
                    f"skipped checkpoint {b.name}{note}: {reason}; using {path.name} instead"
                    + (f", {lost} frames earlier" if lost is not None and lost > 0 else "")
                    + " (--checkpoint latest refuses instead)",
                    CheckpointFallbackWarning,
                    stacklevel=2,
                )
            return state
        if errors:
            raise CheckpointError(
                "no loadable checkpoint in run folder: " + "; ".join(errors) + f"; `adarl run RECIPE -o {self.path} "
                "--overwrite` trains it again from the start"
            )
        raise CheckpointError(
            f"no checkpoint in {str(self.checkpoint_dir)!r} to resume from, though the run folder holds training "
            f"records (were its checkpoints deleted?); `adarl run RECIPE -o {self.path} --overwrite` trains it "
            f"again from the start"
        )

    def load_replay_buffer(self, replay_buffer, *, frames: int, checkpoint: str | os.PathLike | None = None) -> bool:
        """Fill ``replay_buffer`` from ``rb-<frames>/`` beside ``checkpoint`` (default: in this run's checkpoints);
        False when there is none. Reads this version's ``buffer.pt`` or an older checkpoint's ``dumps()`` folder."""
        base = Path(checkpoint).parent if checkpoint is not None else self.checkpoint_dir
        rb_dir = base / f"rb-{int(frames):012d}"
        if not rb_dir.is_dir():
            return False
        cached, self._buffer_cache = self._buffer_cache, None
        if cached is not None and cached[0] == rb_dir.absolute():  # read (and checked) by load_checkpoint
            replay_buffer.load_state_dict(cached[1])
        elif (rb_dir / REPLAY_BUFFER_FILE).exists() or (rb_dir / REPLAY_BUFFER_FILE).is_symlink():
            try:
                sd = safe_load(rb_dir / REPLAY_BUFFER_FILE)
            except Exception as err:  # noqa: BLE001 - any unreadable file is refused the same way
                raise CheckpointError(
                    f"replay buffer {str(rb_dir / REPLAY_BUFFER_FILE)!r} cannot be loaded safely: "
                    f"{why_unloadable(err)}",
                    path=rb_dir,
                    reason=why_unloadable(err),
                ) from None
            replay_buffer.load_state_dict(sd)
        else:
            replay_buffer.loads(str(rb_dir))
        return True


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


def _frames_of(checkpoint: Path) -> int | None:
    try:
        return int(checkpoint.name.split(".")[0].removeprefix("ckpt-"))
    except ValueError:
        return None
