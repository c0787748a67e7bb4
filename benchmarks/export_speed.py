"""act() latency at batch 1 of a policy deployed as TorchRL's actor (``adarl.load_policy``) and exported
(``adarl export``), for dense, full-rank and truncated actors; their parameters and file sizes.

The actors are built as the quickstart recipe builds them (Hopper-v5's observation and action spaces, ``(w, w)``
hidden layers, w in ``--widths``, default 64, 256 and 1024): plain ``nn.Linear`` layers (a full-rank SAC's), the
low-rank layers at full rank (AdaRL before its first rank event), truncated to the ranks a trained Hopper actor
ended with (the whole-run benchmark of docs/performance.md: 11/38 at 64 wide, 11/142 at 256), and truncated to
rank 7 (``--rank``). Each is exported with
:func:`adarl.runtime.export.export_actor` (checked against the actor as every export is) in the default form
(``--layers auto``) and, for the low-rank ones, all-merged and all-factored too.

Timed, one observation per call, one torch thread, ``torch.no_grad``:

* ``TorchRL actor``: ``actor(TensorDict(observation=obs))["action"]``, what ``adarl.load_policy`` returns;
* ``TorchScript``: the exported ``.pt`` file loaded with ``torch.jit.load``, called on the observation tensor;
  ``merged`` / ``factored``: the same with every low-rank layer in that form;
* ``torch.export``: the ``.pt2`` archive, ``torch.export.load(f).module()`` on a ``(1, obs)`` tensor;
* ``predict()``: ``adarl.ExportedPolicy(.pt).predict(obs)`` on a float64 numpy observation (as gymnasium gives it),
  numpy in and out.

All variants take turns in ``--rounds`` rounds of ``--calls / --rounds`` calls each, in one process; the median
call is reported. ``--clock cpu`` (default) times each call by the thread's CPU time (``time.thread_time_ns``),
which a busy machine's other processes do not inflate: with the wall clock, a call preempted mid-way counts the
other process's time slice, which biases long calls (TorchRL's ~0.3 ms) far more than short ones. ``--clock wall``
(``time.perf_counter_ns``) is the figure on an idle machine. Ratios between columns are the robust figures.

    PYTHONPATH=. python benchmarks/export_speed.py [--widths 64 256 1024] [--calls 4000] [--rounds 20] [--json FILE]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import torch
from tensordict import TensorDict

from adarl.core.lowrank import iter_low_rank
from adarl.runtime.builders.common import spec_env
from adarl.runtime.builders.sac import make_recipe_actor
from adarl.runtime.config import load_recipe
from adarl.runtime.export import export_actor
from adarl.runtime.exported import ExportedPolicy
from adarl.runtime.policy import _specs_from_env_id

#: final actor ranks of the trained Hopper-v5 runs of docs/performance.md's whole-run benchmark (adarl, 7000 updates)
TRAINED_RANKS = {64: (11, 38), 256: (11, 142)}


def build_actors(width: int, low_rank: int, specs: dict) -> dict[str, torch.nn.Module]:
    cells = [f"network.actor.num_cells=[{width},{width}]"]

    def build(extra):
        torch.manual_seed(0)
        actor = make_recipe_actor(load_recipe("quickstart", cells + extra), spec_env(specs, "cpu"))
        return actor.eval().requires_grad_(False)

    full = build([])
    actors = {"dense (nn.Linear)": build(["network.actor.low_rank_layers=[]", "rank.enabled=false"])}
    actors["low-rank, full rank"] = full
    for label, ranks in (
        ("low-rank, trained Hopper ranks", TRAINED_RANKS.get(width)),
        (f"low-rank, rank <= {low_rank}", (low_rank, low_rank)),
    ):
        if ranks is None:
            continue
        truncated = copy.deepcopy(full)
        for (_, layer), rank in zip(iter_low_rank(truncated), ranks):
            layer.truncate_(min(rank, layer.rank))
        actors[label] = truncated
    return actors


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="Hopper-v5")
    p.add_argument("--widths", type=int, nargs="+", default=[64, 256, 1024])
    p.add_argument("--rank", type=int, default=7, help="the low rank of the last actor of each width")
    p.add_argument("--calls", type=int, default=4000, help="timed calls per variant")
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--clock", choices=["cpu", "wall"], default="cpu", help="thread CPU time (default) or wall time")
    p.add_argument("--json", default=None, help="also write the rows here")
    a = p.parse_args()
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    torch.set_num_threads(1)
    specs = _specs_from_env_id(a.env)
    obs_dim = int(specs["observation_dim"])
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(obs_dim, generator=g)
    obs_np = obs.double().numpy()  # gymnasium's observations are float64
    obs_batch = obs[None]
    tmp = Path(tempfile.mkdtemp(prefix="adarl-export-bench-"))

    rows, calls = [], {}  # calls: (row, variant) -> a zero-argument callable
    for width in a.widths:
        for label, actor in build_actors(width, a.rank, specs).items():
            key = f"{width}-{len(rows)}"
            low_rank = any(True for _ in iter_low_rank(actor))
            files = {}
            for layers in ("auto", "merged", "factored") if low_rank else ("auto",):
                r = export_actor(actor, tmp / f"{key}-{layers}.pt", layers=layers)
                files[layers] = r
            pt2 = export_actor(actor, tmp / f"{key}.pt2", format="export")
            auto = files["auto"]
            ranks = "/".join(str(layer.rank) for _, layer in iter_low_rank(actor)) or "dense"
            forms = "/".join(x["form"][0].upper() for x in auto.metadata["layers"]) or "-"
            rows.append(
                {
                    "key": key,
                    "width": width,
                    "actor": label,
                    "ranks": ranks,
                    "forms": forms,
                    "actor_parameters": sum(p.numel() for p in actor.parameters()),
                    "program_parameters": auto.metadata["parameters"],
                    "factored_parameters": files["factored"].metadata["parameters"] if low_rank else None,
                    "pt_kib": auto.size_bytes / 1024,
                    "pt2_kib": pt2.size_bytes / 1024,
                }
            )
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", category=DeprecationWarning)
                programs = {f"ts_{k}": torch.jit.load(str(v.path)) for k, v in files.items()}
            ep = ExportedPolicy(pt2.path).program
            policy = ExportedPolicy(auto.path)
            calls[(key, "torchrl")] = lambda actor=actor: actor(TensorDict(observation=obs))["action"]
            for name, prog in programs.items():
                calls[(key, name)] = lambda prog=prog: prog(obs)
            calls[(key, "pt2")] = lambda ep=ep: ep(obs_batch)
            calls[(key, "predict")] = lambda policy=policy: policy.predict(obs_np)

    times: dict[tuple[str, str], list[float]] = {k: [] for k in calls}
    per_round = max(1, a.calls // a.rounds)
    clock = time.thread_time_ns if a.clock == "cpu" else time.perf_counter_ns
    with torch.no_grad():
        for f in calls.values():  # warm-up (TorchScript's profiling executor optimises after the first calls)
            for _ in range(100):
                f()
        for i in range(a.rounds):
            order = list(calls.items())
            if i % 2:
                order.reverse()
            for k, f in order:
                t = times[k]
                for _ in range(per_round):
                    t0 = clock()
                    f()
                    t.append((clock() - t0) / 1000)
    for row in rows:
        med = {v: statistics.median(times[(row["key"], v)]) for v in ("torchrl", "ts_auto", "pt2", "predict")}
        for v in ("ts_merged", "ts_factored"):
            med[v] = statistics.median(times[(row["key"], v)]) if (row["key"], v) in times else None
        row.update({f"{k}_us": v for k, v in med.items()})

    load = os.getloadavg()
    print(
        f"{time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} CPUs, load average {load[0]:.2f}; torch "
        f"{torch.__version__}, 1 thread; {a.env} (observation {obs_dim}); median of {per_round * a.rounds} calls "
        f"per variant, {a.rounds} interleaved rounds; act() at batch 1 in us of "
        f"{'thread CPU time' if a.clock == 'cpu' else 'wall time'}"
    )
    print()
    print(
        "| size | actor | ranks | exported layers | parameters: actor / exported (factored) | file .pt / .pt2 (KiB) "
        "| TorchRL actor | TorchScript | all merged / all factored | torch.export .pt2 | predict() numpy "
        "| TorchRL / TorchScript |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        mf = f"{r['ts_merged_us']:.1f} / {r['ts_factored_us']:.1f}" if r["ts_merged_us"] is not None else "-"
        params = f"{r['actor_parameters']} / {r['program_parameters']}" + (
            f" ({r['factored_parameters']})" if r["factored_parameters"] is not None else ""
        )
        print(
            f"| ({r['width']}, {r['width']}) | {r['actor']} | {r['ranks']} | {r['forms']} | {params} "
            f"| {r['pt_kib']:.1f} / {r['pt2_kib']:.1f} | {r['torchrl_us']:.1f} | {r['ts_auto_us']:.1f} | {mf} "
            f"| {r['pt2_us']:.1f} | {r['predict_us']:.1f} | {r['torchrl_us'] / r['ts_auto_us']:.1f}x |"
        )
    print()
    print("exported layers: M merged (W1 @ W2 as one Linear), F factored (two Linears), per low-rank layer")
    if a.json:
        Path(a.json).write_text(json.dumps({"load_average": load, "clock": a.clock, "rows": rows}, indent=1))
    for f in tmp.iterdir():
        f.unlink()
    tmp.rmdir()


if __name__ == "__main__":
    main()
