"""``adarl bench --whole-run``: whole training runs timed as a user waits for them, AdaRL against SB3 SAC.

The update-window benchmark (:mod:`adarl.experiments.bench._update`) times updates after warm-up. What a user waits
for is more: process start (imports), the random frames, the updates, rank events with their warm starts, evaluations,
checkpoints and the report. Here each variant is one whole run in a fresh subprocess, timed by this driver from
just before the process is started to its exit:

* ``adarl``: ``python -m adarl.cli run quickstart ... --quiet`` with the frames, warm-up, widths, batch and
  evaluation set below, the recipe's rank events scaled so that ``--rank-events`` of them happen
  (``rank.interval = updates // (events + 1) + 1``), a rank event on every core (what ``rank.num_threads: auto``
  gives a user's run on an idle machine), the loop on ``--threads`` (``algorithm.num_threads``);
* ``adarl_norank``: the same run with ``rank.enabled=false`` (the factorised layers stay at full rank);
* ``torchrl``: the same run on TorchRL's stock path (``algorithm.fused=false``, ``collector.lean=false``, plain
  ``nn.Linear`` layers, no rank adaptation): ``SACLoss``, for-loop Adam, ``SoftUpdate``, TorchRL's ``Collector``,
  inside adarl's trainer (evaluations, checkpoints and report included);
* ``sb3``: ``python -m adarl.experiments.bench --whole-run-worker sb3 ...``: Stable-Baselines3 SAC with the same
  settings (``net_arch=[w, w]``, batch, ``learning_starts`` = warm-up, one gradient step per env step, buffer of
  every frame, lr 3e-3, the entropy coefficient learnt from 1.0 as in the quickstart recipe) and an
  ``EvalCallback`` evaluating deterministically at the same frames for the same number of episodes (and once at
  the end, as adarl does, when the frames are not a multiple of the interval); skipped with a note when
  stable-baselines3 is not installed (``pip install 'adarl[bench]'``).

Every variant does one update per frame after ``--warmup`` random frames (adarl's warm-start frames after a rank
event are collected on top, ``replay.warm_start.count_frames=false``, so that every variant takes the same number
of updates; they are part of the schedule's cost), on ``OMP_NUM_THREADS = MKL_NUM_THREADS = --threads``. Repeats
are interleaved (order reversed on every other repeat); the report gives medians per (env, width, variant) and
the ratios of the medians measured side by side in this invocation (``sb3 / adarl``: > 1 means adarl is faster).

This driver imports neither torch nor TorchRL: the recipe checks use :func:`adarl.runtime.config.load_recipe`
(torch-free), and the act() latencies (``--inference``) are measured in a worker process too.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

from adarl.errors import AdaRLValueError
from adarl.experiments.bench._update import interleave
from adarl.runtime.config import load_recipe

__all__ = [
    "WHOLE_RUN_VARIANTS",
    "DEFAULTS",
    "validate",
    "rank_interval",
    "adarl_overrides",
    "adarl_command",
    "sb3_command",
    "event_threads",
    "run_whole_runs",
    "format_whole_run_table",
    "command_line",
    "cli",
]

WHOLE_RUN_VARIANTS = ("adarl", "adarl_norank", "torchrl", "sb3")
#: ours, and the baselines the ratios compare them with
OURS = ("adarl", "adarl_norank")
BASELINES = ("sb3", "torchrl")
#: the recipe every adarl variant runs
RECIPE = "quickstart"
#: defaults of the options whose default differs between modes (bench.add_arguments leaves them None)
DEFAULTS = {"variants": list(WHOLE_RUN_VARIANTS), "warmup": 5000, "frames": 12000, "output": "bench_whole_run.json"}
SB3_NOTE = "sb3 skipped: stable-baselines3 is not installed (pip install 'adarl[bench]')"


def _sb3_available() -> bool:
    return importlib.util.find_spec("stable_baselines3") is not None


def _updates(a) -> int:
    return a.frames - a.warmup


def rank_interval(updates: int, events: int) -> int:
    """Optimisation steps between rank events so that exactly ``events`` happen in ``updates`` steps (none at the
    very last update, whose warm start would be wasted).

    >>> rank_interval(7000, 3), rank_interval(400, 3)
    (1751, 101)
    """
    return updates // (events + 1) + 1


def event_threads() -> int:
    """The cores a rank event uses: what ``rank.num_threads: auto`` gives a run no launcher shares a machine in."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def adarl_overrides(a, env_id: str, width: int, variant: str) -> list[str]:
    """The ``adarl run quickstart`` overrides of one adarl variant (``--set`` last, for adarl and adarl_norank)."""
    ov = [
        f"env.id={env_id}",
        f"collector.total_frames={a.frames}",
        f"collector.init_random_frames={a.warmup}",
        # the first update after the batch that ends at the warm-up: frames - warmup updates in all, as SB3 takes
        f"algorithm.update_after={a.warmup + 1}",
        f"collector.frames_per_batch={a.frames_per_batch}",
        f"algorithm.batch_size={a.batch}",
        "algorithm.utd_ratio=1.0",
        f"algorithm.num_threads={a.threads}",
        f"network.actor.num_cells=[{width},{width}]",
        f"network.critic.num_cells=[{width},{width}]",
        f"replay.size={a.frames}",
        "replay.warm_start.count_frames=false",
        f"eval.interval={a.eval_interval}",
        f"eval.episodes={a.eval_episodes}",
    ]
    if variant == "adarl":
        ov += [
            "rank.enabled=true",
            f"rank.interval={rank_interval(_updates(a), a.rank_events)}",
            f"rank.num_threads={a.event_threads}",
        ]
    elif variant == "adarl_norank":
        ov += ["rank.enabled=false"]
    elif variant == "torchrl":
        ov += [
            "rank.enabled=false",
            "algorithm.fused=false",
            "collector.lean=false",
            "network.actor.low_rank_layers=[]",
            "network.critic.low_rank_layers=[]",
        ]
    else:
        raise AdaRLValueError(f"{variant!r} is not an adarl variant")
    if variant in OURS:
        ov += list(a.set)
    return ov


