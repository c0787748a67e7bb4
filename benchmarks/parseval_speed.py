"""Updates/s of a Parseval SAC step (the ``baselines/hopper_parseval`` recipe's networks, batch 256, one thread):
TorchRL's ``SACLoss`` path with the term (``algorithm.fused=false``, what every Parseval run used before) against
the fused update that adds the parameter-only term itself (``algorithm.fused=auto``), interleaved and repeated in
one process so the ratio is measured side by side.

    PYTHONPATH=. python benchmarks/parseval_speed.py [--repeats 5] [--steps 300]
"""

import argparse
import statistics
import time

import torch

from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.update import FusedStep, LossStep

p = argparse.ArgumentParser()
p.add_argument("--repeats", type=int, default=5)
p.add_argument("--steps", type=int, default=300)
a = p.parse_args()
torch.set_num_threads(1)

OVR = ["collector.total_frames=20000", "collector.init_random_frames=1000", "replay.size=5000"]
paths = {}
for name, fused in (("torchrl", "false"), ("fused", "auto")):
    c = build_sac_components(load_recipe("baselines/hopper_parseval", [*OVR, f"algorithm.fused={fused}"]))
    c.replay_buffer.extend(c.env.rollout(2000, break_when_any_done=False).reshape(-1))
    assert isinstance(c.update, LossStep if fused == "false" else FusedStep), type(c.update)
    paths[name] = c

rates = {name: [] for name in paths}
for _ in range(a.repeats):
    for name, c in paths.items():
        c.update()  # warm
        t = time.perf_counter()
        for _ in range(a.steps):
            out = c.update()
        rates[name].append(a.steps / (time.perf_counter() - t))
        assert "loss_parseval" in out
for name, r in rates.items():
    print(f"{name:8s} updates/s median {statistics.median(r):7.1f}  (min {min(r):.1f}, max {max(r):.1f})")
ratios = [f / s for f, s in zip(rates["fused"], rates["torchrl"], strict=True)]
print(f"fused / torchrl: median {statistics.median(ratios):.2f}x (min {min(ratios):.2f}, max {max(ratios):.2f})")
for c in paths.values():
    c.close()
