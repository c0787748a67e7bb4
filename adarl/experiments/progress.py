"""Progress of an experiment's runs, read from their folders: one line per run and an aggregate bar.

It reads only what a run writes anyway (``metrics/scalars/*.csv``, ``eval.csv``, ``summary.json``), so it works the
same for runs on this machine, on Ray workers or on SLURM nodes, as long as the results folder is shared (a path, or
an fsspec URL the runs upload to). :class:`ProgressBoard` renders plain lines (logs, pipes, CI); :class:`LiveBoard`
redraws the same board in place on a terminal, with rich.
"""

from __future__ import annotations

import csv
import io
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml
from rich import box
from rich.console import Console, Group
from rich.live import Live
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from adarl.runtime import metrics
from adarl.runtime.run_folder.results import is_url, join, read_text

__all__ = ["RunProgress", "BoardTotals", "read_progress", "ProgressBoard", "LiveBoard", "use_live"]


@dataclass
class RunProgress:
    """Where one run stands: ``state`` is pending | running | finished | failed | interrupted | skipped-finished |
    missing-recipe."""

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


def _read(folder: str | Path, rel: str) -> str | None:
    """A run file's text, or None (missing, or a URL that does not answer: progress is best effort)."""
    if is_url(folder):
        try:
            return read_text(join(folder, rel))
        except Exception:  # noqa: BLE001 - a network hiccup must not stop the experiment
            return None
    try:
        return (Path(folder) / rel).read_text()
    except OSError:
        return None


def _last_step(text: str | None) -> tuple[int, float] | None:
    if text is None:
        return None
    lines = text.strip().splitlines()
    for line in reversed(lines):
        parts = line.split(",")
        try:
            return int(float(parts[0])), float(parts[1])
        except (ValueError, IndexError):
            continue
    return None


def read_progress(run_id: str, path: str | Path, state: str) -> RunProgress:
    """Frames done (the last logged training step), the latest evaluation return (else the last training episode's)."""
    p = path if is_url(path) else Path(path)
    total, recipe = None, _read(p, "recipe.yaml")
    try:
        total = int(yaml.safe_load(recipe)["collector"]["total_frames"]) if recipe is not None else None
    except (KeyError, TypeError, ValueError, yaml.YAMLError):
        pass
    frames, ret = 0, None
    for name in (metrics.TRAIN_UPDATES, metrics.TRAIN_RETURN):
        last = None
        for candidate in metrics.csv_paths(name):  # a run of an older adarl wrote train/updates.csv, train.updates.csv
            text = _read(p, candidate)
            if text is not None:
                last = _last_step(text)
                break
        if last is not None:
            frames = max(frames, last[0])
            if name == metrics.TRAIN_RETURN:
                ret = last[1]
    text = _read(p, "eval.csv")
    try:
        rows = list(csv.DictReader(io.StringIO(text))) if text is not None else []
        if rows:
            frames, ret = max(frames, int(rows[-1]["frames"])), float(rows[-1]["mean"])
    except (KeyError, ValueError, TypeError):
        pass
    return RunProgress(run_id, state, frames, total, ret)


@dataclass
class BoardTotals:
    """The aggregate of a board: runs ended (finished, skipped or failed) of all runs, frames done of all frames."""

    n_done: int
    n: int
    done_frames: int
    all_frames: int

    @property
    def frac(self) -> float:
        return self.done_frames / self.all_frames if self.all_frames else 0.0

    def line(self, width: int) -> str:
        filled = int(round(self.frac * width))
        bar = "#" * filled + "." * (width - filled)
        return f"[{bar}] {self.n_done}/{self.n} runs done, {100 * self.frac:.0f}% of frames"


class ProgressBoard:
    """Tracks states set by a launcher and renders the per-run lines plus an aggregate bar.

    ETA of a running run: its frames left at the frame rate seen since it was first seen running (in this session).
    """

    def __init__(self, runs, width: int = 30) -> None:
        self.runs = runs  # PlannedRun objects; their .status is the state
        self.width = width
        self._seen: dict[str, tuple[float, int]] = {}
        self.running: set[str] = set()

    def snapshot(self) -> tuple[list[RunProgress], BoardTotals]:
        """Every run's progress (read now from its folder) and the aggregate."""
        progs, done_frames, all_frames = [], 0, 0
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
                # a run that has not started has no recipe.yaml yet: its planned budget counts all the same
                total = prog.total_frames or getattr(r, "total_frames", None) or 0
                all_frames += total
                done_frames += total if state in ("finished", "skipped-finished") else min(prog.frames, total)
                n_done += state in ("finished", "skipped-finished", "failed")
            progs.append(prog)
        n = sum(r.status != "missing-recipe" for r in self.runs)
        return progs, BoardTotals(n_done, n, done_frames, all_frames)

    def render(self) -> list[str]:
        """Plain lines: one per run, then the aggregate bar."""
        progs, totals = self.snapshot()
        return [p.line() for p in progs] + [totals.line(self.width)]