def validate(a) -> None:
    """Clear errors for options a whole run cannot take, before anything is run (recipe checks included)."""
    for name in ("frames", "repeats", "batch", "threads", "eval_interval", "eval_episodes", "rank_events"):
        if getattr(a, name) < 1:
            raise AdaRLValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if a.frames_per_batch < 1:
        raise AdaRLValueError(f"--frames-per-batch must be >= 1, got {a.frames_per_batch}")
    if a.warmup < 0:
        raise AdaRLValueError(f"--warmup must be >= 0, got {a.warmup}")
    if a.warmup >= a.frames:
        raise AdaRLValueError(f"--warmup ({a.warmup}) must be below --frames ({a.frames}): no update would run")
    for name in ("frames", "warmup", "eval_interval"):
        if getattr(a, name) % a.frames_per_batch:
            raise AdaRLValueError(
                f"--{name.replace('_', '-')} ({getattr(a, name)}) must be a multiple of --frames-per-batch "
                f"({a.frames_per_batch}): adarl collects, updates and evaluates on batch boundaries, so only then "
                f"do its updates and evaluations fall where SB3's do"
            )
    if a.eval_interval > a.frames:
        raise AdaRLValueError(f"--eval-interval ({a.eval_interval}) must be at most --frames ({a.frames})")
    bad = [w for w in a.widths if w < 1]
    if bad:
        raise AdaRLValueError(f"--widths must be >= 1, got {bad}")
    bad = [v for v in a.variants if v not in WHOLE_RUN_VARIANTS]
    if bad:
        raise AdaRLValueError(
            f"--whole-run variants are {', '.join(WHOLE_RUN_VARIANTS)}; {', '.join(bad)} time(s) the update window "
            f"only (adarl bench without --whole-run)"
        )
    if "adarl" in a.variants:
        interval = rank_interval(_updates(a), a.rank_events)
        if interval * a.rank_events > _updates(a):
            raise AdaRLValueError(
                f"{_updates(a)} updates (--frames - --warmup) are too few for --rank-events {a.rank_events}"
            )
    if a.inference and a.inference_rank < 1:
        raise AdaRLValueError(f"--inference-rank must be >= 1, got {a.inference_rank}")
    if a.inference and any(a.inference_rank > w for w in a.widths):
        raise AdaRLValueError(f"--inference-rank ({a.inference_rank}) must be at most every width ({a.widths})")
    if a.inference and a.inference_calls < 10:
        raise AdaRLValueError(f"--inference-calls must be >= 10, got {a.inference_calls}")
    for env_id in a.envs:  # a bad env id, width or --set override fails here, with the recipe's own error
        for width in a.widths:
            for variant in (v for v in a.variants if v != "sb3"):
                load_recipe(RECIPE, adarl_overrides(a, env_id, width, variant))


