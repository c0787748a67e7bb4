"""``adarl bench --pack``: N seeds packed in one process against the same N seeds solo, measured side by side.

Why: packing (``adarl run --pack-seeds``; docs/performance.md, "Packed seeds") pays only where a seed's update is
bound by per-call overhead. This measures where, for the seed counts and widths asked for, in one invocation on the
same cores (absolute times move with the machine's load; the ratios, measured side by side, much less):

* the update window (default): one :class:`~adarl.fast.packed.PackedSACUpdate` step for N seeds against the same N
  seeds' fused updates one after another, in this process (sampling, noise, losses, backward, clipping, Adam,
  schedules, Polyak; no env, no collection, no rank events), solo and packed windows interleaved, median of
  ``--repeats``;
* ``--whole-run``: whole runs, process start to finished run folders (rank events, warm starts, evaluations,
  checkpoints, reports): N seeds in one ``adarl run --pack-seeds`` process (a row per ``--pack-threads``) against N
  solo ``adarl run`` processes two at a time (as ``adarl experiment -j 2`` runs them on 2 cores), and two packs of
  N/2 side by side; aggregate frames/s.

Each time per seed-step is set next to the floor packing cannot go under (:data:`FLOOR`). Unlike the other bench
drivers this one imports torch: it times the update window in its own process; the hub loads it for ``--pack``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from adarl.errors import AdaRLValueError
from adarl.experiments.bench._update import add_arguments, interleave
from adarl.experiments.bench._whole_run import _versions, write_and_print
from adarl.fast.packed import PackedSACUpdate
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.trainers.packed import pack_refusal

__all__ = [
    "PACK_VARIANTS",
    "FLOOR",
    "validate_pack",
    "window_overrides",
    "pack_whole_run_overrides",
    "update_window",
    "whole_run_layouts",
    "run_pack",
    "format_pack_table",
    "pack_command_line",
    "cli",
]

#: the recipe every seed runs, and the one bench variant a pack can run (the fused SAC update with rank adaptation)
RECIPE = "quickstart"
PACK_VARIANTS = ("adarl",)
#: the issue's estimate of the real work in one synchronous Hopper-v5 (64, 64) step (ms): the update's arithmetic
#: and the simulator's step, what is left once packing has removed the per-call overhead; no estimate at other sizes
FLOOR = {"env": "Hopper-v5", "width": 64, "update_ms": 1.0, "simulator_ms": 0.27, "step_ms": 1.3}
#: per-mode defaults of the options bench.add_arguments leaves None
DEFAULTS = {"variants": list(PACK_VARIANTS), "seeds": [1, 2, 4, 8, 16], "steps": 200, "frames": 6000}
OUTPUT = {False: "bench_pack.json", True: "bench_pack_whole_run.json"}
#: the options each mode takes (every other `adarl bench` option must keep its default)
TAKES = {
    False: ("steps", "skip", "warmup"),
    True: ("frames", "frames_per_batch", "warmup", "pack_threads", "no_two_packs"),
}
#: the options both modes take
SHARED = ("pack", "whole_run", "envs", "widths", "variants", "seeds", "repeats", "batch", "threads", "set", "output")
SHARED += ("markdown", "quiet")
#: solo runs at once (the 2 cores of the machine the issue's goal is set on), and the whole-run layouts' labels
SOLO_AT_ONCE = 2
SOLO, TWO_PACKS = "solo (2 at a time)", "2 packs of N/2 side by side"


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def floor_ms(env_id: str, width: int, whole_run: bool) -> float | None:
    """The floor a seed-step (whole runs) or a seed-update (the window) is set against, where it is estimated."""
    if (env_id, width) != (FLOOR["env"], FLOOR["width"]):
        return None
    return FLOOR["step_ms"] if whole_run else FLOOR["update_ms"]


def window_overrides(a, env_id: str, width: int, seed: int) -> list[str]:
    """The recipe overrides of one seed in the update window (``--set`` last)."""
    cells = f"[{width},{width}]"
    ov = [f"env.id={env_id}", "algorithm.fused=true", f"seed={seed}", f"network.actor.num_cells={cells}"]
    ov += [f"network.critic.num_cells={cells}", "lr_schedule.warmup_steps=1", f"algorithm.batch_size={a.batch}"]
    return ov + list(a.set)


def pack_whole_run_overrides(a, env_id: str, width: int, threads: int) -> list[str]:
    """The ``adarl run quickstart`` overrides of every whole run (solo or packed): two rank events with their warm
    starts, two evaluations and checkpoints, scaled to ``--frames`` (``--set`` last)."""
    f, cells = a.frames, f"[{width},{width}]"
    return [
        f"env.id={env_id}",
        f"collector.total_frames={f}",
        f"collector.init_random_frames={a.warmup}",
        f"collector.frames_per_batch={a.frames_per_batch}",
        f"rank.interval={f // 3}",
        "lr_schedule.warmup_steps=200",
        "replay.warm_start.frames=500",
        f"eval.interval={f // 2}",
        "eval.episodes=2",
        "eval.max_steps=200",
        f"checkpoint.interval={f // 2}",
        f"network.actor.num_cells={cells}",
        f"network.critic.num_cells={cells}",
        f"algorithm.batch_size={a.batch}",
        "algorithm.fused=true",
        f"algorithm.num_threads={threads}",
        *a.set,
    ]


def validate_pack(a) -> None:
    """Refuse what a pack cannot measure, by name, and fill the per-mode defaults, before anything runs."""
    whole = bool(a.whole_run)
    p = argparse.ArgumentParser()
    add_arguments(p)
    default = vars(p.parse_args([]))
    takes = SHARED + TAKES[whole]
    given = [n for n in default if n not in takes and getattr(a, n, default[n]) != default[n]]
    if given:
        mode = "--pack --whole-run" if whole else "--pack"
        raise AdaRLValueError(
            f"{mode} does not take {', '.join(map(_flag, given))}; it takes "
            f"{', '.join(_flag(n) for n in takes if n not in ('pack', 'whole_run'))}"
        )
    for key, value in DEFAULTS.items():
        if key in takes and getattr(a, key) is None:
            setattr(a, key, list(value) if isinstance(value, list) else value)
    bad = [v for v in a.variants if v not in PACK_VARIANTS]
    if bad:
        raise AdaRLValueError(
            f"--pack packs the {', '.join(PACK_VARIANTS)} variant only (the fused SAC update a pack runs), got "
            f"{', '.join(bad)}: adarl bench without --pack compares the others"
        )
    if any(n < 1 for n in a.seeds) or len(set(a.seeds)) != len(a.seeds):
        raise AdaRLValueError(f"--seeds must be distinct seed counts >= 1, e.g. --seeds 1 2 4 8 16; got {a.seeds}")
    if any(w < 1 for w in a.widths):
        raise AdaRLValueError(f"--widths must be >= 1, got {a.widths}")
    a.output = OUTPUT[whole] if a.output is None else a.output
    if whole:
        a.warmup = a.frames // 6 if a.warmup is None else a.warmup
        a.pack_threads = [a.threads] if a.pack_threads is None else a.pack_threads
        if any(t < 1 for t in a.pack_threads):
            raise AdaRLValueError(f"--pack-threads must be >= 1, got {a.pack_threads}")
        positive = ("frames", "frames_per_batch", "repeats", "batch", "threads")
    else:
        a.warmup = 1000 if a.warmup is None else a.warmup
        positive = ("steps", "warmup", "repeats", "batch", "threads")
        if a.skip < 0:
            raise AdaRLValueError(f"--skip must be >= 0, got {a.skip}")
    for name in positive:
        if getattr(a, name) < 1:
            raise AdaRLValueError(f"{_flag(name)} must be >= 1, got {getattr(a, name)}")
    if whole and not 0 <= a.warmup < a.frames:
        raise AdaRLValueError(f"--warmup ({a.warmup}) must be >= 0 and below --frames ({a.frames})")
    for env_id in a.envs:  # a bad env id, width or --set fails here with the recipe's error, an unpackable one so too
        for width in a.widths:
            ov = (
                pack_whole_run_overrides(a, env_id, width, a.threads)
                if whole
                else window_overrides(a, env_id, width, 0)
            )
            reason = pack_refusal(load_recipe(RECIPE, ov))
            if reason is not None:
                raise AdaRLValueError(f"--pack: {env_id} ({width}, {width}) cannot be packed: {reason}")


def _seed(a, env_id: str, width: int, seed: int):
    c = build_sac_components(load_recipe(RECIPE, window_overrides(a, env_id, width, seed)))
    torch.manual_seed(seed)
    c.replay_buffer.extend(c.env.rollout(a.warmup, break_when_any_done=False).reshape(-1))
    return c


def _finished(cs) -> None:
    """Wait for the seeds' device (a GPU queues its kernels: a window ends when its work is done, not queued)."""
    device = cs[0].update.fused.loss.log_alpha.device
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _solo_window(cs, steps: int) -> float:
    _finished(cs)
    t0 = time.perf_counter()
    for _ in range(steps):
        for c in cs:
            c.update()
    _finished(cs)
    return time.perf_counter() - t0


