"""What many test files share: tiny-run overrides, ``adarl`` in a subprocess, waiting on one, installed plugins.

* :func:`tiny` / :func:`tiny_ppo`: the overrides of a tiny run (Hopper, seconds): one base list each; a test that
  needs other values passes them (``tiny("collector.total_frames=1600", "eval.episodes=1")`` replaces those keys in
  place, a key the base lacks is appended) or drops keys (``drop=("rank.interval",)``).
* :func:`adarl` / :func:`start_adarl`: ``python -m adarl.cli ARGS`` (one torch thread, this checkout first on
  ``PYTHONPATH``, an installed plugin's folder after it), run to its end or started in the background;
  :func:`adarl_calls`: several quick ``adarl`` command lines (show, eval, export, refusals) one after another in one
  such process, each with its own exit status and output, so that the torch import is paid once;
  :func:`wait_for` polls a condition while such a process runs; :func:`checkpoints` names a run's checkpoints.
* :func:`install_plugin`: a plugin package pip-installed into a folder of its own (``pip install --target``, so the
  test venv is left as it was); put that folder on ``PYTHONPATH`` (``site=``) to use it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: the tiny SAC run: 600 frames, rank events every 150 updates, evaluations and checkpoints every 300 frames
TINY = (
    "collector.total_frames=600",
    "collector.init_random_frames=200",
    "collector.frames_per_batch=100",
    "algorithm.batch_size=32",
    "rank.interval=150",
    "replay.size=2000",
    "replay.warm_start.frames=100",
    "lr_schedule.warmup_steps=20",
    "eval.interval=300",
    "eval.episodes=2",
    "eval.max_steps=50",
    "checkpoint.interval=300",
)
#: with :func:`tiny`: 1600 frames, rank events every 400 updates (at least two; they truncate the actor's second
#: layer): the CLI, policy and export tests' run
RANK_EVENTS = (
    "collector.total_frames=1600",
    "collector.init_random_frames=300",
    "algorithm.batch_size=64",
    "rank.interval=400",
    "replay.size=5000",
    "lr_schedule.warmup_steps=50",
    "eval.interval=800",
    "eval.max_steps=60",
    "checkpoint.interval=500",
)
#: with :func:`tiny`: N = 1200 frames, a multiple of the batch (100), the evaluation (600), logging (200) and
#: checkpoint (400) intervals: the continued-run and run-log tests' run
INTERVALS_1200 = (
    "collector.total_frames=1200",
    "collector.init_random_frames=300",
    "algorithm.batch_size=64",
    "rank.interval=300",
    "replay.size=5000",
    "lr_schedule.warmup_steps=50",
    "eval.interval=600",
    "eval.episodes=1",
    "eval.max_steps=40",
    "checkpoint.interval=400",
    "logging.log_interval=200",
)
#: the tiny PPO run: two batches of 128 frames, one epoch
TINY_PPO = (
    "collector.total_frames=256",
    "collector.frames_per_batch=128",
    "algorithm.ppo.epochs=1",
    "eval.interval=256",
    "eval.episodes=1",
    "eval.max_steps=30",
    "checkpoint.interval=256",
)


#: the device the update tests build their components on: ``ADARL_TEST_DEVICE=cuda`` runs them on a GPU (issue 49's
#: GPU check, docs/reports/issue49/gpu_check.sh); unset, the CPU (CI)
TEST_DEVICE = os.environ.get("ADARL_TEST_DEVICE", "cpu")

#: components built, not trained (the update tests): quickstart at 2000 frames, a 2000-frame buffer, batch 64
BUILT = (
    "collector.total_frames=2000",
    "collector.init_random_frames=500",
    "replay.size=2000",
    "algorithm.batch_size=64",
    *((f"device={TEST_DEVICE}",) if TEST_DEVICE != "cpu" else ()),
)


def filled_sac(*overrides: str):
    """quickstart's SAC components on TorchRL's path (``max_grad_norm`` 1) with 200 frames in the buffer, a
    non-trivial alpha and targets that differ from the online critics, and one sampled batch: what the fused update
    is compared with. Returns ``(components, batch)``."""
    import torch

    from adarl.runtime.builders.sac import build_sac_components
    from adarl.runtime.config import load_recipe

    recipe = load_recipe("quickstart", [*BUILT, "algorithm.fused=false", "algorithm.max_grad_norm=1.0", *overrides])
    c = build_sac_components(recipe)
    torch.manual_seed(3)
    c.replay_buffer.extend(c.env.rollout(200, break_when_any_done=False).reshape(-1))
    with torch.no_grad():
        c.modules.loss.log_alpha.fill_(-0.7)  # a non-trivial alpha and alpha loss
        for p in c.modules.loss.target_qvalue_network_params.flatten_keys().values():
            p.add_(0.01 * torch.randn_like(p))  # targets differ from the online critics
    return c, c.replay_buffer.sample()


def _merged(base: tuple[str, ...], overrides: tuple[str, ...], drop) -> list[str]:
    out = {o.split("=", 1)[0]: o for o in base}
    for o in overrides:
        out[o.split("=", 1)[0]] = o  # a key of the base keeps its place; a new one goes last
    unknown = set(drop) - set(out)
    assert not unknown, f"drop names keys the list does not hold: {sorted(unknown)}"
    return [o for k, o in out.items() if k not in drop]


def tiny(*overrides: str, drop=()) -> list[str]:
    """:data:`TINY` with ``overrides`` (``key=value``) in place of its values for those keys, less ``drop``."""
    return _merged(TINY, overrides, drop)


def tiny_ppo(*overrides: str, drop=()) -> list[str]:
    """:data:`TINY_PPO` with ``overrides`` in place of its values for those keys, less ``drop``."""
    return _merged(TINY_PPO, overrides, drop)


def adarl_env(site: Path | None = None) -> dict[str, str]:
    """The environment of an ``adarl`` subprocess: this checkout (and ``site``, an installed plugin's folder) on
    ``PYTHONPATH``, one torch/OpenMP thread, headless MuJoCo."""
    paths = [str(REPO)] + ([str(site)] if site is not None else [])
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(paths),
        "OMP_NUM_THREADS": "1",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }


def adarl(
    *args: str, cwd: Path | None = None, site: Path | None = None, timeout: float = 600, env: dict | None = None
) -> subprocess.CompletedProcess:
    """``adarl ARGS`` in a subprocess, run to its end; its output captured as text (``env``: variables to set)."""
    return subprocess.run(
        [sys.executable, "-m", "adarl.cli", *args],
        cwd=cwd or REPO,
        env={**adarl_env(site), **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


#: run by :func:`adarl_calls` in its subprocess: each command line as ``python -m adarl.cli`` runs it (``sys.argv``
#: set, ``main()`` called as ``sys.exit(main())`` would be), its stdout and stderr captured apart, its exit status
#: what the process's would be
_CALLS = """
import contextlib, io, json, sys, traceback
from adarl.cli import main

where, calls, results = sys.argv[1], json.loads(sys.argv[2]), []
for args in calls:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        sys.argv = [sys.argv[0], *args]
        try:
            code = main()
        except SystemExit as stop:
            code = stop.code
        except Exception:  # uncaught: as a process, the traceback on stderr and status 1
            traceback.print_exc()
            code = 1
        if code is not None and not isinstance(code, int):  # sys.exit("message"): printed, status 1
            print(code, file=sys.stderr)
            code = 1
    results.append({"args": args, "returncode": code or 0, "stdout": out.getvalue(), "stderr": err.getvalue()})
with open(where, "w") as fh:
    json.dump(results, fh)
"""


def adarl_calls(
    *calls: list[str] | tuple[str, ...],
    cwd: Path | None = None,
    site: Path | None = None,
    timeout: float = 600,
    env: dict | None = None,
) -> list[subprocess.CompletedProcess]:
    """Each of ``calls`` (``adarl`` command lines) run in turn, in ONE subprocess (the environment of :func:`adarl`):
    one :class:`~subprocess.CompletedProcess` each, as :func:`adarl` gives it (exit status, stdout, stderr).

    For quick commands whose outcome does not depend on a fresh process (``show``, ``eval``, ``export``, refusals
    before anything trains): a later call sees the modules an earlier one imported and the warnings it already
    showed. Not for training runs, signal or fault-injection tests, or checks of a warning."""
    import json
    import tempfile

    with tempfile.TemporaryDirectory(prefix="adarl-calls-") as tmp:
        results = Path(tmp) / "results.json"
        proc = subprocess.run(
            [sys.executable, "-c", _CALLS, str(results), json.dumps([list(c) for c in calls])],
            cwd=cwd or REPO,
            env={**adarl_env(site), **(env or {})},
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        assert proc.returncode == 0 and results.is_file(), proc.stdout[-2000:] + proc.stderr[-3000:]
        done = json.loads(results.read_text())
    assert len(done) == len(calls), done
    return [subprocess.CompletedProcess(["adarl", *r["args"]], r["returncode"], r["stdout"], r["stderr"]) for r in done]


def start_adarl(*args: str, cwd: Path | None = None, site: Path | None = None) -> subprocess.Popen:
    """``adarl ARGS`` in the background, to be stopped, killed or signalled at a moment a test waits for."""
    return subprocess.Popen(
        [sys.executable, "-m", "adarl.cli", *args],
        cwd=cwd or REPO,
        env=adarl_env(site),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for(condition, proc: subprocess.Popen, timeout: float = 300, poll: float = 0.05) -> bool:
    """Poll ``condition()`` (a file appearing) until it holds, ``proc`` ends (then: whether it holds now) or
    ``timeout`` seconds pass (generous: CI is loaded). Nothing is decided by the clock but the limit."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        if proc.poll() is not None:
            return bool(condition())
        time.sleep(poll)
    return False


def checkpoints(run: Path) -> set[str]:
    """The names of a run folder's checkpoint files (``ckpt-<frames>.pt``)."""
    folder = run / "checkpoints"
    return {p.name for p in folder.glob("ckpt-*.pt")} if folder.is_dir() else set()


def install_plugin(root: Path, package: str, source: str, pyproject: str) -> Path:
    """The plugin package ``package`` (its ``__init__.py`` is ``source``, with ``pyproject``), pip-installed into a
    folder of its own under ``root``; returns that folder."""
    src = root / "src"
    (src / package).mkdir(parents=True)
    (src / package / "__init__.py").write_text(textwrap.dedent(source))
    (src / "pyproject.toml").write_text(textwrap.dedent(pyproject))
    site = root / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index", "-q"]
        + ["--target", str(site), str(src)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert (site / package).is_dir()
    return site
