"""Profile fused AdaRL-SAC updates (Hopper-v5, (w, w) networks, batch 256, one thread): where the time goes.

    PYTHONPATH=. python benchmarks/profile_update.py [--width 64] [--updates 100]
"""

import argparse

import torch
from torch.profiler import profile

from adarl.config import load_recipe
from adarl.training import build_components

p = argparse.ArgumentParser()
p.add_argument("--width", type=int, default=64)
p.add_argument("--updates", type=int, default=100)
a = p.parse_args()
torch.set_num_threads(1)
w = a.width
c = build_components(load_recipe("quickstart", [f"network.actor.num_cells=[{w},{w}]",
                                                f"network.critic.num_cells=[{w},{w}]"]))
c.replay_buffer.extend(c.env.rollout(1000, break_when_any_done=False).reshape(-1))
update, sample = c.extras["fused_update"], c.extras["fused_sampler"]
for _ in range(30):
    update.step(*sample())
with profile() as prof:
    for _ in range(a.updates):
        update.step(*sample())
print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
