"""Why Tiwari et al.'s sparsification layer costs more on Ant and Humanoid: PyTorch's CPU ``topk`` on the layer's
1024 units, and where a fused update of a sparse recipe spends its time (docs/baselines/sparsification.md).

1. ``topk(k)`` on a batch x 1024 tensor for the layer's ``k + 1`` (Hopper 8, Walker2d 14, Ant 18, Humanoid 36) and
   around 16, where PyTorch's CPU kernel leaves its partial-heap path (``64 k <= n``) for ``nth_element``;
2. the same winners from rounds of ``topk(<= 16)``, each round's winners masked to ``-inf`` (checked equal to one
   ``topk`` on untied random data), beside one ``topk``;
3. with ``--recipe``, torch.profiler's operator table over fused updates of that recipe on real frames.

Each time is the best of three windows (one torch thread); on a busy machine compare the ratios.

    PYTHONPATH=. python benchmarks/sparse_topk.py [--rows 256] [--recipe recipes/baselines/humanoid_sparse.yaml]
"""

import argparse
import time

import torch


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


def topk_in_rounds(x: torch.Tensor, k: int, step: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` largest of each row from rounds of ``topk(<= step)``, each round's winners masked before the next."""
    y, values, indices = x.clone(), [], []
    while k > 0:
        v, i = y.topk(min(step, k), dim=-1)
        values.append(v)
        indices.append(i)
        y.scatter_(-1, i, float("-inf"))
        k -= v.shape[-1]
    return torch.cat(values, -1), torch.cat(indices, -1)


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
        t = time.perf_counter()
        for _ in range(updates):
            c.update(None)
        print(f"{recipe}: {(time.perf_counter() - t) / updates * 1e3:.2f} ms an update ({type(c.update).__name__})")
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
        line = f"  topk({k}): {best_us(lambda k=k: x.topk(k, dim=-1)):.0f} us"
        if k > 16:
            v1, i1 = x.topk(k, dim=-1)
            v2, i2 = topk_in_rounds(x, k)
            assert torch.equal(v1, v2) and torch.equal(i1, i2), "rounds of topk(<= 16) chose other winners"
            line += f"; in rounds of topk(<= 16): {best_us(lambda k=k: topk_in_rounds(x, k)):.0f} us"
        print(line)
    if a.recipe:
        profile_recipe(a.recipe, a.updates)


if __name__ == "__main__":
    main()
