"""Frames/s of collection alone on Hopper-v5: TorchRL's Collector vs adarl's LeanCollector (same env, same policy).

    PYTHONPATH=. python benchmarks/collector_speed.py [--frames 2000]
"""

import argparse
import time

import torch

from adarl.config import load_recipe
from adarl.training import build_components

p = argparse.ArgumentParser()
p.add_argument("--frames", type=int, default=2000)
a = p.parse_args()
torch.set_num_threads(1)
for lean in ("false", "true", "false", "true"):
    c = build_components(load_recipe("quickstart", [f"collector.lean={lean}", "collector.frames_per_batch=250"]),
                         init_random_frames=0)
    n, t = 0, time.perf_counter()
    for batch in c.collector:
        n += batch.numel()
        if n >= a.frames:
            break
    print(f"{'LeanCollector' if lean == 'true' else 'torchrl Collector'}: {n / (time.perf_counter() - t):.0f} frames/s")
    c.collector.shutdown()