def _packed_window(cs, packed: PackedSACUpdate, steps: int) -> float:
    _finished(cs)
    t0 = time.perf_counter()
    for _ in range(steps):
        batches = [c.update.sampler() for c in cs]
        noises = [c.update.fused.draw_noise(b[0], b[1]) for c, b in zip(cs, batches, strict=True)]
        packed.step(batches, noises)
    _finished(cs)
    return time.perf_counter() - t0


def update_window(a, env_id: str, width: int, n: int) -> dict:
    """N seeds' updates one after another against one packed step for all of them, in this process: each seed's
    replay holds ``--warmup`` frames of its env, ``--skip`` untimed updates, then ``--repeats`` windows of
    ``--steps`` updates a seed, interleaved (order reversed every other repeat); medians."""
    solo = [_seed(a, env_id, width, s) for s in range(n)]
    packs = [_seed(a, env_id, width, s) for s in range(n)]
    packed = PackedSACUpdate([c.update.fused for c in packs])
    try:
        _solo_window(solo, a.skip)
        _packed_window(packs, packed, a.skip)
        runs = interleave(
            ["solo", "packed"],
            a.repeats,
            lambda v: {"s": _solo_window(solo, a.steps) if v == "solo" else _packed_window(packs, packed, a.steps)},
        )
    finally:
        for c in solo + packs:
            c.close()
    times = {v: [r["s"] for r in rs] for v, rs in runs.items()}
    solo_s, packed_s = statistics.median(times["solo"]), statistics.median(times["packed"])
    updates = n * a.steps
    return {
        "env": env_id,
        "width": width,
        "seeds": n,
        "solo_seed_updates_per_s": updates / solo_s,
        "packed_seed_updates_per_s": updates / packed_s,
        "solo_ms_per_seed_update": 1e3 * solo_s / updates,
        "packed_ms_per_seed_update": 1e3 * packed_s / updates,
        "ratio_packed_over_solo": solo_s / packed_s,
        "floor_ms": floor_ms(env_id, width, False),
        "solo_windows_s": times["solo"],
        "packed_windows_s": times["packed"],
    }


