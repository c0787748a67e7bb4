"""Profile one fused AdaRL-SAC update (Hopper-v5, (64, 64), batch 256, one thread): where the time goes.

    PYTHONPATH=. python benchmarks/profile_update.py
"""

import torch
from torch.profiler import profile

from adarl.config import load_recipe
from adarl.training import build_components

torch.set_num_threads(1)
c = build_components(load_recipe("quickstart"))
c.replay_buffer.extend(c.env.rollout(1000, break_when_any_done=False).reshape(-1))
update = c.extras["fused_update"]
for _ in range(50):
    update(c.replay_buffer.sample())
with profile() as prof:
    for _ in range(100):
        update(c.replay_buffer.sample())
print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
