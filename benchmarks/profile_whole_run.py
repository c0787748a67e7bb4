"""Where the wall time of a whole run goes: adarl's and SB3's, phase by phase, sampled with py-spy.

    pip install py-spy      # a sampling profiler (a separate binary; not a dependency of adarl)
    python benchmarks/profile_whole_run.py --envs Hopper-v5 --widths 64 --frames 12000 --warmup 5000 \
        --eval-interval 4000 --eval-episodes 3 --rank-events 3 --markdown profile.md

It runs the same commands as ``adarl bench --whole-run`` (the same options and overrides, built by its own
functions: :func:`adarl.experiments.bench.adarl_command` and ``sb3_command``), once each, under
``py-spy record`` (100 samples a second; idle samples and background threads dropped), and files every sample under the
first phase whose marker is on its stack: rank events (SVD and re-factorisation), their warm starts, evaluation,
checkpoints, the report, updates, collection, building, imports. Why py-spy and not cProfile: cProfile's per-call
overhead inflates Python-heavy code (the collectors, TorchRL's TensorDict bookkeeping) several times over and would
distort the split between adarl and SB3; a sampling profiler costs the profiled process almost nothing. The
seconds are samples / rate, so they add up to the process's busy main-thread time, not to its wall time.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from adarl.experiments import bench
from adarl.experiments.bench import DEFAULTS, adarl_command, event_threads, sb3_command

RATE = 100  # samples a second

#: (phase, markers): a sample goes to the first phase with a marker in one of its stack frames
PHASES = [
    ("warm start after a rank event", ["ReplayWarmStart.__call__"]),
    ("rank event (SVD, re-factorisation, optimiser reset)", ["RankAdapter.step"]),
    ("evaluation", ["BaseTrainer._evaluate", "evaluate_policy ("]),
    ("checkpoint", ["BaseTrainer.save_checkpoint"]),
    ("report and plots", ["write_report", "BaseTrainer._write_summary"]),
    ("updates", ["Trainer._update (", "SAC.train ("]),
    ("collection (env steps, policy, replay writes)", ["BaseTrainer._train_batches", "collect_rollouts ("]),
    ("imports", ["_find_and_load ("]),
    ("building (envs, networks, buffer)", ["BaseTrainer.__init__", "SAC.__init__", "whole_run_sb3 ("]),
]
OTHER = "other (argument parsing, recipe, interpreter)"


def classify(raw: str) -> dict[str, float]:
    """Seconds per phase from py-spy's raw (collapsed-stack) output: ``frame;frame;... count`` per line, root first.

    Only the main thread counts: a stack rooted in ``Thread._bootstrap`` is a background thread (tqdm's monitor,
    which py-spy does not always see as idle while it waits), and an empty stack holds no Python frame."""
    seconds: dict[str, float] = collections.defaultdict(float)
    for line in raw.splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or stack.startswith("Thread._bootstrap"):
            continue
        phase = next((name for name, marks in PHASES if any(m in stack for m in marks)), OTHER)
        seconds[phase] += int(count) / RATE
    return dict(seconds)


def profile(cmd: list[str], env: dict, py_spy: str, workdir: Path, keep: Path | None) -> tuple[dict[str, float], float]:
    raw = workdir / "stacks.txt" if keep is None else keep
    prof = [py_spy, "record", "--rate", str(RATE), "--format", "raw", "--output", str(raw), "--"]
    t0 = time.perf_counter()
    proc = subprocess.run(prof + cmd, env=env, cwd=workdir, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not raw.exists():
        raise SystemExit(f"profiled run failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return classify(raw.read_text()), wall


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    bench.add_arguments(p)
    p.add_argument("--py-spy", default=shutil.which("py-spy") or "py-spy", help="the py-spy binary")
    p.add_argument("--raw-dir", type=Path, default=None, help="keep py-spy's raw stacks here, one file per run")
    a = p.parse_args(argv)
    for key, value in DEFAULTS.items():
        if getattr(a, key) is None:
            setattr(a, key, list(value) if isinstance(value, list) else value)
    a.variants = [v for v in a.variants if v in ("adarl", "sb3", "adarl_norank", "torchrl")]
    a.event_threads = event_threads() if a.event_threads == "auto" else int(a.event_threads)
    if a.output == DEFAULTS["output"]:
        a.output = "profile_whole_run.json"
    threads = str(a.threads)
    env = dict(os.environ, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
    if a.raw_dir is not None:
        a.raw_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for env_id in a.envs:
        for width in a.widths:
            for variant in a.variants:
                with tempfile.TemporaryDirectory(prefix="adarl-profile-") as tmp:
                    if variant == "sb3":
                        cmd = sb3_command(a, env_id, width)
                    else:
                        cmd = adarl_command(a, env_id, width, variant, Path(tmp) / "run")
                    keep = None if a.raw_dir is None else a.raw_dir / f"{env_id}_{width}_{variant}.txt"
                    phases, wall = profile(cmd, env, a.py_spy, Path(tmp), keep)
                results.append({"env": env_id, "width": width, "variant": variant, "wall_s": wall, "phases": phases})
                print(f"  profiled {env_id} ({width},{width}) {variant}: {wall:.1f} s", file=sys.stderr, flush=True)
    Path(a.output).write_text(json.dumps({"argv": sys.argv, "results": results}, indent=2) + "\n")
    table = format_table(results)
    if a.markdown:
        Path(a.markdown).write_text(table + "\n")
    print(table)
    return 0


def format_table(results: list[dict]) -> str:
    names = [n for n, _ in PHASES] + [OTHER]
    head = [f"{r['env']} ({r['width']}, {r['width']}) {r['variant']}" for r in results]
    lines = ["| phase (s of main-thread samples) | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for name in names:
        if any(r["phases"].get(name) for r in results):
            lines.append(f"| {name} | " + " | ".join(f"{r['phases'].get(name, 0.0):.1f}" for r in results) + " |")
    lines.append("| sampled, in all | " + " | ".join(f"{sum(r['phases'].values()):.1f}" for r in results) + " |")
    lines.append("| wall time under py-spy | " + " | ".join(f"{r['wall_s']:.1f}" for r in results) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