def _adarl_run(a, env_id: str, width: int, threads: int, seeds: int | list[int], out: Path) -> tuple[list[str], int]:
    """``python -m adarl.cli run quickstart ...``: one seed solo (``seeds`` an int), or a pack; with its threads."""
    how = [f"seed={seeds}"] if isinstance(seeds, int) else ["--pack-seeds", *map(str, seeds)]
    cmd = [sys.executable, "-m", "adarl.cli", "run", RECIPE, *pack_whole_run_overrides(a, env_id, width, threads)]
    return [*cmd, *how, "-o", str(out), "--quiet"], threads


def _run_processes(runs: list[tuple[list[str], int]], at_once: int, workdir: Path) -> float:
    """Every command, at most ``at_once`` at a time (the next starts as one ends); the wall time from the first start
    to the last exit. A failed run stops the others and raises with its stderr."""
    pending, running = list(enumerate(runs)), {}
    t0 = time.perf_counter()
    try:
        while pending or running:
            while pending and len(running) < at_once:
                i, (cmd, threads) = pending.pop(0)
                env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
                with open(workdir / f"stderr{i}.txt", "w") as err:
                    running[i] = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err)
            time.sleep(0.02)
            for i, proc in list(running.items()):
                if proc.poll() is None:
                    continue
                del running[i]
                if proc.returncode != 0:
                    tail = (workdir / f"stderr{i}.txt").read_text()[-3000:]
                    raise RuntimeError(
                        f"a benchmark run failed (exit {proc.returncode}): {shlex.join(runs[i][0])}\n{tail}"
                    )
        return time.perf_counter() - t0
    finally:
        for proc in running.values():  # only after a failure: the runs this call started
            proc.kill()
            proc.wait()