def _timed(cmd: list[str], env: dict, workdir: Path) -> dict:
    """Run ``cmd`` to its end; wall time from just before the process starts to its exit, and its own CPU time
    and peak RSS (``wait4``)."""
    out_path, err_path = workdir / "stdout.txt", workdir / "stderr.txt"
    with open(out_path, "w") as out, open(err_path, "w") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env, cwd=workdir)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss / 1024,
        "returncode": proc.returncode,
        "stdout": out_path.read_text(),
        "stderr": err_path.read_text(),
    }


def _env(a) -> dict:
    threads = str(a.threads)
    return dict(os.environ, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)


def _failed(what: str, res: dict) -> RuntimeError:
    return RuntimeError(f"whole run {what} failed (exit {res['returncode']}):\n{res['stderr'][-3000:]}")


def _eval_rows(run: Path) -> list[dict]:
    path = run / "eval.csv"
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def adarl_command(a, env_id: str, width: int, variant: str, run: Path) -> list[str]:
    """The process an adarl variant's whole run is: ``python -m adarl.cli run quickstart ... -o run --quiet``."""
    cmd = [sys.executable, "-m", "adarl.cli", "run", RECIPE, *adarl_overrides(a, env_id, width, variant)]
    return cmd + ["-o", str(run), "--quiet"]


def run_adarl(variant: str, env_id: str, width: int, a) -> dict:
    """One adarl variant's whole run (``python -m adarl.cli run quickstart ...``), timed; what its run folder says."""
    with tempfile.TemporaryDirectory(prefix="adarl-whole-run-") as tmp:
        run = Path(tmp) / "run"
        cmd = adarl_command(a, env_id, width, variant, run)
        res = _timed(cmd, _env(a), Path(tmp))
        if res["returncode"] != 0 or not (run / "summary.json").exists():
            raise _failed(f"{variant} {env_id} {width}", res)
        summary = json.loads((run / "summary.json").read_text())
        evals = _eval_rows(run)
    return {
        "wall_s": res["wall_s"],
        "cpu_s": res["cpu_s"],
        "peak_rss_mb": res["peak_rss_mb"],
        "loop_s": summary["wall_time_s"],  # train(): from the first frame to the report written
        "frames": summary["frames"],
        "env_frames": summary["env_frames"],
        "warm_start_frames": summary["warm_start_frames"],
        "updates": summary["updates"],
        "rank_events": summary["rank_events"],
        "final_ranks": {summary["layer_names"].get(k, k): r for k, r in summary["ranks"].items()},
        "evals": len(evals),
        "eval_episodes": sum(int(r["episodes"]) for r in evals),
        "final_eval_mean": (summary.get("final_eval") or {}).get("mean"),
        "command": shlex.join(["python", *cmd[1:]]),
    }


def sb3_command(a, env_id: str, width: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "adarl.experiments.bench",
        "--whole-run-worker",
        "sb3",
        "--env",
        env_id,
        "--width",
        str(width),
        "--frames",
        str(a.frames),
        "--warmup",
        str(a.warmup),
        "--batch",
        str(a.batch),
        "--threads",
        str(a.threads),
        "--eval-interval",
        str(a.eval_interval),
        "--eval-episodes",
        str(a.eval_episodes),
    ]


def _worker_line(res: dict, tag: str) -> dict | None:
    for line in res["stdout"].splitlines():
        if line.startswith(tag + " "):
            return json.loads(line[len(tag) + 1 :])
    return None


def run_sb3(env_id: str, width: int, a) -> dict:
    """One SB3 SAC whole run in a fresh process (:func:`adarl.experiments.bench.whole_run_sb3`), timed."""
    with tempfile.TemporaryDirectory(prefix="adarl-whole-run-sb3-") as tmp:
        cmd = sb3_command(a, env_id, width)
        res = _timed(cmd, _env(a), Path(tmp))
    out = _worker_line(res, "ADARL_WHOLE_RUN")
    if res["returncode"] != 0 or out is None:
        raise _failed(f"sb3 {env_id} {width}", res)
    return {
        "wall_s": res["wall_s"],
        "cpu_s": res["cpu_s"],
        "peak_rss_mb": res["peak_rss_mb"],
        **out,
        "env_frames": out["frames"],
        "warm_start_frames": 0,
        "rank_events": 0,
        "final_ranks": {},
        "command": shlex.join(["python", *cmd[1:]]),
    }


def run_one(variant: str, env_id: str, width: int, a) -> dict:
    return run_sb3(env_id, width, a) if variant == "sb3" else run_adarl(variant, env_id, width, a)