def use_live(stream=None, environ=None) -> bool:
    """Whether to redraw in place: ``stream`` (stdout) is a terminal, and not a dumb one or under CI."""
    stream = sys.stdout if stream is None else stream
    environ = os.environ if environ is None else environ
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty()) and not environ.get("CI") and environ.get("TERM") != "dumb"


_STYLES = {
    "running": "bold cyan",
    "finished": "green",
    "skipped-finished": "green",
    "failed": "bold red",
    "interrupted": "yellow",
    "pending": "dim",
    "missing-recipe": "yellow",
}
_KEEP_FIRST = ("running", "failed", "interrupted")  # rows kept when the terminal is too short for all of them


class LiveBoard:
    """A :class:`ProgressBoard` redrawn in place with rich: the aggregate bar, then a table with one row per run
    (state, run, frames, last return, ETA). Messages go through :meth:`log` and scroll above it. When the terminal
    is too short for every row, running, failed and interrupted runs are shown first and the rest is counted."""

    def __init__(self, board: ProgressBoard, console=None) -> None:
        self.board = board
        self.console = console if console is not None else Console()
        self._start = time.monotonic()
        self._live = Live(console=self.console, auto_refresh=False, transient=False)
        self._started = False

    def renderable(self):
        progs, totals = self.board.snapshot()
        head = Table.grid(padding=(0, 1))
        head.add_row(
            ProgressBar(total=max(totals.all_frames, 1), completed=totals.done_frames, width=self.board.width),
            Text(
                f"{totals.n_done}/{totals.n} runs done, {100 * totals.frac:.0f}% of frames, "
                f"{_fmt_s(time.monotonic() - self._start)} elapsed"
            ),
        )
        room = max(self.console.size.height - 8, 3)
        keep = set(range(len(progs)))
        if len(progs) > room:
            order = sorted(keep, key=lambda i: (progs[i].state not in _KEEP_FIRST, progs[i].state != "pending", i))
            keep = set(order[:room])
        shown = [p for i, p in enumerate(progs) if i in keep]
        table = Table(box=box.SIMPLE_HEAD, pad_edge=False, expand=False)
        for name, justify in (
            ("state", "left"),
            ("run", "left"),
            ("frames", "right"),
            ("return", "right"),
            ("eta", "right"),
        ):
            table.add_column(name, justify=justify, no_wrap=True)
        for p in shown:
            total = f"/{p.total_frames}" if p.total_frames else ""
            table.add_row(
                Text(p.state, style=_STYLES.get(p.state, "")),
                p.run_id,
                f"{p.frames}{total}",
                "-" if p.last_return is None else f"{p.last_return:.1f}",
                "-" if p.eta_s is None else _fmt_s(p.eta_s),
            )
        if len(shown) < len(progs):
            hidden: dict[str, int] = {}
            for i, p in enumerate(progs):
                if i not in keep:
                    hidden[p.state] = hidden.get(p.state, 0) + 1
            counts = ", ".join(f"{n} {state}" for state, n in sorted(hidden.items()))
            table.caption = f"{len(progs) - len(shown)} more: {counts}"
        return Group(head, table)

    def update(self) -> None:
        if self._started:
            self._live.update(self.renderable(), refresh=True)

    def log(self, message: str) -> None:
        """Print a message above the board (plain text: no rich markup)."""
        self.console.print(message, markup=False, highlight=False, soft_wrap=True)

    def __enter__(self) -> LiveBoard:
        self._live.update(self.renderable())
        self._live.start(refresh=True)
        self._started = True
        return self

    def __exit__(self, *exc) -> None:
        try:
            self._live.update(self.renderable(), refresh=True)
        finally:
            self._live.stop()
            self._started = False
