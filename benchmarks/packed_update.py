"""Seed-updates/s of N seeds' SAC updates: one packed update (adarl.fast.packed) against the same N seeds' fused
updates one after another, side by side in one process (interleaved, the order reversed every other repeat, median
of the repeats), at Hopper-v5's sizes, batch 256, one torch thread unless --threads.

The update window only (sampling, noise, losses, backward, clipping, Adam, schedules, Polyak): no env, no
collection, no rank events. Whole runs come with the packed trainer (issue 49).

    PYTHONPATH=. python benchmarks/packed_update.py [--seeds 1 2 4 8 16] [--widths 64 256] [--steps 200]
        [--repeats 3] [--output benchmarks/results/packed_update.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch

from adarl.fast.packed import PackedSACUpdate
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe

p = argparse.ArgumentParser()
p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4, 8, 16])
p.add_argument("--widths", type=int, nargs="+", default=[64, 256])
p.add_argument("--steps", type=int, default=200, help="updates per seed per timed window")
p.add_argument("--warmup", type=int, default=20)
p.add_argument("--repeats", type=int, default=3)
p.add_argument("--threads", type=int, default=1)
p.add_argument("--output", default=None)
a = p.parse_args()
torch.set_num_threads(a.threads)


def components(width: int, seed: int):
    recipe = load_recipe(
        "quickstart",
        [
            "algorithm.fused=true",
            f"seed={seed}",
            f"network.actor.num_cells=[{width},{width}]",
            f"network.critic.num_cells=[{width},{width}]",
            "lr_schedule.warmup_steps=1",
        ],
    )
    c = build_sac_components(recipe)
    torch.manual_seed(seed)
    c.replay_buffer.extend(c.env.rollout(1000, break_when_any_done=False).reshape(-1))
    return c


def solo_window(cs, steps: int) -> float:
    t0 = time.perf_counter()
    for _ in range(steps):
        for c in cs:
            c.update()
    return time.perf_counter() - t0


def packed_window(cs, packed: PackedSACUpdate, steps: int) -> float:
    t0 = time.perf_counter()
    for _ in range(steps):
        batches = [c.update.sampler() for c in cs]
        noises = [c.update.fused.draw_noise(b[0], b[1]) for c, b in zip(cs, batches, strict=True)]
        packed.step(batches, noises)
    return time.perf_counter() - t0


rows = []
for width in a.widths:
    for n in a.seeds:
        solo_cs = [components(width, s) for s in range(n)]
        packed_cs = [components(width, s) for s in range(n)]
        packed = PackedSACUpdate([c.update.fused for c in packed_cs])
        solo_window(solo_cs, a.warmup)
        packed_window(packed_cs, packed, a.warmup)
        times = {"solo": [], "packed": []}
        for r in range(a.repeats):
            order = ("solo", "packed") if r % 2 == 0 else ("packed", "solo")
            for v in order:
                dt = solo_window(solo_cs, a.steps) if v == "solo" else packed_window(packed_cs, packed, a.steps)
                times[v].append(dt)
        solo_s, packed_s = statistics.median(times["solo"]), statistics.median(times["packed"])
        row = {
            "width": width,
            "seeds": n,
            "solo_seed_updates_per_s": n * a.steps / solo_s,
            "packed_seed_updates_per_s": n * a.steps / packed_s,
            "solo_ms_per_seed_update": 1e3 * solo_s / (n * a.steps),
            "packed_ms_per_seed_update": 1e3 * packed_s / (n * a.steps),
            "ratio_packed_over_solo": solo_s / packed_s,
            "solo_windows_s": times["solo"],
            "packed_windows_s": times["packed"],
        }
        rows.append(row)
        print(
            f"({width}, {width}) N={n:>2}: solo {row['solo_ms_per_seed_update']:.3f} ms/seed-update, packed "
            f"{row['packed_ms_per_seed_update']:.3f} ms/seed-update, packed/solo throughput "
            f"{row['ratio_packed_over_solo']:.2f}x",
            flush=True,
        )

print("\n| size | N | solo ms / seed-update | packed ms / seed-update | packed / solo throughput |")
print("|---|---|---|---|---|")
for r in rows:
    print(
        f"| ({r['width']}, {r['width']}) | {r['seeds']} | {r['solo_ms_per_seed_update']:.3f} | "
        f"{r['packed_ms_per_seed_update']:.3f} | {r['ratio_packed_over_solo']:.2f}x |"
    )
if a.output:
    meta = {
        "torch": torch.__version__,
        "threads": a.threads,
        "steps": a.steps,
        "warmup": a.warmup,
        "repeats": a.repeats,
        "machine": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    with open(a.output, "w") as f:
        json.dump({"settings": meta, "rows": rows}, f, indent=2)
