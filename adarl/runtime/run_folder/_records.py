"""A run folder's training records: its loggers, ``eval.csv``, ``ranks.json``/``ranks.csv`` and JSON files.

Part of :class:`adarl.runtime.run_folder.run_dir.RunDir` (a mixin: the folder's layout is described there); what it
writes is
written atomically or fsync'ed, so a crash leaves the previous records readable.
"""

from __future__ import annotations

import csv
import io
import json
import os
import uuid
from pathlib import Path

from adarl.runtime import metrics
from adarl.runtime.config import recipe_to_yaml
from adarl.runtime.run_folder._file_safety import (
    atomic_write_text,
    naming,
    plain,
)
from adarl.runtime.run_folder._loggers import Fanout, logging_backends, tensorboard_logger

_EVAL_FIELDS = ["frames", "updates", "mean", "std", "ci95", "episodes", "returns", "ranks"]


class RunRecords:
    """The records :class:`~adarl.runtime.run_folder.run_dir.RunDir` writes and reads below ``self.path``."""

    path: Path

    def ensure_present(self) -> None:  # pragma: no cover - RunDir's
        raise NotImplementedError

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
        backends = logging_backends(recipe)  # a missing extra is named now, before anything is written
        return Fanout(make=lambda: self._loggers(recipe, backends, step), check=self.ensure_present)

    def _loggers(self, recipe, backends: set[str], step: int | None) -> list:
        """The loggers :meth:`make_logger` names, made (files created) at the run's first scalar."""
        from torchrl.record import loggers as torchrl_loggers  # here: a process that never logs skips its import

        loggers = [torchrl_loggers.CSVLogger(exp_name="metrics", log_dir=str(self.path))]
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
        return loggers

    def close_logger(self, logger: Fanout) -> None:
        for lg in logger.started:
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
        for lg in logger.started:
            for name, fd in list(getattr(getattr(lg, "experiment", None), "files", {}).items()):
                try:
                    with naming(Path(name)):
                        fd.flush()
                        os.fsync(fd.fileno())
                except ValueError:  # closed file; an OSError (a full disk) propagates: the checkpoint would lie
                    pass
        self.write_progress()

    def write_progress(self) -> Path:
        """``metrics/progress.csv``: every scalar of the run in one wide table, as SB3's ``progress.csv`` (one row
        per logged step, ``time/total_timesteps`` first, a column per metric, blank where a metric was not logged at
        that step). Made from the per-metric CSV files (the records resume truncates), at every checkpoint and at the
        end of the run, so it always agrees with them (none before the first scalar); pandas writes it."""
        import pandas as pd

        scalars = {name: rows for name, rows in self.scalars().items() if rows}
        path = self.path / "metrics" / "progress.csv"
        if not scalars:  # nothing logged (yet, or after a resume to frame 0): no table, and no stale one
            path.unlink(missing_ok=True)
            return path
        table = pd.DataFrame(
            {name: pd.Series(dict(rows), dtype=float) for name, rows in sorted(scalars.items()) if rows}
        ).sort_index()
        table.insert(0, "time/total_timesteps", table.index.astype("int64"))
        path.parent.mkdir(exist_ok=True)
        atomic_write_text(path, table.to_csv(index=False, float_format="%.10g"))
        return path

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