def act_latency(env_id: str, width: int, a) -> list[dict]:
    """act() latencies at batch 1 of one width's actors, measured in a worker process on one thread."""
    cmd = [
        sys.executable,
        "-m",
        "adarl.experiments.bench",
        "--act-latency-worker",
        "--env",
        env_id,
        "--width",
        str(width),
        "--inference-rank",
        str(a.inference_rank),
        "--inference-calls",
        str(a.inference_calls),
    ]
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    with tempfile.TemporaryDirectory(prefix="adarl-act-latency-") as tmp:
        res = _timed(cmd, env, Path(tmp))
    rows = _worker_line(res, "ADARL_ACT_LATENCY")
    if res["returncode"] != 0 or rows is None:
        raise _failed(f"act latency {env_id} {width}", res)
    return [dict(r, env=env_id, width=width) for r in rows]


_SUMMED = ("wall_s", "cpu_s", "peak_rss_mb", "loop_s")
_SAME = ("frames", "env_frames", "warm_start_frames", "updates", "rank_events", "evals", "eval_episodes")


def run_whole_runs(a) -> dict:
    """Interleave variants x repeats for each (env, width); medians, ratios of medians and every run."""
    variants = [v for v in a.variants if v != "sb3" or _sb3_available()]
    skipped = [v for v in a.variants if v not in variants]
    load_before = os.getloadavg()
    results = []
    for env_id in a.envs:
        for width in a.widths:
            runs = interleave(
                variants,
                a.repeats,
                lambda v, env_id=env_id, width=width: run_one(v, env_id, width, a),
                None
                if a.quiet
                else lambda v, rep, r, env_id=env_id, width=width: print(
                    f"  whole run {env_id} ({width},{width}) {v} #{rep + 1}: {r['wall_s']:.1f} s, "
                    f"{r['updates']} updates, {r['rank_events']} rank events",
                    file=sys.stderr,
                    flush=True,
                ),
            )
            row: dict = {"env": env_id, "width": width, "variants": {}}
            for v, rs in runs.items():
                d = {k: statistics.median(r[k] for r in rs) for k in _SUMMED}
                d.update({k: statistics.median(r[k] for r in rs) for k in _SAME})  # equal across repeats, or nearly
                d["final_ranks"] = rs[-1]["final_ranks"]
                d["runs"] = rs
                row["variants"][v] = d
            wall = {v: d["wall_s"] for v, d in row["variants"].items()}
            row["ratios"] = {f"{b}/{o}": wall[b] / wall[o] for b in BASELINES for o in OURS if b in wall and o in wall}
            if "adarl" in wall and "adarl_norank" in wall:  # > 1: the rank events pay for themselves in this run
                row["ratios"]["adarl_norank/adarl"] = wall["adarl_norank"] / wall["adarl"]
            results.append(row)
    inference = [r for env_id in a.envs for w in a.widths for r in act_latency(env_id, w, a)] if a.inference else []
    return {
        "mode": "whole-run",
        "command": command_line(a),
        "argv": list(sys.argv),
        "settings": {k: v for k, v in vars(a).items() if k != "func"},
        "recipe": RECIPE,
        "rank_interval": rank_interval(_updates(a), a.rank_events),
        "skipped": skipped,
        "results": results,
        "inference": inference,
        "machine": {
            "cpus": os.cpu_count(),
            "load_avg_before": load_before,
            "load_avg_after": os.getloadavg(),
            "date": time.strftime("%Y-%m-%d %H:%M"),
        },
        "versions": _versions(),
    }


