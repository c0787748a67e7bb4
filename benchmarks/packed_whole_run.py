"""Aggregate env frames/s of N seeds trained whole: packed in one process (`adarl run --pack-seeds`) against N solo
runs two at a time (`adarl run`, the way the experiment driver runs them on 2 cores), side by side in one run of this
script, process start to finished run folders (rank events, warm starts, evaluations, checkpoints and reports
included).

    PYTHONPATH=. python benchmarks/packed_whole_run.py [--seeds 1 2 4 8] [--frames 6000] [--width 64]
        [--threads 1] [--no-two-packs] [--output benchmarks/results/packed_whole_run.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

p = argparse.ArgumentParser()
p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4, 8])
p.add_argument("--frames", type=int, default=6000)
p.add_argument("--width", type=int, default=64)
p.add_argument("--threads", type=int, nargs="*", default=[1], help="torch threads of the one packed process")
p.add_argument("--no-two-packs", action="store_true", help="skip the variant of two packs of N/2 side by side")
p.add_argument("--output", default=None)
a = p.parse_args()

w = a.width
OVERRIDES = [
    f"collector.total_frames={a.frames}",
    f"collector.init_random_frames={a.frames // 6}",
    "collector.frames_per_batch=250",
    f"rank.interval={a.frames // 3}",
    "lr_schedule.warmup_steps=200",
    "replay.warm_start.frames=500",
    f"eval.interval={a.frames // 2}",
    "eval.episodes=2",
    "eval.max_steps=200",
    f"checkpoint.interval={a.frames // 2}",
    f"network.actor.num_cells=[{w},{w}]",
    f"network.critic.num_cells=[{w},{w}]",
    "algorithm.fused=true",
]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


def adarl(args: list[str], threads: int = 1) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "adarl.cli", "run", "quickstart", *OVERRIDES, f"algorithm.num_threads={threads}"]
    return subprocess.Popen([*cmd, *args, "--quiet"], env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def check(proc: subprocess.Popen) -> None:
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"a benchmark run failed ({proc.returncode}): {err.decode()[-2000:]}")


def solo(n: int, root: Path) -> float:
    """N solo runs, two at a time."""
    t0 = time.perf_counter()
    pending = list(range(n))
    running: list[subprocess.Popen] = []
    while pending or running:
        while pending and len(running) < 2:
            s = pending.pop(0)
            running.append(adarl([f"seed={s}", "-o", str(root / f"solo{s}")]))
        done = running.pop(0)
        check(done)
    return time.perf_counter() - t0


def packed(n: int, root: Path, threads: int) -> float:
    """One process, the N seeds packed, ``threads`` torch threads."""
    t0 = time.perf_counter()
    check(adarl(["--pack-seeds", *map(str, range(n)), "-o", str(root / f"pack{threads}")], threads))
    return time.perf_counter() - t0


def two_packs(n: int, root: Path) -> float:
    """Two processes side by side (one per core), each packing half of the seeds, one torch thread each."""
    t0 = time.perf_counter()
    half = [list(range(n))[: n // 2], list(range(n))[n // 2 :]]
    procs = [adarl(["--pack-seeds", *map(str, h), "-o", str(root / f"half{k}")]) for k, h in enumerate(half)]
    for proc in procs:
        check(proc)
    return time.perf_counter() - t0


rows = []
for n in a.seeds:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        times = {"solo (2 at a time)": solo(n, root)}
        for t in a.threads:
            times[f"packed, {t} thread(s)"] = packed(n, root, t)
        if n >= 2 and not a.no_two_packs:
            times["2 packs of N/2 side by side"] = two_packs(n, root)
        shutil.rmtree(root, ignore_errors=True)
    base = times["solo (2 at a time)"]
    for variant, secs in times.items():
        row = {
            "seeds": n,
            "width": w,
            "variant": variant,
            "wall_s": secs,
            "aggregate_frames_per_s": n * a.frames / secs,
            "vs_solo": base / secs,
        }
        rows.append(row)
        print(
            f"N={n:>2} ({w}, {w}) {variant:<28} {secs:7.1f} s  {row['aggregate_frames_per_s']:7.1f} frames/s  "
            f"{row['vs_solo']:.2f}x",
            flush=True,
        )

print("\n| N | size | variant | wall (s) | aggregate frames/s | vs solo |")
print("|---|---|---|---|---|---|")
for r in rows:
    print(
        f"| {r['seeds']} | ({r['width']}, {r['width']}) | {r['variant']} | {r['wall_s']:.1f} | "
        f"{r['aggregate_frames_per_s']:.1f} | {r['vs_solo']:.2f}x |"
    )
if a.output:
    meta = {
        "frames": a.frames,
        "overrides": OVERRIDES,
        "machine": f"{os.cpu_count()} cores, {platform.machine()}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    Path(a.output).write_text(json.dumps({"settings": meta, "rows": rows}, indent=2) + "\n")
