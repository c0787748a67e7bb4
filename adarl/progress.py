"""Progress of an experiment's runs, read from their folders: one line per run and an aggregate bar.

It reads only what a run writes anyway (``metrics/scalars/*.csv``, ``eval.csv``, ``summary.json``), so it works the
same for runs on this machine, on Ray workers or on SLURM nodes, as long as the results folder is shared.
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

__all__ = ["RunProgress", "read_progress", "ProgressBoard"]


@dataclass
class RunProgress:
    """Where one run stands: ``state`` is pending | running | finished | failed | skipped-finished | missing-recipe."""

    run_id: str
    state: str
    frames: int
    total_frames: int | None
    last_return: float | None
    eta_s: float | None = None

    def line(self) -> str:
        total = f"/{self.total_frames}" if self.total_frames else ""
        ret = "-" if self.last_return is None else f"{self.last_return:.1f}"
        eta = "-" if self.eta_s is None else _fmt_s(self.eta_s)
        return f"  {self.state:<16} {self.run_id:<40} frames {self.frames}{total:<8} return {ret:<8} eta {eta}"


def _fmt_s(s: float) -> str:
    s = int(max(s, 0))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def _last_step(csv_path: Path) -> tuple[int, float] | None:
    try:
        lines = csv_path.read_text().strip().splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        parts = line.split(",")
        try:
            return int(float(parts[0])), float(parts[1])
        except (ValueError, IndexError):
            continue
    return None


def read_progress(run_id: str, path: str | Path, state: str) -> RunProgress:
    """Frames done (the last logged training step), the latest evaluation return (else the last training episode's)."""
    p = Path(path)
    total = None
    try:
        total = int(yaml.safe_load((p / "recipe.yaml").read_text())["collector"]["total_frames"])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError):
        pass
    scalars = p / "metrics" / "scalars"
    frames, ret = 0, None
    for name in ("train.updates.csv", "train.episode_return.csv"):
        last = _last_step(scalars / name)
        if last is not None:
            frames = max(frames, last[0])
            if name == "train.episode_return.csv":
                ret = last[1]
    try:
        with (p / "eval.csv").open() as fh:
            rows = list(csv.DictReader(fh))
        if rows:
            frames, ret = max(frames, int(rows[-1]["frames"])), float(rows[-1]["mean"])
    except (OSError, KeyError, ValueError):
        pass
    return RunProgress(run_id, state, frames, total, ret)


class ProgressBoard:
    """Tracks states set by a launcher and renders the per-run lines plus an aggregate bar.

    ETA of a running run: its frames left at the frame rate seen since it was first seen running (in this session).
    """

    def __init__(self, runs, width: int = 30) -> None:
        self.runs = runs  # PlannedRun objects; their .status is the state
        self.width = width
        self._seen: dict[str, tuple[float, int]] = {}
        self.running: set[str] = set()

    def render(self) -> list[str]:
        lines, done_frames, all_frames = [], 0, 0
        n_done = 0
        now = time.monotonic()
        for r in self.runs:
            state = "running" if (r.run_id in self.running and r.status == "pending") else r.status
            prog = read_progress(r.run_id, r.path, state)
            if state == "running" and prog.total_frames:
                t0, f0 = self._seen.setdefault(r.run_id, (now, prog.frames))
                if prog.frames > f0 and now > t0:
                    prog.eta_s = (prog.total_frames - prog.frames) * (now - t0) / (prog.frames - f0)
            if state != "missing-recipe":
                total = prog.total_frames or 0
                all_frames += total
                done_frames += total if state in ("finished", "skipped-finished") else min(prog.frames, total)
                n_done += state in ("finished", "skipped-finished", "failed")
            lines.append(prog.line())
        n = sum(r.status != "missing-recipe" for r in self.runs)
        frac = done_frames / all_frames if all_frames else 0.0
        filled = int(round(frac * self.width))
        lines.append(f"[{'#' * filled}{'.' * (self.width - filled)}] {n_done}/{n} runs done, {100 * frac:.0f}% of frames")
        return lines
