"""Updates/s of one SAC update of the ``baselines/hopper_sparse`` recipe (Tiwari et al.'s sparsification layer:
1024 units, 7 active, in actor and critic; TorchRL's ``SACLoss`` path, as its runs train) with the layer's dense
and sparse forms (:mod:`adarl.baselines.sparse`), side by side in one process on the same components and replay
buffer.

The two forms alternate in short blocks, in ABBA order (dense, sparse, sparse, dense, ...), so that a change in the
machine's load between blocks falls on both alike; each adjacent pair gives one ratio, and the median ratio is the
answer. Time is this thread's CPU time (``time.thread_time``: what other processes of a busy machine take from the
wall clock is not counted, though their use of the shared caches and memory still is) and wall time.

    PYTHONPATH=. python benchmarks/sparse_speed.py [--recipe baselines/hopper_sparse] [--pairs 40] [--steps 5]
"""

import argparse
import statistics
import time
import warnings

import torch

from adarl.baselines.sparse import set_form
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.update import LossStep

p = argparse.ArgumentParser()
p.add_argument("--recipe", default="baselines/hopper_sparse")
p.add_argument("--pairs", type=int, default=40, help="dense/sparse block pairs")
p.add_argument("--steps", type=int, default=5, help="updates per block")
a = p.parse_args()

warnings.filterwarnings("ignore")  # TorchRL's notices (the target updater, collectors): not what is measured
OVR = ["collector.total_frames=20000", "collector.init_random_frames=1000", "replay.size=5000"]
c = build_sac_components(load_recipe(a.recipe, OVR))
torch.manual_seed(0)
c.replay_buffer.extend(c.env.rollout(2000, break_when_any_done=False).reshape(-1))
assert isinstance(c.update, LossStep), type(c.update)
nets = (c.modules.loss.actor_network, c.modules.loss.qvalue_network)
layers = set_form(nets, "sparse")
print(
    f"{a.recipe}: {layers} sparsification layers, batch {c.recipe.algorithm.batch_size}, "
    f"{torch.get_num_threads()} torch thread(s), {a.pairs} pairs of {a.steps}-update blocks"
)


def block(form: str) -> tuple[float, float]:
    """Updates/s of ``a.steps`` updates with every layer in ``form``: (CPU time, wall time)."""
    set_form(nets, form)
    c.update(update=0)  # the first update after a switch is not timed
    t_cpu, t_wall = time.thread_time(), time.perf_counter()
    for i in range(a.steps):
        c.update(update=i)
    return a.steps / (time.thread_time() - t_cpu), a.steps / (time.perf_counter() - t_wall)


rates = {"dense": [], "sparse": []}
for i in range(a.pairs):
    order = ("dense", "sparse") if i % 2 == 0 else ("sparse", "dense")
    for form in order:
        rates[form].append(block(form))
for j, what in enumerate(("CPU time", "wall time")):
    for form, r in rates.items():
        r = [x[j] for x in r]
        q = statistics.quantiles(r, n=4)
        print(f"{what:9s} {form:6s} updates/s median {statistics.median(r):6.1f}  (quartiles {q[0]:.1f}, {q[2]:.1f})")
    ratios = [s[j] / d[j] for s, d in zip(rates["sparse"], rates["dense"], strict=True)]
    q = statistics.quantiles(ratios, n=4)
    med = statistics.median(ratios)
    print(f"{what:9s} sparse / dense, per pair: median {med:.2f}x (quartiles {q[0]:.2f}, {q[2]:.2f})")
c.close()
