"""Why Tiwari et al.'s sparsification layer costs more on Ant and Humanoid: PyTorch's CPU ``topk`` on the layer's
1024 units, and where a fused update of a sparse recipe spends its time (docs/baselines/sparsification.md).

1. ``topk(k)`` on a batch x 1024 tensor for the layer's ``k + 1`` (Hopper 8, Walker2d 14, Ant 18, Humanoid 36) and
   around 16, where PyTorch's CPU kernel leaves its partial-heap path (``64 k <= n``) for ``nth_element``;
2. ``adarl.baselines.sparse.largest`` (what the layer selects with: numpy's ``argpartition`` beyond the heap's
   range), checked equal to one ``topk`` (values and units) on untied random data, beside it;
3. with ``--recipe``, fused updates of that recipe on real frames, the layer selecting by ``largest`` and by ``topk``
   alone (as before numpy's selection) in alternating windows in one process, and torch.profiler's operator table.

Each time is the best of three windows (one torch thread); on a busy machine compare the ratios.

    PYTHONPATH=. python benchmarks/sparse_topk.py [--rows 256] [--recipe recipes/baselines/humanoid_sparse.yaml]
"""

import argparse
import statistics
import time

import torch

from adarl.baselines import sparse
from adarl.baselines.sparse import largest


def best_us(fn, calls: int = 300) -> float:
    """The best of three windows of ``calls`` calls, in microseconds a call."""
    for _ in range(10):
        fn()
    windows = []
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(calls):
            fn()
        windows.append((time.perf_counter() - t) / calls * 1e6)
    return min(windows)


def profile_recipe(recipe: str, updates: int) -> None:
    from torch.profiler import ProfilerActivity, profile

    from adarl.runtime.config import load_recipe
    from adarl.runtime.families import family

    overrides = ["collector.total_frames=20000", "collector.init_random_frames=1000", "replay.size=5000"]
    rc = load_recipe(recipe, overrides)
    c = family(rc).build(rc)
    try:
        frames = iter(c.collector)
        while len(c.replay_buffer) < 1000:
            c.replay_buffer.extend(next(frames).reshape(-1))
        for _ in range(20):
            c.update(None)
        select = {"largest": sparse.largest, "topk": lambda x, m: x.topk(m, dim=-1)}
        ms = {name: [] for name in select}
        for _ in range(5):  # alternating windows: both selections see the same load
            for name, fn in select.items():
                sparse.largest = fn
                t = time.perf_counter()
                for _ in range(updates):
                    c.update(None)
                ms[name].append((time.perf_counter() - t) / updates * 1e3)
        sparse.largest = select["largest"]
        med = {name: statistics.median(v) for name, v in ms.items()}
        print(
            f"{recipe} ({type(c.update).__name__}), median of 5 windows of {updates} updates: "
            f"{med['largest']:.2f} ms an update selecting by largest, {med['topk']:.2f} by topk "
            f"({med['topk'] / med['largest']:.2f}x)"
        )
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(30):
                c.update(None)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))
    finally:
        c.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=256, help="the batch: rows of the 1024-unit pre-activation")
    p.add_argument("--recipe", default=None, help="also profile fused updates of this recipe")
    p.add_argument("--updates", type=int, default=100)
    a = p.parse_args()
    torch.set_num_threads(1)
    x = torch.randn(a.rows, 1024)
    print(f"topk on {a.rows} x 1024, one thread, best of three windows:")
    for k in (8, 14, 16, 17, 18, 36):
        v1, i1 = x.topk(k, dim=-1)
        v2, i2 = largest(x, k)
        assert torch.equal(v1, v2) and torch.equal(i1, i2), f"largest({k}) chose other units than topk"
        t_topk, t_largest = best_us(lambda k=k: x.topk(k, dim=-1)), best_us(lambda k=k: largest(x, k))
        print(f"  k = {k}: topk {t_topk:.0f} us, largest {t_largest:.0f} us ({t_topk / t_largest:.2f}x)")
    if a.recipe:
        profile_recipe(a.recipe, a.updates)


if __name__ == "__main__":
    main()
