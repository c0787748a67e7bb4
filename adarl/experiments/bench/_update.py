"""Side-by-side SAC speed benchmark: AdaRL-SAC (fused), the same without rank adaptation, stock TorchRL SAC, SB3.

Why: users pick the fastest correct tool, and rank adaptation must cost nothing noticeable. Every measurement
runs in its own subprocess (a clean peak-memory figure, no shared caches), the variants are interleaved and
repeated, and the report gives medians and the ratios between variants measured in the same invocation
(absolute numbers move with machine load; ratios much less).

Each variant does one gradient update per environment step, batch 256, with the same MLP sizes for actor and
critic, one torch thread unless told otherwise. ``adarl bench --help`` lists the options;
``python -m adarl.experiments.bench --worker ...`` is the per-measurement entry point the driver calls.

``adarl bench --whole-run`` times whole runs instead, process start to exit, against SB3 SAC
(:mod:`adarl.experiments.bench._whole_run`, the driver); its SB3 run (:func:`whole_run_sb3`) and the act()
latencies of ``--inference`` (:func:`act_latency`) run here, in worker processes
(``--whole-run-worker sb3``, ``--act-latency-worker``).

The driver itself never imports torch, TorchRL or the recipe runtime (they load inside :func:`measure`, in each
worker process): its caches and peak memory stay out of the measurements, and ``adarl --help`` builds the bench
options from this module without them.

Long because: the driver and the worker entry points it starts (``--worker``, ``--whole-run-worker``,
``--act-latency-worker``) are one command line, ``python -m adarl.experiments.bench``, sharing its option parser.
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

__all__ = [
    "VARIANTS",
    "interleave",
    "run_benchmark",
    "measure",
    "rank_event_seconds",
    "format_table",
    "whole_run_sb3",
    "act_latency",
    "main",
]

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

    from adarl.runtime.builders.sac import build_sac_components

    total = warmup + skip + steps
    extra = tuple(overrides) if variant.startswith("adarl") else ()  # --set applies to our loops only
    c = build_sac_components(_recipe(env_id, width, variant, warmup, total, rank_interval, batch, extra))
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

    from adarl.runtime.builders.sac import build_sac_components

    torch.set_num_threads(threads)
    extra = () if event_threads is None else (f"rank.num_threads={event_threads}",)
    times = []
    for _ in range(repeats):
        r = _recipe("Hopper-v5", width, "adarl", 10, 100, 10**9, 8, extra)
        c = build_sac_components(r)
        t = time.perf_counter()
        c.adapter.adapt()
        times.append(time.perf_counter() - t)
        c.collector.shutdown()
    return statistics.median(times)


def whole_run_sb3(
    env_id: str,
    width: int,
    *,
    frames: int,
    warmup: int,
    batch: int = 256,
    threads: int = 1,
    eval_interval: int,
    eval_episodes: int,
) -> dict:
    """One Stable-Baselines3 SAC run as ``adarl bench --whole-run`` times it (the driver times the process, from
    its start to its exit; this returns what the run did, and ``loop_s``, the time inside ``learn()`` and the
    final evaluation).

    The settings of :func:`measure`'s sb3 variant: ``net_arch=[w, w]``, ``batch``, ``learning_starts=warmup``,
    one gradient step per env step, a buffer of every frame, lr 3e-3, the entropy coefficient learnt from 1.0 (as
    the quickstart recipe). An ``EvalCallback`` evaluates deterministically every ``eval_interval`` frames for
    ``eval_episodes`` episodes, and once more at the end when the frames are not a multiple of the interval (as
    adarl's trainer does)."""
    import torch

    torch.set_num_threads(threads)
    import gymnasium as gym
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor

    class CountingEval(EvalCallback):
        evals, last, last_mean = 0, -1, None

        def _on_step(self) -> bool:
            due = self.eval_freq > 0 and self.n_calls % self.eval_freq == 0
            out = super()._on_step()
            if due:
                self.evals, self.last, self.last_mean = self.evals + 1, self.num_timesteps, float(self.last_mean_reward)
            return out

    model = SAC(
        "MlpPolicy",
        gym.make(env_id),
        batch_size=batch,
        learning_starts=warmup,
        train_freq=1,
        gradient_steps=1,
        buffer_size=frames,
        policy_kwargs={"net_arch": [width, width]},
        device="cpu",
        learning_rate=3e-3,
        seed=0,
        verbose=0,
    )
    cb = CountingEval(
        Monitor(gym.make(env_id)), eval_freq=eval_interval, n_eval_episodes=eval_episodes, deterministic=True
    )
    t = time.perf_counter()
    model.learn(total_timesteps=frames, callback=cb)
    if cb.last != model.num_timesteps:
        mean, _ = evaluate_policy(model, cb.eval_env, n_eval_episodes=eval_episodes, deterministic=True)
        cb.evals, cb.last_mean = cb.evals + 1, float(mean)
    return {
        "loop_s": time.perf_counter() - t,
        "frames": int(model.num_timesteps),
        "updates": int(model._n_updates),
        "evals": cb.evals,
        "eval_episodes": cb.evals * eval_episodes,
        "final_eval_mean": cb.last_mean,
    }


def act_latency(env_id: str, width: int, *, rank: int = 7, calls: int = 2000) -> list[dict]:
    """Median act() latency at batch 1, one thread, ``torch.no_grad``, of three ``(width, width)`` SAC actors
    built as the quickstart recipe builds them: plain ``nn.Linear`` layers (what a full-rank SAC deploys), the
    recipe's low-rank layers at full rank (AdaRL before its first rank event), and the same truncated to ``rank``
    (each layer to at most its own largest rank).

    ``act_us``: the deployed call, ``actor(TensorDict(observation=obs))`` with the deterministic action (what
    :func:`adarl.load_policy` returns); ``network_us``: the MLP alone on the observation tensor and ``tanh`` of
    its mean. The actors' calls are interleaved in rounds; the median over ``calls`` calls each."""
    import copy

    import gymnasium as gym
    import torch
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type
    from torchrl.modules import MLP

    from adarl.core.lowrank import iter_low_rank
    from adarl.runtime.builders.common import spec_env
    from adarl.runtime.builders.sac import make_recipe_actor
    from adarl.runtime.config import load_recipe

    torch.set_num_threads(1)
    env = gym.make(env_id)
    obs_dim, act_dim = int(env.observation_space.shape[-1]), int(env.action_space.shape[-1])
    specs = {
        "observation_dim": obs_dim,
        "action_kind": "box",
        "action_low": torch.as_tensor(env.action_space.low, dtype=torch.float32),
        "action_high": torch.as_tensor(env.action_space.high, dtype=torch.float32),
    }
    env.close()
    cells = [f"network.actor.num_cells=[{width},{width}]"]

    def build(extra):
        torch.manual_seed(0)
        return make_recipe_actor(load_recipe("quickstart", cells + extra), spec_env(specs, "cpu"))

    low_rank = build([])
    truncated = copy.deepcopy(low_rank)
    for _, layer in iter_low_rank(truncated):
        layer.truncate_(min(rank, layer.rank))
    actors = {
        "dense (nn.Linear)": build(["network.actor.low_rank_layers=[]", "rank.enabled=false"]),
        "low-rank, full rank": low_rank,
        f"low-rank, rank <= {rank}": truncated,
    }
    obs = torch.randn(obs_dim)
    act_us: dict[str, list[float]] = {k: [] for k in actors}
    net_us: dict[str, list[float]] = {k: [] for k in actors}
    rounds = 10
    per_round = max(1, calls // rounds)
    clock = time.perf_counter_ns
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        nets = {}
        for name, actor in actors.items():
            actor.eval().requires_grad_(False)
            nets[name] = next(m for m in actor.modules() if isinstance(m, MLP))
            for _ in range(50):  # warm-up
                actor(TensorDict(observation=obs))
                torch.tanh(nets[name](obs)[..., :act_dim])
        for _ in range(rounds):
            for name, actor in actors.items():
                net = nets[name]
                for _ in range(per_round):
                    t = clock()
                    actor(TensorDict(observation=obs))
                    act_us[name].append((clock() - t) / 1000)
                for _ in range(per_round):
                    t = clock()
                    torch.tanh(net(obs)[..., :act_dim])
                    net_us[name].append((clock() - t) / 1000)
    return [
        {
            "actor": name,
            "ranks": "/".join(str(layer.rank) for _, layer in iter_low_rank(actor)) or "dense",
            "parameters": sum(p.numel() for p in actor.parameters()),
            "act_us": statistics.median(act_us[name]),
            "network_us": statistics.median(net_us[name]),
            "calls": len(act_us[name]),
        }
        for name, actor in actors.items()
    ]


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


def _whole_run_worker(args) -> int:
    import warnings

    warnings.filterwarnings("ignore")
    out = whole_run_sb3(
        args.env,
        args.width,
        frames=args.frames,
        warmup=args.warmup,
        batch=args.batch,
        threads=args.threads,
        eval_interval=args.eval_interval,
        eval_episodes=args.eval_episodes,
    )
    print("ADARL_WHOLE_RUN " + json.dumps(out))
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


def interleave(variants: list[str], repeats: int, run, report=None) -> dict[str, list[dict]]:
    """``run(variant)`` for every variant, ``repeats`` times, interleaved with the order reversed on every other
    repeat (a slow drift of the machine's load falls on every variant alike); ``report(variant, repeat, result)``
    after each."""
    runs: dict[str, list[dict]] = {v: [] for v in variants}
    for rep in range(repeats):
        for v in variants if rep % 2 == 0 else list(reversed(variants)):
            runs[v].append(run(v))
            if report is not None:
                report(v, rep, runs[v][-1])
    return runs


def run_benchmark(a) -> dict:
    """Interleave variants x repeats for each (env, width); return medians, ratios and the raw runs."""
    variants = [v for v in a.variants if v != "sb3" or _sb3_available()]
    skipped = [v for v in a.variants if v not in variants]
    results = []
    for env_id in a.envs:
        for width in a.widths:
            runs = interleave(
                variants,
                a.repeats,
                lambda v, env_id=env_id, width=width: _spawn(v, env_id, width, a),
                None
                if a.quiet
                else lambda v, rep, r, env_id=env_id, width=width: print(
                    f"  {env_id} ({width},{width}) {v} #{rep + 1}: {r['updates_per_s']:.1f} updates/s",
                    file=sys.stderr,
                    flush=True,
                ),
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
        default=None,
        choices=VARIANTS,
        help="adarl (fused, rank adaptation on), adarl_compiled (the same with algorithm.compile; its "
        "rank events, each a recompilation, are timed after the window), adarl_process / adarl_thread "
        "(collector.overlap: process / thread), adarl_norank, torchrl (stock SACLoss loop), sb3 (default: all; "
        "--whole-run: adarl adarl_norank torchrl sb3, the only ones it runs)",
    )
    p.add_argument("--repeats", type=int, default=3, help="repeats per variant (the median is reported)")
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="timed updates per measurement (default: 1000; --pack: 200 a seed per timed window)",
    )
    p.add_argument(
        "--warmup",
        type=int,
        default=None,
        help="random-action frames before updates start (default: 1000; --whole-run: 5000, the quickstart recipe's; "
        "--pack: the frames each seed's replay holds, default 1000; --pack --whole-run: --frames // 6)",
    )
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
    p.add_argument(
        "--output", default=None, help="JSON report path (default: bench.json; --whole-run: bench_whole_run.json)"
    )
    p.add_argument("--quiet", action="store_true")
    w = p.add_argument_group(
        "whole runs (--whole-run)",
        "Whole training runs timed from process start to exit, each in a fresh process: adarl (the quickstart "
        "recipe with its rank events scaled), adarl_norank, torchrl (TorchRL's stock path in adarl's trainer) and "
        "sb3 (Stable-Baselines3 SAC with an EvalCallback), same env, frames, update ratio, batch, widths, threads "
        "and evaluations. --envs, --widths, --variants, --repeats, --warmup, --batch, --threads, --set and "
        "--output apply too.",
    )
    w.add_argument("--whole-run", action="store_true", help="time whole runs end to end (docs/performance.md)")
    w.add_argument(
        "--frames", type=int, default=None, help="env frames of each run (default: 12000; --pack --whole-run: 6000)"
    )
    w.add_argument(
        "--frames-per-batch",
        type=int,
        default=250,
        help="adarl's collector batch (the quickstart recipe's 250); --frames, --warmup and --eval-interval "
        "must be multiples of it",
    )
    w.add_argument("--eval-interval", type=int, default=4000, help="frames between evaluations (default: 4000)")
    w.add_argument("--eval-episodes", type=int, default=3, help="deterministic episodes per evaluation (default: 3)")
    w.add_argument(
        "--rank-events",
        type=int,
        default=3,
        help="adarl: rank events in the run (rank.interval = updates // (events + 1) + 1; default: 3)",
    )
    w.add_argument(
        "--event-threads",
        default="auto",
        help="adarl: torch threads of a rank event (rank.num_threads; default auto: every core, as a user's "
        "`adarl run` on an idle machine)",
    )
    w.add_argument(
        "--inference",
        action="store_true",
        help="also time act() at batch 1 (one thread): dense, low-rank at full rank and truncated actors",
    )
    w.add_argument("--inference-rank", type=int, default=7, help="rank of the truncated actor's layers (default: 7)")
    w.add_argument("--inference-calls", type=int, default=2000, help="timed act() calls per actor (default: 2000)")
    w.add_argument("--markdown", default=None, metavar="PATH", help="also write the markdown table to PATH")
    k = p.add_argument_group(
        "packed seeds (--pack)",
        "N seeds of the quickstart recipe's fused SAC packed in one process (adarl run --pack-seeds) against the same "
        "N seeds solo, side by side, each time next to the ~1.3 ms floor of a (64, 64) Hopper step: the update window "
        "(--steps, --skip, --warmup), or with --whole-run whole runs (--frames, --frames-per-batch, --warmup, "
        "--pack-threads, --no-two-packs). --envs, --widths, --repeats, --batch, --threads, --set, --output and "
        "--markdown apply too.",
    )
    k.add_argument("--pack", action="store_true", help="packed seeds against solo seeds (docs/performance.md)")
    k.add_argument(
        "--seeds", nargs="+", type=int, default=None, metavar="N", help="seed counts N (default: 1 2 4 8 16)"
    )
    k.add_argument(
        "--pack-threads",
        nargs="+",
        type=int,
        default=None,
        metavar="T",
        help="--whole-run: torch threads of the one packed process, a row each (default: --threads)",
    )
    k.add_argument("--no-two-packs", action="store_true", help="--whole-run: no row of two packs of N/2 side by side")


def cli(a) -> int:
    """``adarl bench`` (the update window; ``--whole-run`` goes to :mod:`adarl.experiments.bench._whole_run`)."""
    if getattr(a, "whole_run", False):  # `python -m adarl.experiments.bench --whole-run`: not this driver's mode
        raise AdaRLValueError("--whole-run is timed by `adarl bench --whole-run` (adarl.experiments.bench._whole_run)")
    if getattr(a, "pack", False):
        raise AdaRLValueError("--pack is measured by `adarl bench --pack` (adarl.experiments.bench._packed)")
    a.variants = list(VARIANTS) if a.variants is None else a.variants
    a.warmup = 1000 if a.warmup is None else a.warmup
    a.steps = 1000 if a.steps is None else a.steps
    a.output = "bench.json" if a.output is None else a.output
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
    p.add_argument("--whole-run-worker", choices=["sb3"], help=argparse.SUPPRESS)
    p.add_argument("--act-latency-worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.whole_run_worker:
        return _whole_run_worker(a)
    if a.act_latency_worker:
        rows = act_latency(a.env, a.width, rank=a.inference_rank, calls=a.inference_calls)
        print("ADARL_ACT_LATENCY " + json.dumps(rows))
        return 0
    return _worker(a) if a.worker else cli(a)


if __name__ == "__main__":
    sys.exit(main())
