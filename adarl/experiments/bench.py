"""Side-by-side SAC speed benchmark: AdaRL-SAC (fused), the same without rank adaptation, stock TorchRL SAC, SB3.

Why: users pick the fastest correct tool, and rank adaptation must cost nothing noticeable. Every measurement
runs in its own subprocess (a clean peak-memory figure, no shared caches), the variants are interleaved and
repeated, and the report gives medians and the ratios between variants measured in the same invocation
(absolute numbers move with machine load; ratios much less).

Each variant does one gradient update per environment step, batch 256, with the same MLP sizes for actor and
critic, one torch thread unless told otherwise. ``adarl bench --help`` lists the options;
``python -m adarl.experiments.bench --worker ...`` is the per-measurement entry point the driver calls.

The driver itself never imports torch, TorchRL or the recipe runtime (they load inside :func:`measure`, in each
worker process): its caches and peak memory stay out of the measurements, and ``adarl --help`` builds the bench
options from this module without them.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from adarl.errors import AdaRLValueError

__all__ = ["VARIANTS", "run_benchmark", "measure", "rank_event_seconds", "format_table", "main"]

VARIANTS = ("adarl", "adarl_compiled", "adarl_process", "adarl_thread", "adarl_norank", "torchrl", "sb3")
#: our loops, compared with the baselines
OURS = ("adarl", "adarl_compiled", "adarl_process", "adarl_thread")
BASELINES = ("torchrl", "sb3")


def _sb3_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("stable_baselines3") is not None


def _recipe(
    env_id: str,
    width: int,
    variant: str,
    warmup: int,
    total: int,
    rank_interval: int,
    batch: int,
    extra: tuple[str, ...] = (),
):
    from adarl.runtime.config import load_recipe

    ov = [
        f"env.id={env_id}",
        "env.perturbation.preset=none",
        f"collector.total_frames={total}",
        f"collector.init_random_frames={warmup}",
        "collector.frames_per_batch=50",
        f"replay.size={max(total, batch)}",
        f"algorithm.batch_size={batch}",
        f"network.actor.num_cells=[{width},{width}]",
        f"network.critic.num_cells=[{width},{width}]",
        "replay.warm_start.frames=0",
    ]
    if variant in ("adarl", "adarl_process", "adarl_thread"):
        ov += [f"rank.interval={rank_interval}", "algorithm.fused=true"]
        if variant != "adarl":  # collection in a worker process / a background thread, one batch staler
            ov += [f"collector.overlap={variant.removeprefix('adarl_')}"]
    elif variant == "adarl_compiled":  # its rank events (each recompiles) are timed after the window
        ov += [f"rank.interval={10**9}", "algorithm.fused=true", "algorithm.compile=true"]
    elif variant == "adarl_norank":
        ov += ["rank.enabled=false", "algorithm.fused=true"]
    else:  # stock TorchRL: plain MLPs, SACLoss, for-loop Adam, SoftUpdate (TorchRL's reference SAC recipe)
        ov += [
            "rank.enabled=false",
            "algorithm.fused=false",
            "network.actor.low_rank_layers=[]",
            "network.critic.low_rank_layers=[]",
        ]
    return load_recipe("base", ov + list(extra))


def _measure_torchrl(variant, env_id, width, warmup, steps, skip, batch, rank_interval, overrides=()) -> dict:
    import torch

    from adarl.runtime.builders.sac import build_components

    total = warmup + skip + steps
    extra = tuple(overrides) if variant.startswith("adarl") else ()  # --set applies to our loops only
    c = build_components(_recipe(env_id, width, variant, warmup, total, rank_interval, batch, extra))
    event_s: list[float] = []

    def update():
        c.update()  # the run's update step: the fused one, or TorchRL's SACLoss + Adam + SoftUpdate (torchrl)
        if c.adapter is not None:
            n = len(c.adapter.history)
            t = time.perf_counter()
            c.adapter.step()
            if len(c.adapter.history) > n:
                event_s.append(time.perf_counter() - t)

    frames = updates = 0
    t0 = None
    for batch_td in c.collector:
        batch_td = batch_td.reshape(-1)
        c.replay_buffer.extend(batch_td)
        frames += batch_td.numel()
        if frames > warmup:
            for _ in range(batch_td.numel()):
                update()
                updates += 1
                if updates == skip:
                    t0, f0 = time.perf_counter(), frames
        if t0 is not None and updates >= skip + steps:
            break
    wall = time.perf_counter() - t0
    if variant == "adarl_compiled":
        # A rank event recompiles the update (at its first call afterwards): time two events, each with the update
        # that recompiles, less one update of the window's mean duration, as the others' events are timed.
        per_update = wall / (updates - skip)
        for _ in range(2):
            t = time.perf_counter()
            c.adapter.adapt()
            update()
            event_s.append(time.perf_counter() - t - per_update)
    c.collector.shutdown()  # joins a collector worker process, so its peak memory is counted below
    del torch
    return {
        "updates_per_s": (updates - skip) / wall,
        "env_steps_per_s": (frames - f0) / wall,
        "rank_event_s": event_s,
        "rank_events": len(event_s),
    }


def _measure_sb3(env_id, width, warmup, steps, skip, batch) -> dict:
    import gymnasium as gym
    from stable_baselines3 import SAC

    env = gym.make(env_id)
    model = SAC(
        "MlpPolicy",
        env,
        batch_size=batch,
        learning_starts=warmup,
        train_freq=1,
        gradient_steps=1,
        buffer_size=warmup + skip + steps + 10,
        policy_kwargs={"net_arch": [width, width]},
        device="cpu",
        learning_rate=3e-3,
        seed=0,
        verbose=0,
    )
    model.learn(total_timesteps=warmup + skip)
    t = time.perf_counter()
    model.learn(total_timesteps=steps, reset_num_timesteps=False)
    wall = time.perf_counter() - t
    return {"updates_per_s": steps / wall, "env_steps_per_s": steps / wall, "rank_event_s": [], "rank_events": 0}


def measure(
    variant: str,
    env_id: str,
    width: int,
    *,
    warmup: int = 1000,
    steps: int = 1000,
    skip: int = 100,
    batch: int = 256,
    threads: int = 1,
    rank_interval: int = 400,
    overrides: tuple[str, ...] = (),
) -> dict:
    """One measurement in this process: updates/s and env steps/s over ``steps`` updates after warm-up.

    ``overrides`` are recipe overrides for the adarl variants (e.g. ``network.actor.rank=64``)."""
    import torch

    torch.set_num_threads(threads)
    if variant == "sb3":
        out = _measure_sb3(env_id, width, warmup, steps, skip, batch)
    else:
        out = _measure_torchrl(variant, env_id, width, warmup, steps, skip, batch, rank_interval, overrides)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # a collector worker process (adarl_process): its own peak, reported beside the trainer's
    out["worker_peak_rss_mb"] = (
        resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024 if variant == "adarl_process" else 0.0
    )
    return out


def rank_event_seconds(width: int, *, repeats: int = 3, threads: int = 1, event_threads: int | None = None) -> float:
    """Median wall time of one rank event on an actor and a twin critic with two ``width``-wide low-rank layers.

    ``threads`` is the loop's torch thread count, ``event_threads`` the recipe's ``rank.num_threads``."""
    import torch

    from adarl.runtime.builders.sac import build_components

    torch.set_num_threads(threads)
    extra = () if event_threads is None else (f"rank.num_threads={event_threads}",)
    times = []
    for _ in range(repeats):
        r = _recipe("Hopper-v5", width, "adarl", 10, 100, 10**9, 8, extra)
        c = build_components(r)
        t = time.perf_counter()
        c.adapter.adapt()
        times.append(time.perf_counter() - t)
        c.collector.shutdown()
    return statistics.median(times)


def _worker(args) -> int:
    os.environ.setdefault("RL_WARNINGS", "False")
    import warnings

    warnings.filterwarnings("ignore")
    out = measure(
        args.variant,
        args.env,
        args.width,
        warmup=args.warmup,
        steps=args.steps,
        skip=args.skip,
        batch=args.batch,
        threads=args.threads,
        rank_interval=args.rank_interval,
        overrides=tuple(args.set),
    )
    print("ADARL_BENCH " + json.dumps(out))
    return 0


def _spawn(variant, env_id, width, a) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "adarl.experiments.bench",
        "--worker",
        "--variant",
        variant,
        "--env",
        env_id,
        "--width",
        str(width),
        "--warmup",
        str(a.warmup),
        "--steps",
        str(a.steps),
        "--skip",
        str(a.skip),
        "--batch",
        str(a.batch),
        "--threads",
        str(a.threads),
        "--rank-interval",
        str(a.rank_interval),
        "--set",
        *a.set,
    ]
    with tempfile.TemporaryDirectory(prefix="adarl-bench-inductor-") as cache:
        # a fresh inductor cache: every compilation is cold, as each rank event's new shapes are in a real run
        env = dict(
            os.environ, OMP_NUM_THREADS=str(a.threads), MKL_NUM_THREADS=str(a.threads), TORCHINDUCTOR_CACHE_DIR=cache
        )
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    for line in proc.stdout.splitlines():
        if line.startswith("ADARL_BENCH "):
            return json.loads(line[len("ADARL_BENCH ") :])
    raise RuntimeError(f"benchmark worker {variant} {env_id} {width} failed:\n{proc.stderr[-2000:]}")


def run_benchmark(a) -> dict:
    """Interleave variants x repeats for each (env, width); return medians, ratios and the raw runs."""
    variants = [v for v in a.variants if v != "sb3" or _sb3_available()]
    skipped = [v for v in a.variants if v not in variants]
    results = []
    for env_id in a.envs:
        for width in a.widths:
            runs: dict[str, list[dict]] = {v: [] for v in variants}
            for rep in range(a.repeats):
                order = variants if rep % 2 == 0 else list(reversed(variants))  # interleaved, order alternates
                for v in order:
                    runs[v].append(_spawn(v, env_id, width, a))
                    if not a.quiet:
                        print(
                            f"  {env_id} ({width},{width}) {v} #{rep + 1}: "
                            f"{runs[v][-1]['updates_per_s']:.1f} updates/s",
                            file=sys.stderr,
                            flush=True,
                        )
            row = {"env": env_id, "width": width, "variants": {}}
            for v, rs in runs.items():
                events = [t for r in rs for t in r["rank_event_s"]]
                row["variants"][v] = {
                    "updates_per_s": statistics.median(r["updates_per_s"] for r in rs),
                    "env_steps_per_s": statistics.median(r["env_steps_per_s"] for r in rs),
                    "peak_rss_mb": statistics.median(r["peak_rss_mb"] for r in rs),
                    "worker_peak_rss_mb": statistics.median(r.get("worker_peak_rss_mb", 0.0) for r in rs),
                    "rank_event_ms": 1000 * statistics.median(events) if events else None,
                    "runs": rs,
                }
            ups = {v: d["updates_per_s"] for v, d in row["variants"].items()}
            row["ratios"] = {f"adarl/{v}": ups["adarl"] / ups[v] for v in ups if v != "adarl" and "adarl" in ups}
            for ours in OURS[1:]:  # the compiled and overlapped loops against the baselines too
                row["ratios"].update({f"{ours}/{v}": ups[ours] / ups[v] for v in BASELINES if ours in ups and v in ups})
            for v, d in row["variants"].items():  # share of wall time at the paper's interval of 1e6 updates
                if d["rank_event_ms"] is not None:
                    d["rank_overhead_at_paper_interval"] = (d["rank_event_ms"] / 1000) / (1e6 / ups[v])
            if "rank_overhead_at_paper_interval" in row["variants"].get("adarl", {}):
                row["rank_overhead_at_paper_interval"] = row["variants"]["adarl"]["rank_overhead_at_paper_interval"]
            results.append(row)
    # one rank event stand-alone, at the loop's thread count and (rank.num_threads) with every core
    thread_counts = sorted({a.threads, os.cpu_count() or 1})
    events = [
        {"width": w, "threads": t, "ms": 1000 * rank_event_seconds(w, threads=a.threads, event_threads=t)}
        for w in a.event_widths
        for t in thread_counts
    ]
    return {
        "settings": {k: v for k, v in vars(a).items() if k not in ("func",)},
        "skipped": skipped,
        "results": results,
        "rank_events_standalone": events,
        "machine": {"cpus": os.cpu_count(), "load_avg": os.getloadavg()},
    }


def format_table(report: dict) -> str:
    lines = [
        "| env | size | variant | updates/s | env steps/s | peak RSS (MB) | rank event (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in report["results"]:
        for v, d in row["variants"].items():
            ev = "-" if d["rank_event_ms"] is None else f"{d['rank_event_ms']:.1f}"
            rss = f"{d['peak_rss_mb']:.0f}"
            if d.get("worker_peak_rss_mb"):
                rss += f" + {d['worker_peak_rss_mb']:.0f} (worker)"
            lines.append(
                f"| {row['env']} | ({row['width']}, {row['width']}) | {v} | {d['updates_per_s']:.1f} | "
                f"{d['env_steps_per_s']:.1f} | {rss} | {ev} |"
            )
    lines += ["", "| env | size | ratio | value |", "|---|---|---|---|"]
    for row in report["results"]:
        for k, val in row["ratios"].items():
            lines.append(f"| {row['env']} | ({row['width']}, {row['width']}) | updates/s {k} | {val:.2f}x |")
        shares = {
            v: d["rank_overhead_at_paper_interval"]
            for v, d in row["variants"].items()
            if d.get("rank_overhead_at_paper_interval") is not None
        }
        if not shares and "rank_overhead_at_paper_interval" in row:
            shares = {"adarl": row["rank_overhead_at_paper_interval"]}
        for v, share in shares.items():
            lines.append(
                f"| {row['env']} | ({row['width']}, {row['width']}) | rank-event share of wall time at "
                f"interval 1e6, {v} | {100 * share:.5f}% |"
            )
    lines += ["", "| layer width | torch threads | one rank event, actor + 2 critics (ms) |", "|---|---|---|"]
    lines += [f"| {e['width']} | {e['threads']} | {e['ms']:.1f} |" for e in report["rank_events_standalone"]]
    if report["skipped"]:
        lines += ["", f"skipped (not installed): {', '.join(report['skipped'])}"]
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--envs", nargs="+", default=["Hopper-v5"], help="gymnasium env ids (e.g. Hopper-v5 Humanoid-v5)")
    p.add_argument("--widths", nargs="+", type=int, default=[64, 256], help="hidden width w of (w, w) MLPs")
    p.add_argument(
        "--variants",
        nargs="+",
        default=list(VARIANTS),
        choices=VARIANTS,
        help="adarl (fused, rank adaptation on), adarl_compiled (the same with algorithm.compile; its "
        "rank events, each a recompilation, are timed after the window), adarl_process / adarl_thread "
        "(collector.overlap: process / thread), adarl_norank, torchrl (stock SACLoss loop), sb3",
    )
    p.add_argument("--repeats", type=int, default=3, help="repeats per variant (the median is reported)")
    p.add_argument("--steps", type=int, default=1000, help="timed updates per measurement")
    p.add_argument("--warmup", type=int, default=1000, help="random-action frames before updates start")
    p.add_argument("--skip", type=int, default=100, help="untimed updates before the timed window")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--threads", type=int, default=1, help="torch threads per measurement")
    p.add_argument(
        "--rank-interval",
        type=int,
        default=400,
        help="adarl variant: updates between rank events (to time events inside the window)",
    )
    p.add_argument(
        "--event-widths",
        nargs="*",
        type=int,
        default=[64, 1024],
        help="layer widths for the stand-alone rank-event timing",
    )
    p.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="recipe overrides for the adarl variants, e.g. network.actor.rank=64 network.critic.rank=64 "
        "to time the loop at the ranks a truncation leaves",
    )
    p.add_argument("--output", default="bench.json", help="JSON report path")
    p.add_argument("--quiet", action="store_true")


def cli(a) -> int:
    for name in ("repeats", "steps", "warmup", "batch", "threads", "rank_interval"):
        if getattr(a, name) < 1:
            raise AdaRLValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    for env_id in a.envs if a.set else ():  # a bad override fails here, with the recipe's error, before measuring
        for width in a.widths:
            _recipe(
                env_id, width, "adarl", a.warmup, a.warmup + a.skip + a.steps, a.rank_interval, a.batch, tuple(a.set)
            )
    report = run_benchmark(a)
    Path(a.output).write_text(json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    print(f"\nJSON report: {a.output}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m adarl.experiments.bench", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--variant", choices=VARIANTS, help=argparse.SUPPRESS)
    p.add_argument("--env", help=argparse.SUPPRESS)
    p.add_argument("--width", type=int, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    return _worker(a) if a.worker else cli(a)


if __name__ == "__main__":
    sys.exit(main())