def _versions() -> dict:
    out = {"python": sys.version.split()[0]}
    for name in ("adarl", "torch", "torchrl", "stable-baselines3", "gymnasium", "mujoco"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def command_line(a) -> str:
    """The invocation, every setting spelled out (it reproduces the table whatever the defaults become)."""
    args = ["adarl", "bench", "--whole-run", "--envs", *a.envs, "--widths", *map(str, a.widths)]
    args += ["--variants", *a.variants, "--repeats", str(a.repeats), "--frames", str(a.frames)]
    args += ["--warmup", str(a.warmup), "--frames-per-batch", str(a.frames_per_batch), "--batch", str(a.batch)]
    args += ["--threads", str(a.threads), "--eval-interval", str(a.eval_interval)]
    args += ["--eval-episodes", str(a.eval_episodes), "--rank-events", str(a.rank_events)]
    args += ["--event-threads", str(a.event_threads)]
    if a.set:
        args += ["--set", *a.set]
    if a.inference:
        args += ["--inference", "--inference-rank", str(a.inference_rank), "--inference-calls", str(a.inference_calls)]
    args += ["--output", str(a.output)]
    if a.markdown:
        args += ["--markdown", str(a.markdown)]
    return shlex.join(args)


def _ranks(d: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in d["final_ranks"].items()) or "-"


def format_whole_run_table(report: dict) -> str:
    s = report["settings"]
    m = report["machine"]
    lines = [
        f"Command: `{report['command']}`",
        "",
        f"{m['date']}, {m['cpus']} CPUs, load average {m['load_avg_before'][0]:.2f} before and "
        f"{m['load_avg_after'][0]:.2f} after; {s['frames']} frames, {s['frames'] - s['warmup']} updates after "
        f"{s['warmup']} random frames, batch {s['batch']}, {s['threads']} thread(s), evaluation every "
        f"{s['eval_interval']} frames ({s['eval_episodes']} episodes); adarl: recipe {report['recipe']}, a rank "
        f"event every {report['rank_interval']} updates on {s['event_threads']} thread(s). Wall time: process start "
        f"to exit, median of {s['repeats']}.",
        "",
        "| env | size | variant | wall time (s) | training loop (s) | CPU time (s) | updates | env frames | "
        "eval episodes | rank events | final ranks | peak RSS (MB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in report["results"]:
        size = f"({row['width']}, {row['width']})"
        for v, d in row["variants"].items():
            lines.append(
                f"| {row['env']} | {size} | {v} | {d['wall_s']:.1f} | {d['loop_s']:.1f} | {d['cpu_s']:.1f} | "
                f"{d['updates']:.0f} | {d['env_frames']:.0f} | {d['eval_episodes']:.0f} | "
                f"{d['rank_events']:.0f} | {_ranks(d)} | {d['peak_rss_mb']:.0f} |"
            )
    lines += ["", "| env | size | wall-time ratio (> 1: the second is faster) | value |", "|---|---|---|---|"]
    for row in report["results"]:
        for k, val in row["ratios"].items():
            lines.append(f"| {row['env']} | ({row['width']}, {row['width']}) | {k.replace('/', ' / ')} | {val:.2f}x |")
    for row in report["results"]:
        updates = {v: d["updates"] for v, d in row["variants"].items()}
        if len(set(updates.values())) > 1:  # e.g. a --set that changes the update cadence of our loops only
            lines += [
                "",
                f"note: the variants took different numbers of updates in {row['env']} ({row['width']}, "
                f"{row['width']}): " + ", ".join(f"{v} {n:.0f}" for v, n in updates.items()),
            ]
    if report["inference"]:
        lines += [
            "",
            "| env | size | actor | ranks | parameters | act() at batch 1 (us, median) | network only (us) |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in report["inference"]:
            lines.append(
                f"| {r['env']} | ({r['width']}, {r['width']}) | {r['actor']} | {r['ranks']} | {r['parameters']} | "
                f"{r['act_us']:.1f} | {r['network_us']:.1f} |"
            )
    if report["skipped"]:
        lines += ["", SB3_NOTE if report["skipped"] == ["sb3"] else f"skipped: {', '.join(report['skipped'])}"]
    return "\n".join(lines)


def cli(a) -> int:
    """``adarl bench --whole-run``: check the options, run, write the JSON and print (and write) the table."""
    for key, value in DEFAULTS.items():
        if getattr(a, key) is None:
            setattr(a, key, list(value) if isinstance(value, list) else value)
    if a.event_threads == "auto":
        a.event_threads = event_threads()
    else:
        try:
            a.event_threads = int(a.event_threads)
        except ValueError:
            raise AdaRLValueError(
                f"--event-threads must be 'auto' or an integer >= 1, got {a.event_threads!r}"
            ) from None
        if a.event_threads < 1:
            raise AdaRLValueError(f"--event-threads must be 'auto' or an integer >= 1, got {a.event_threads}")
    validate(a)
    if "sb3" in a.variants and not _sb3_available():
        print(SB3_NOTE, file=sys.stderr, flush=True)
    write_and_print(a, run_whole_runs(a), format_whole_run_table)
    return 0


def write_and_print(a, report: dict, table_of) -> None:
    """The JSON report at ``--output``, the table printed (and at ``--markdown``): every bench mode's ending."""
    Path(a.output).write_text(json.dumps(report, indent=2) + "\n")
    table = table_of(report)
    if a.markdown:
        Path(a.markdown).write_text(table + "\n")
    print(table)
    print(f"\nJSON report: {a.output}" + (f"; markdown: {a.markdown}" if a.markdown else ""))
