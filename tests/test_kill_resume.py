"""Real CLI runs killed and resumed: kill -9 at random moments (5 times in one run) must end with exactly the
metrics of an uninterrupted run, for AdaRL-SAC and for the RNAC baselines' PPO loop; SIGTERM must save a
checkpoint and exit cleanly.

The seed of the kill times is printed on failure (ADARL_KILL_SEED picks one). Budget: about a minute per run on 2
cores.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest
from _helpers import checkpoints, start_adarl, tiny, tiny_ppo, wait_for

REPO = Path(__file__).resolve().parents[1]

RUN = tiny(
    "collector.total_frames=2000",
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "replay.warm_start.frames=50",
    "eval.interval=200",
    "eval.episodes=1",
    "eval.max_steps=30",
    "checkpoint.interval=50",
    "checkpoint.keep_last=2",
)
# RNAC-IPM's PPO loop: a checkpoint after every 128-frame batch (2 epochs of 2 minibatches each)
PPO_RUN = tiny_ppo(
    "collector.total_frames=2560",
    "algorithm.ppo.epochs=2",
    "eval.interval=512",
    "checkpoint.interval=128",
    "checkpoint.keep_last=2",
    "logging.log_interval=256",
)


def _finish(proc: subprocess.Popen, timeout: float = 300) -> tuple[int, str]:
    _, err = proc.communicate(timeout=timeout)
    return proc.returncode, err


def _wait_for_checkpoint(
    path: Path,
    proc: subprocess.Popen,
    newer_than: set[str] = frozenset(),
    timeout: float = 120,
    min_frames: int = 0,
) -> bool:
    """Wait for a checkpoint not in `newer_than` at `min_frames` or later."""
    new = lambda: any(int(n[5:-3]) >= min_frames for n in checkpoints(path) - set(newer_than))  # noqa: E731
    return wait_for(new, proc, timeout)


def _results(run: Path) -> dict[str, str]:
    """Every metric file and the evaluation/rank records, as text (timing fields left out)."""
    root = run / "metrics" / "scalars"
    out = {
        f"metrics/{p.relative_to(root).as_posix()}": p.read_text()
        for p in sorted(root.rglob("*.csv"))
        if p.relative_to(root).parts[0] != "time"
    }  # time/fps: wall clock
    assert "metrics/rollout/ep_rew_mean.csv" in out
    # SB3's wide progress.csv agrees with the per-metric files after every resume (timing columns left out)
    progress = pd.read_csv(run / "metrics" / "progress.csv")
    assert list(progress.columns[:1]) == ["time/total_timesteps"] and "time/time_elapsed" in progress
    assert "eval/mean_ep_length" in progress and "eval/mean_reward" in progress
    timing = [c for c in progress.columns if c.startswith("time/") and c != "time/total_timesteps"]
    out["metrics/progress.csv"] = progress.drop(columns=timing).to_csv(index=False)
    out["eval.csv"] = (run / "eval.csv").read_text()
    if (run / "ranks.json").is_file():  # rank records (AdaRL); the PPO loop has none
        out["ranks.json"] = (run / "ranks.json").read_text()
    summary = json.loads((run / "summary.json").read_text())
    for k in ("wall_time_s", "updates_per_s"):
        summary.pop(k)
    out["summary.json"] = json.dumps(summary, sort_keys=True)
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    "recipe, base, extra, ref_extra",
    [
        ("quickstart", RUN, [], []),
        ("quickstart", RUN, ["collector.overlap=process"], ["collector.overlap=thread"]),
        ("baselines/hopper_rnac_ipm", PPO_RUN, [], []),
        ("baselines/hopper_sac_restarts", RUN, [], []),
    ],
    ids=["default", "overlap", "ppo", "restarts"],
)
def test_kill_9_at_random_moments_then_resume_matches_an_uninterrupted_run(tmp_path, recipe, base, extra, ref_extra):
    # "overlap": the killed run collects in a worker process (killed with it), the reference in a thread; both
    # overlap modes must give the very same run. "ppo": the RNAC baselines' loop (same BaseTrainer resume).
    # "restarts": the sac_restarts control (events that restart the LR and refill the buffer, truncating nothing).
    seed = int(os.environ.get("ADARL_KILL_SEED", random.randrange(10**6)))
    rng = random.Random(seed)
    ref, killed = tmp_path / "reference", tmp_path / "killed"
    run = [*base, *extra]
    reference = start_adarl("run", recipe, *base, *ref_extra, "-o", str(ref), "--quiet")  # beside the killed one

    # One kill in each fifth of the run's first three quarters, at a random frame: the kill waits for the first new
    # checkpoint at or past that frame (the process is past start-up, training), then a random delay lands it
    # anywhere in the training loop. Frame targets, not wall-clock delays alone: a slow (loaded) or fast machine
    # moves the run on by different amounts in the same delay, and five delays could carry the run to its end
    # (CI once killed a run after its last checkpoint, leaving nothing for the next kill).
    total = int(next(a for a in run if a.startswith("collector.total_frames=")).split("=")[1])
    lo, hi = total // 20, total * 3 // 4
    targets = [rng.randrange(lo + i * (hi - lo) // 5, lo + (i + 1) * (hi - lo) // 5) for i in range(5)]
    kills = []
    proc = start_adarl("run", recipe, *run, "-o", str(killed), "--quiet")
    for target in targets:
        seen = (
            {p.name for p in (killed / "checkpoints").glob("ckpt-*.pt")} if (killed / "checkpoints").is_dir() else set()
        )
        reached = _wait_for_checkpoint(killed, proc, newer_than=seen if kills else set(), min_frames=target)
        assert reached, (
            f"seed {seed}: no checkpoint at {target}+ frames after kills {kills}: {proc.communicate()[1][-3000:]}"
        )
        time.sleep(rng.uniform(0.0, 0.3))
        assert proc.poll() is None, f"seed {seed}: the run ended before its kill at {target}+ frames (kills {kills})"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        kills.append(sorted(p.name for p in (killed / "checkpoints").glob("ckpt-*.pt"))[-1])
        proc = start_adarl("resume", str(killed), "--quiet")
    rc, err = _finish(proc)
    assert rc == 0, f"seed {seed}: {err[-3000:]}"
    assert len(kills) == 5, f"seed {seed}: {kills}"
    rc, err = _finish(reference)
    assert rc == 0, err[-3000:]

    want, got = _results(ref), _results(killed)
    assert set(want) == set(got), f"seed {seed}: metric files differ: {set(want) ^ set(got)}"
    for name in want:  # bit-identical, not approximately equal
        assert got[name] == want[name], f"seed {seed}, kills after {kills}: {name} differs from the uninterrupted run"


@pytest.mark.slow
def test_sigterm_saves_a_checkpoint_and_exits_cleanly(tmp_path):
    run = tmp_path / "run"
    proc = start_adarl("run", "quickstart", *RUN, "checkpoint.interval=10000", "-o", str(run), "--quiet")
    assert _wait_for_checkpoint(run, proc), proc.communicate()[1][-3000:]  # the frame-0 checkpoint: training began
    updates = run / "metrics" / "scalars" / "train" / "n_updates.csv"
    end = time.monotonic() + 120  # an event, not a clock: the first logged update (past the random frames)
    while not (updates.is_file() and updates.read_text().count("\n") >= 2) and proc.poll() is None:
        assert time.monotonic() < end, "no update logged in 120 s"
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    rc, err = _finish(proc, timeout=120)
    assert rc == 128 + signal.SIGTERM, err[-3000:]
    assert "SIGTERM" in err and "adarl resume" in err and "Traceback" not in err
    ckpts = sorted((run / "checkpoints").glob("ckpt-*.pt"))
    frames = int(ckpts[-1].stem.split("-")[1])
    assert frames > 0, "SIGTERM saved no new checkpoint"
    rc, err = _finish(start_adarl("resume", str(run), "--quiet"))
    assert rc == 0, err[-3000:]
    assert json.loads((run / "summary.json").read_text())["frames"] >= 2000
