"""Where the time of one fused AdaRL-SAC update goes (Hopper-v5, (w, w) networks, batch 256, one thread).

    PYTHONPATH=. python benchmarks/profile_update.py [--env Hopper-v5] [--width 64] [--updates 300] [--torch-profiler]

By default it times the parts of the update by wall clock: the manual step's passes (each network's forward and
backward, the TanhNormal sample and its backward, merging low-rank products), Adam, the rest. Why not only
torch.profiler: on this VM it inflates short element-wise kernels ~10x (a ReLU on a 2 x 256 x 64 tensor shows as
~70 us under the profiler against ~6 us timed alone), so its percentages overstate them. ``--torch-profiler``
prints its operator table as well.
"""

import argparse
import collections
import functools
import time

import torch

from adarl.fast import adam, manual_backward
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe

p = argparse.ArgumentParser()
p.add_argument("--env", default="Hopper-v5")
p.add_argument("--width", type=int, default=64)
p.add_argument("--updates", type=int, default=300)
p.add_argument("--torch-profiler", action="store_true")
a = p.parse_args()
torch.set_num_threads(1)
w = a.width
c = build_sac_components(
    load_recipe(
        "quickstart",
        [
            f"env.id={a.env}",
            "env.perturbation.preset=none",
            f"network.actor.num_cells=[{w},{w}]",
            f"network.critic.num_cells=[{w},{w}]",
        ],
    )
)
c.replay_buffer.extend(c.env.rollout(1000, break_when_any_done=False).reshape(-1))
update, sample = c.update.fused, c.update.sampler  # the run's FusedStep
if update.backward != "manual":
    raise SystemExit(f"this profile times the manual backward; the update uses {update.backward!r}")
for _ in range(30):
    update.step(*sample())

spent: dict[str, float] = collections.defaultdict(float)
name_of = {id(net): net.name for net in (update._manual.actor, update._manual.critic, update._manual.target)}


def timed(label, fn, net_arg=None):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        t = time.perf_counter()
        out = fn(*args, **kwargs)
        key = label if net_arg is None else f"{label} {net_arg(args)}"
        spent[key] += time.perf_counter() - t
        return out

    return wrapper


def layers_owner(args):  # forward/backward get prepared layers: name them by the first weight's key
    layers = args[0] if isinstance(args[0], list) else args[1]
    return next(layer.keys[0].split(":")[0] for layer in layers if layer.kind != "act")


manual_backward.forward = timed("forward", manual_backward.forward, layers_owner)
manual_backward.backward = timed("backward", manual_backward.backward, layers_owner)
manual_backward._Net.prepare = timed("merge low-rank products", manual_backward._Net.prepare)
step = update._manual
step._sample = timed("TanhNormal sample", step._sample)
step._sample_backward = timed("TanhNormal sample backward", step._sample_backward)
adam.DirectAdamStep.step = timed("Adam (3 optimisers)", adam.DirectAdamStep.step)
batches = [sample() for _ in range(a.updates)]
total = time.perf_counter()
for b in batches:
    update.step(*b)
total = time.perf_counter() - total
print(f"| part of one update, {a.env} ({w}, {w}) | ms | share |\n|---|---|---|")
for k, v in sorted(spent.items(), key=lambda kv: -kv[1]):
    print(f"| {k} | {1000 * v / a.updates:.3f} | {100 * v / total:.0f}% |")
rest = total - sum(spent.values())
print(
    f"| losses, targets, gradients into .grad, LR schedules, Polyak update | {1000 * rest / a.updates:.3f} | "
    f"{100 * rest / total:.0f}% |"
)
print(f"| **total** | **{1000 * total / a.updates:.3f}** | 100% |")
if a.torch_profiler:
    from torch.profiler import profile

    with profile() as prof:
        for b in batches[:100]:
            update.step(*b)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
