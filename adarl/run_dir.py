"""The run folder: one directory per run with everything it produced.

::

    <run>/recipe.yaml            resolved recipe (what ran; `adarl resume` rebuilds from it)
    <run>/metrics/scalars/       TorchRL CSVLogger scalars, one file per metric ("step,value", step = frames):
                                 train/episode_return.csv, eval/return.csv, rank/actor.layer0.csv (adarl.metrics)
    <run>/wandb_run_id           the wandb run this folder logs to (with logging.backends: [wandb]), for resume
    <run>/eval.csv               nominal-dynamics evaluations (frames, updates, mean, std, ci95, episodes, ranks)
    <run>/ranks.json, ranks.csv  rank history: per event and layer, old/new rank, spectrum, energy, error
    <run>/checkpoints/           ckpt-<frames>.pt (torch.save, loaded with weights_only=True) [+ replay buffer]
    <run>/summary.json           final counters, ranks and evaluation
    <run>/report.md, plots/      the report (training return with rank events, rank over time)

Checkpoints are written to a temporary file, fsync'ed and renamed, so a crash mid-write leaves the previous one
intact; the last ``keep_last`` are kept.
"""

from __future__ import annotations

import csv
import errno
import json
import os
import shutil
from pathlib import Path

import torch

from adarl.errors import AdaRLError, CheckpointError

__all__ = ["RunDir", "CHECKPOINT_FORMAT", "CHECKPOINT_VERSION"]

CHECKPOINT_FORMAT = "adarl.checkpoint"
CHECKPOINT_VERSION = 1
_EVAL_FIELDS = ["frames", "updates", "mean", "std", "ci95", "episodes", "returns", "ranks"]


class _Fanout:
    """Send each scalar to every configured TorchRL logger (CSV always; tensorboard / wandb on request)."""

    def __init__(self, loggers):
        self.loggers = loggers

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        for lg in self.loggers:
            lg.log_scalar(name, float(value), step=step)