def whole_run_layouts(a, env_id: str, width: int, n: int):
    """``{label: run(root) -> (wall seconds, run folders)}``: the ways N seeds are trained whole, side by side."""
    seeds = list(range(n))

    def solo(root: Path):
        runs = [_adarl_run(a, env_id, width, a.threads, s, root / f"solo{s}") for s in seeds]
        return _run_processes(runs, SOLO_AT_ONCE, root), [root / f"solo{s}" for s in seeds]

    def packed(threads: int):
        def run(root: Path):
            wall = _run_processes([_adarl_run(a, env_id, width, threads, seeds, root / "pack")], 1, root)
            return wall, [root / "pack" / f"seed={s}" for s in seeds]

        return run

    def two_packs(root: Path):
        halves = [seeds[: n // 2], seeds[n // 2 :]]
        runs = [_adarl_run(a, env_id, width, a.threads, h, root / f"half{k}") for k, h in enumerate(halves)]
        return _run_processes(runs, 2, root), [root / f"half{k}" / f"seed={s}" for k, h in enumerate(halves) for s in h]

    layouts = {SOLO: solo, **{f"packed, {t} thread(s)": packed(t) for t in a.pack_threads}}
    if n >= 2 and not a.no_two_packs:
        layouts[TWO_PACKS] = two_packs
    return layouts


def _whole_runs(a, env_id: str, width: int, n: int) -> list[dict]:
    layouts = whole_run_layouts(a, env_id, width, n)

    def run(label: str) -> dict:
        with tempfile.TemporaryDirectory(prefix="adarl-bench-pack-") as tmp:
            wall, folders = layouts[label](Path(tmp))
            missing = [str(f) for f in folders if not (f / "summary.json").exists()]
        if missing:
            raise RuntimeError(f"{label}: runs ended without a summary.json: {missing}")
        return {"wall_s": wall}

    runs = interleave(list(layouts), a.repeats, run)
    walls = {label: statistics.median(r["wall_s"] for r in rs) for label, rs in runs.items()}
    return [
        {
            "env": env_id,
            "seeds": n,
            "width": width,
            "variant": label,
            "wall_s": wall,
            "aggregate_frames_per_s": n * a.frames / wall,
            "ms_per_seed_step": 1e3 * wall / (n * a.frames),
            "vs_solo": walls[SOLO] / wall,
            "floor_ms": floor_ms(env_id, width, True),
            "walls_s": [r["wall_s"] for r in runs[label]],
        }
        for label, wall in walls.items()
    ]


def run_pack(a) -> dict:
    """Every (env, width, N) of the options, in order; the report (settings, rows, machine, versions)."""
    load_before = os.getloadavg()
    if not a.whole_run:
        torch.set_num_threads(a.threads)
    rows = []
    for env_id in a.envs:
        for width in a.widths:
            for n in a.seeds:
                new = _whole_runs(a, env_id, width, n) if a.whole_run else [update_window(a, env_id, width, n)]
                rows += new
                if not a.quiet:
                    print("\n".join("  " + _progress(r) for r in new), file=sys.stderr, flush=True)
    settings = {k: v for k, v in vars(a).items() if k in SHARED + TAKES[bool(a.whole_run)]}
    overrides = {
        f"{env_id} ({w}, {w})": pack_whole_run_overrides(a, env_id, w, a.threads)
        if a.whole_run
        else window_overrides(a, env_id, w, 0)
        for env_id in a.envs
        for w in a.widths
    }
    return {
        "mode": "pack-whole-run" if a.whole_run else "pack",
        "command": pack_command_line(a),
        "argv": list(sys.argv),
        "settings": settings,
        "recipe": RECIPE,
        "overrides": overrides,  # seed=0 in the window's: each seed S has seed=S
        "floor": FLOOR,
        "rows": rows,
        "machine": {
            "cpus": os.cpu_count(),
            "load_avg_before": load_before,
            "load_avg_after": os.getloadavg(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        },
        "versions": _versions(),
    }


def _progress(r: dict) -> str:
    size = f"{r['env']} ({r['width']}, {r['width']}) N={r['seeds']}"
    if "variant" in r:
        return f"{size} {r['variant']}: {r['wall_s']:.1f} s, {r['aggregate_frames_per_s']:.1f} frames/s"
    return (
        f"{size}: solo {r['solo_ms_per_seed_update']:.3f}, packed {r['packed_ms_per_seed_update']:.3f} "
        f"ms/seed-update, packed/solo {r['ratio_packed_over_solo']:.2f}x"
    )


def pack_command_line(a) -> str:
    """The invocation, every setting spelled out (it reproduces the table whatever the defaults become)."""
    args = ["adarl", "bench", "--pack", *(["--whole-run"] if a.whole_run else [])]
    args += ["--seeds", *map(str, a.seeds), "--envs", *a.envs, "--widths", *map(str, a.widths)]
    args += ["--repeats", str(a.repeats)]
    if a.whole_run:
        args += ["--frames", str(a.frames), "--frames-per-batch", str(a.frames_per_batch), "--warmup", str(a.warmup)]
        args += ["--pack-threads", *map(str, a.pack_threads), *(["--no-two-packs"] if a.no_two_packs else [])]
    else:
        args += ["--steps", str(a.steps), "--skip", str(a.skip), "--warmup", str(a.warmup)]
    args += ["--batch", str(a.batch), "--threads", str(a.threads)]
    if a.set:
        args += ["--set", *a.set]
    args += ["--output", str(a.output)]
    if a.markdown:
        args += ["--markdown", str(a.markdown)]
    return shlex.join(args)


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def format_pack_table(report: dict) -> str:
    """The rows side by side: per seed-step (or seed-update) ms next to the floor, and packed / solo."""
    s, m, f = report["settings"], report["machine"], report["floor"]
    floor = (
        f"floor: ~{f['step_ms']} ms a seed-step at {f['env']} ({f['width']}, {f['width']}) (~{f['update_ms']:.0f} ms "
        f"update arithmetic + ~{f['simulator_ms']} ms simulator, the issue's estimate; none at other sizes)"
    )
    lines = [f"Command: `{report['command']}`", ""]
    head = f"{m['date']}, {m['cpus']} CPUs, load average {m['load_avg_before'][0]:.2f} before and "
    head += f"{m['load_avg_after'][0]:.2f} after; batch {s['batch']}, {s['threads']} torch thread(s)"
    if report["mode"] == "pack":
        lines += [
            f"{head}; the update window alone: {s['steps']} timed updates a seed after {s['skip']} untimed, median "
            f"of {s['repeats']} windows, solo and packed interleaved in one process; {floor}, its update part "
            f"~{f['update_ms']:.0f} ms here.",
            "",
            "| env | size | seeds N | solo ms / seed-update | packed ms / seed-update | update floor (ms) | "
            "packed / floor | packed / solo |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in report["rows"]:
            over = "-" if r["floor_ms"] is None else f"{r['packed_ms_per_seed_update'] / r['floor_ms']:.1f}x"
            lines.append(
                f"| {r['env']} | ({r['width']}, {r['width']}) | {r['seeds']} | {r['solo_ms_per_seed_update']:.3f} | "
                f"{r['packed_ms_per_seed_update']:.3f} | {_ms(r['floor_ms'])} | {over} | "
                f"{r['ratio_packed_over_solo']:.2f}x |"
            )
        return "\n".join(lines)
    lines += [
        f"{head}; whole runs, process start to finished run folders, {s['frames']} frames a seed "
        f"({s['warmup']} random), median of {s['repeats']}; {floor}.",
        "",
        "| env | size | seeds N | how the seeds ran | wall (s) | aggregate frames/s | ms / seed-step | floor (ms) | "
        "vs solo runs two at a time |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["rows"]:
        lines.append(
            f"| {r['env']} | ({r['width']}, {r['width']}) | {r['seeds']} | {r['variant']} | {r['wall_s']:.1f} | "
            f"{r['aggregate_frames_per_s']:.1f} | {r['ms_per_seed_step']:.2f} | {_ms(r['floor_ms'])} | "
            f"{r['vs_solo']:.2f}x |"
        )
    return "\n".join(lines)


def cli(a) -> int:
    """``adarl bench --pack``: check the options, measure, write the JSON and print (and write) the table."""
    validate_pack(a)
    write_and_print(a, run_pack(a), format_pack_table)
    return 0
