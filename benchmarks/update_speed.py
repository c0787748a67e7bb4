"""Updates/s of one SAC step alone (no env): stock SACLoss + Adam + SoftUpdate vs the fused update (autograd or
hand-written backward), eager and compiled, interleaved and repeated in one process (Hopper-v5 sizes, batch 256,
one thread).

    PYTHONPATH=. python benchmarks/update_speed.py [--width 64] [--repeats 3] [--steps 300] [--no-compile]
"""

import argparse
import statistics
import time

import torch

from adarl.fast.adam import make_adam
from adarl.fast.sac import FusedSACUpdate
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe

p = argparse.ArgumentParser()
p.add_argument("--width", type=int, default=64)
p.add_argument("--repeats", type=int, default=3)
p.add_argument("--steps", type=int, default=300)
p.add_argument("--no-compile", action="store_true")
a = p.parse_args()
torch.set_num_threads(1)
w = a.width
c = build_sac_components(
    load_recipe(
        "quickstart",
        ["algorithm.fused=false", f"network.actor.num_cells=[{w},{w}]", f"network.critic.num_cells=[{w},{w}]"],
    )
)
c.replay_buffer.extend(c.env.rollout(1000, break_when_any_done=False).reshape(-1))
loss = c.modules.loss


def stock():
    td = loss(c.replay_buffer.sample())
    (td["loss_actor"] + td["loss_qvalue"] + td["loss_alpha"]).backward()
    for opt in c.optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    c.modules.target_updater.step()


def adams(fused):
    return [make_adam(o.param_groups[0]["params"], o.param_groups[0]["lr"], fused=fused) for o in c.optimizers.values()]


def fused(**kw):
    f = FusedSACUpdate(loss, adams(kw.pop("fused_adam", True)), tau=0.005, **kw)
    return lambda: f(c.replay_buffer.sample())


variants = {
    "stock SACLoss + Adam + SoftUpdate": stock,
    "fused update (autograd), for-loop Adam": fused(fused_adam=False, backward="autograd"),
    "fused update (autograd) + fused Adam": fused(backward="autograd"),
    "fused update (manual backward) + fused Adam": fused(backward="manual"),
}
if not a.no_compile:
    for backward in ("autograd", "manual"):
        comp = FusedSACUpdate(loss, adams(True), tau=0.005, compile=True, backward=backward)
        t = time.perf_counter()
        comp(c.replay_buffer.sample())
        print(f"torch.compile of the fused update ({backward}): {time.perf_counter() - t:.1f} s")
        variants[f"fused update ({backward}) + fused Adam, torch.compile"] = (
            lambda f: lambda: f(c.replay_buffer.sample())
        )(comp)
rates = {k: [] for k in variants}
for _rep in range(a.repeats):
    for k, f in variants.items():
        for _ in range(20):
            f()
        t = time.perf_counter()
        for _ in range(a.steps):
            f()
        rates[k].append(a.steps / (time.perf_counter() - t))
base = statistics.median(rates["stock SACLoss + Adam + SoftUpdate"])
print(f"| update path, ({w}, {w}) | updates/s (median of {a.repeats}) | vs stock |\n|---|---|---|")
for k, r in rates.items():
    print(f"| {k} | {statistics.median(r):.1f} | {statistics.median(r) / base:.2f}x |")