class RunDir:
    """A run folder; see the module docstring for its layout."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(cls, path: str | os.PathLike, *, overwrite: bool = False) -> RunDir:
        """Make a new run folder; refuse an existing non-empty one unless ``overwrite`` (then it is replaced)."""
        p = Path(path)
        if p.exists() and any(p.iterdir()):
            if not overwrite:
                raise AdaRLError(
                    f"run folder {str(p)!r} already exists and is not empty; choose another output.dir, "
                    f"resume it with `adarl resume {p}`, or pass --overwrite to replace it"
                )
            shutil.rmtree(p)
        p.mkdir(parents=True, exist_ok=True)
        return cls(p)

    @classmethod
    def open(cls, path: str | os.PathLike) -> RunDir:
        p = Path(path)
        if not (p / "recipe.yaml").is_file():
            raise AdaRLError(f"{str(p)!r} is not an adarl run folder (no recipe.yaml in it)")
        return cls(p)

    @property
    def recipe_path(self) -> Path:
        return self.path / "recipe.yaml"

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
        import uuid

        rid = uuid.uuid4().hex[:16]
        _atomic_write_text(p, rid + "\n")
        return rid

    def make_logger(self, recipe, *, step: int | None = None) -> _Fanout:
        """TorchRL loggers from ``recipe.logging``: CSV into ``metrics/``, optional tensorboard and wandb.

        ``step``: the frames a resume continues from (None: a new run). TensorBoard then hides the events logged
        after it (the work since the checkpoint, logged again), and wandb continues the folder's run (same id,
        ``resume="allow"``) on the same step axis (frames; wandb cannot hide rows, so the lost work's rows stay).
        wandb gets the resolved recipe as the run's config, TensorBoard as text."""
        from torchrl.record.loggers import CSVLogger

        loggers = [CSVLogger(exp_name="metrics", log_dir=str(self.path))]
        backends = set(recipe.logging.backends)
        if recipe.logging.wandb_mode == "disabled":
            backends.discard("wandb")
        for backend, package in (("tensorboard", "tensorboard"), ("wandb", "wandb")):
            if backend in backends:
                import importlib.util

                if importlib.util.find_spec(package) is None:
                    raise AdaRLError(
                        f"logging.backends includes {backend!r} but the {package!r} package is not installed; "
                        f"install it (pip install 'adarl[{backend}]') or remove {backend!r} from logging.backends "
                        f"(allowed without extras: ['csv'])"
                    )
        config = recipe.model_dump(mode="json") if hasattr(recipe, "model_dump") else None
        if "tensorboard" in backends:
            new = not (self.path / "tensorboard").exists()
            tb = _tensorboard_logger(self.path, purge_step=None if step is None else int(step) + 1)
            if new and config is not None:
                from adarl.config import recipe_to_yaml

                tb.experiment.add_text("recipe", "```yaml\n" + recipe_to_yaml(recipe) + "```", global_step=0)
            loggers.append(tb)
        if "wandb" in backends:
            from torchrl.record.loggers import WandbLogger

            loggers.append(WandbLogger(exp_name=recipe.name, project=recipe.logging.wandb_project,
                                       offline=recipe.logging.wandb_mode == "offline", save_dir=str(self.path),
                                       id=self.wandb_run_id(), config=config))
        return _Fanout(loggers)

    def close_logger(self, logger: _Fanout) -> None:
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
        """All CSV scalars as ``{name: [(step, value), ...]}``: ``train/episode_return`` from
        ``metrics/scalars/train/episode_return.csv``, and a folder's older flat files by their own names
        (``train.episode_return``; :func:`adarl.metrics.series` reads either)."""
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
                parts = line.split(",")
                try:  # a line cut short by a crash (no value, or no number) is dropped too
                    float(parts[1])
                    if len(parts) == 2 and int(float(parts[0])) <= frames:
                        keep.append(line)
                except (ValueError, IndexError):
                    continue
            _atomic_write_text(f, "".join(k + "\n" for k in keep))
        ev = self.path / "eval.csv"
        if ev.is_file():
            rows = [r for r in self.read_eval() if int(r["frames"]) <= frames]
            self._write_eval_rows(rows)

    # ------------------------------------------------------------------ evaluation and ranks
    def append_eval(self, frames: int, updates: int, result, ranks: dict) -> None:
        path = self.path / "eval.csv"
        new = not path.exists()
        with path.open("a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=_EVAL_FIELDS)
            if new:
                w.writeheader()
            w.writerow({"frames": frames, "updates": updates, "mean": result.mean, "std": result.std,
                        "ci95": result.ci95, "episodes": len(result.returns),
                        "returns": json.dumps(result.returns), "ranks": json.dumps(ranks)})
            fh.flush()
            os.fsync(fh.fileno())

    def sync_metrics(self, logger: _Fanout) -> None:
        """Flush and fsync the CSV metric files, so that what a checkpoint says was logged is on disk."""
        for lg in logger.loggers:
            for fd in list(getattr(getattr(lg, "experiment", None), "files", {}).values()):
                try:
                    fd.flush()
                    os.fsync(fd.fileno())
                except (OSError, ValueError):  # closed file
                    pass

    def read_eval(self) -> list[dict]:
        path = self.path / "eval.csv"
        if not path.is_file():
            return []
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))

    def _write_eval_rows(self, rows: list[dict]) -> None:
        import io

        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=_EVAL_FIELDS)
        w.writeheader()
        w.writerows(rows)
        _atomic_write_text(self.path / "eval.csv", buf.getvalue())

    def last_eval(self) -> dict | None:
        rows = self.read_eval()
        if not rows:
            return None
        r = rows[-1]
        return {"frames": int(r["frames"]), "mean": float(r["mean"]), "std": float(r["std"]),
                "ci95": float(r["ci95"]), "episodes": int(r["episodes"])}

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
            import io

            keys = list(dict.fromkeys(k for row in flat for k in row))
            buf = io.StringIO()
            w = csv.DictWriter(buf, fieldnames=keys)
            w.writeheader()
            w.writerows(flat)
            _atomic_write_text(self.path / "ranks.csv", buf.getvalue())

    def read_rank_history(self) -> list[dict]:
        p = self.path / "ranks.json"
        return json.loads(p.read_text()) if p.is_file() else []

    def write_json(self, name: str, obj) -> None:
        _atomic_write_text(self.path / name, json.dumps(obj, indent=2, default=_json_default) + "\n")

    # ------------------------------------------------------------------ checkpoints
    def checkpoints(self) -> list[Path]:
        """Checkpoint files, oldest first."""
        d = self.checkpoint_dir
        return sorted(d.glob("ckpt-*.pt")) if d.is_dir() else []

    @property
    def best_checkpoint_path(self) -> Path:
        """``checkpoints/best.pt``: the state at the best nominal evaluation so far (no replay buffer)."""
        return self.checkpoint_dir / "best.pt"

    def _payload(self, state: dict, frames: int, **extra) -> dict:
        from adarl import __version__

        return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "adarl_version": __version__,
                "frames": int(frames), **extra, "state": state}

    def save_checkpoint(self, state: dict, *, frames: int, keep_last: int = 3, replay_buffer=None) -> Path:
        """Write ``ckpt-<frames>.pt`` (and the replay buffer beside it) atomically, then delete the oldest.

        Order: buffer to a temporary folder, renamed; checkpoint to a temporary file, fsync'ed, renamed; folder
        fsync'ed; only then older checkpoints are removed. A crash or a full disk at any point leaves the previous
        checkpoint loadable; on a write error the partial files are removed and :class:`CheckpointError` says so.
        """
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        path = self.checkpoint_dir / f"ckpt-{int(frames):012d}.pt"
        rb_dir = self.checkpoint_dir / f"rb-{int(frames):012d}"
        rb_tmp = rb_dir.with_name(rb_dir.name + ".tmp")
        try:
            if replay_buffer is not None:
                shutil.rmtree(rb_tmp, ignore_errors=True)
                replay_buffer.dumps(str(rb_tmp))
                shutil.rmtree(rb_dir, ignore_errors=True)
                os.replace(rb_tmp, rb_dir)
            _atomic_torch_save(self._payload(state, frames, replay_buffer=replay_buffer is not None), path)
            _fsync_dir(self.checkpoint_dir)
        except OSError as err:
            shutil.rmtree(rb_tmp, ignore_errors=True)
            if replay_buffer is not None and not path.exists():
                shutil.rmtree(rb_dir, ignore_errors=True)
            prev = [p.name for p in self.checkpoints() if p != path]
            hint = " (disk full)" if err.errno == errno.ENOSPC else ""
            raise CheckpointError(
                f"could not write checkpoint {path.name}{hint}: {err.strerror or err}; the run stopped. The previous "
                f"checkpoint {prev[-1] if prev else '(none)'} is intact: free space and `adarl resume {self.path}`"
            ) from None
        for old in self.checkpoints()[:-keep_last]:
            old.unlink(missing_ok=True)
            shutil.rmtree(self.checkpoint_dir / old.name.replace("ckpt-", "rb-").replace(".pt", ""),
                          ignore_errors=True)
        return path

    def save_best(self, state: dict, *, frames: int, score: float) -> Path | None:
        """Replace ``checkpoints/best.pt`` (atomically); a write error keeps the old one and only warns."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        try:
            _atomic_torch_save(self._payload(state, frames, score=float(score)), self.best_checkpoint_path)
        except OSError as err:
            import warnings

            warnings.warn(f"could not update {self.best_checkpoint_path}: {err}", stacklevel=2)
            return None
        return self.best_checkpoint_path

    def load_checkpoint(self, path: str | os.PathLike) -> dict:
        """Load one checkpoint safely (``weights_only=True``: no code runs from the file)."""
        path = Path(path)
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise CheckpointError(f"checkpoint {str(path)!r} does not exist") from None
        except Exception as err:  # truncated zip, pickle with code, garbage bytes
            raise CheckpointError(
                f"checkpoint {str(path)!r} cannot be loaded safely (corrupt, truncated or not an adarl "
                f"checkpoint; only tensors and plain containers are accepted): {type(err).__name__}: "
                f"{str(err).splitlines()[0] if str(err) else ''}"
            ) from None
        if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
            raise CheckpointError(f"{str(path)!r} is not an adarl checkpoint (format marker missing)")
        if int(payload.get("version", 0)) > CHECKPOINT_VERSION:
            raise CheckpointError(
                f"{str(path)!r} was written by a newer adarl (checkpoint version {payload['version']}, this "
                f"version reads up to {CHECKPOINT_VERSION}); upgrade adarl to load it"
            )
        state = payload["state"]
        if payload.get("replay_buffer") and not (self.checkpoint_dir / f"rb-{int(payload['frames']):012d}").is_dir():
            raise CheckpointError(f"{str(path)!r}: its replay buffer folder rb-{int(payload['frames']):012d} is missing")
        if not isinstance(state, dict) or "counters" not in state:
            raise CheckpointError(f"{str(path)!r} is not an adarl checkpoint (no training state in it)")
        return state

    def load_latest_checkpoint(self, *, quarantine: bool = False) -> dict:
        """The newest checkpoint that loads; older ones are tried if the newest is damaged.

        ``quarantine=True`` (resume) renames the damaged newer ones to ``*.pt.corrupt`` so that rotation never
        keeps them in place of good checkpoints.
        """
        errors, bad = [], []
        for path in reversed(self.checkpoints()):
            try:
                state = self.load_checkpoint(path)
            except CheckpointError as err:
                errors.append(str(err))
                bad.append(path)
                continue
            if quarantine:
                for b in bad:
                    os.replace(b, b.with_name(b.name + ".corrupt"))
            return state
        if errors:
            raise CheckpointError("no loadable checkpoint in run folder: " + "; ".join(errors))
        raise CheckpointError(f"no checkpoint in {str(self.checkpoint_dir)!r} to resume from")

    def load_replay_buffer(self, replay_buffer, *, frames: int) -> bool:
        rb_dir = self.checkpoint_dir / f"rb-{int(frames):012d}"
        if not rb_dir.is_dir():
            return False
        replay_buffer.loads(str(rb_dir))
        return True


def _tensorboard_logger(path: Path, *, purge_step: int | None):
    """TorchRL's TensorboardLogger, with SummaryWriter's ``purge_step`` (events at or after it are hidden)."""
    from torchrl.record.loggers import TensorboardLogger

    class _Tensorboard(TensorboardLogger):
        def _create_experiment(self):
            from torch.utils.tensorboard import SummaryWriter

            return SummaryWriter(log_dir=os.path.join(self.log_dir, self.exp_name), purge_step=purge_step)

    return _Tensorboard(exp_name="tensorboard", log_dir=str(path))


def _json_default(obj):
    if isinstance(obj, torch.Tensor):
        return obj.tolist()
    if hasattr(obj, "as_dict"):
        return obj.as_dict()
    if hasattr(obj, "__dict__"):
        return vars(obj)
    return str(obj)


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _atomic_torch_save(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("wb") as fh:
            torch.save(obj, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
