"""ms per frame of collection alone on Hopper-v5 (paper perturbation, policy actions, 1 torch thread), side by side:
TorchRL's ``Collector``, and adarl's ``LeanCollector`` stepping TorchRL's env (``direct=False``) or the gymnasium env
directly (``direct=True``, :mod:`adarl.fast.direct_env`; the same batches bit for bit). Same env layout and policy for
all; the variants take turns for ``--rounds`` rounds and the median round is reported.

    PYTHONPATH=. python benchmarks/collector_speed.py [--frames 3000] [--rounds 3] [--skip-torchrl]
"""

import argparse
import statistics
import time

import torch

from adarl.fast.collector import LeanCollector
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe

p = argparse.ArgumentParser()
p.add_argument("--frames", type=int, default=3000, help="frames per variant per round")
p.add_argument("--rounds", type=int, default=3)
p.add_argument("--frames-per-batch", type=int, default=250)
p.add_argument("--skip-torchrl", action="store_true", help="leave TorchRL's Collector out")
a = p.parse_args()
torch.set_num_threads(1)
overrides = [f"collector.frames_per_batch={a.frames_per_batch}"]
variants = {}
if not a.skip_torchrl:
    variants["torchrl Collector"] = iter(
        build_sac_components(
            load_recipe("quickstart", overrides + ["collector.lean=false"]), init_random_frames=0
        ).collector
    )
for direct in (False, True):
    c = build_sac_components(load_recipe("quickstart", overrides), init_random_frames=0)
    lean = LeanCollector(c.env, c.modules.actor, frames_per_batch=a.frames_per_batch, direct=direct)
    variants[f"LeanCollector(direct={direct})"] = iter(lean)
for it in variants.values():  # warm-up: the first batch builds TorchRL's caches
    next(it)
times = {name: [] for name in variants}
for _ in range(a.rounds):
    for name, it in variants.items():
        n, t = 0, time.perf_counter()
        while n < a.frames:
            n += next(it).numel()
        times[name].append((time.perf_counter() - t) * 1e3 / n)
for name, ms in times.items():
    print(f"{name:28s} {statistics.median(ms):.3f} ms/frame (rounds: {', '.join(f'{x:.3f}' for x in ms)})")
