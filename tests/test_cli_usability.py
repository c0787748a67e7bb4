"""The `adarl` command as a new user meets it: options anywhere, --version, a quick --help, a light `import adarl`,
a clear error for an unavailable device, and quiet meaning quiet (issue 20)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from _helpers import adarl

REPO = Path(__file__).resolve().parents[1]
HEAVY = (
    "torch",
    "torchrl",
    "tensordict",
    "mujoco",
    "gymnasium",
    "pydantic",
    "omegaconf",
    "matplotlib",
    "pandas",
    "scipy",
)


def _python(code: str, cwd: Path | None = None, timeout: int = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-c", code], cwd=cwd or REPO, env=env, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.parametrize(
    "argv, recipe, output, overrides",
    [
        (["run", "quickstart", "-o", "DIR", "seed=1"], "quickstart", "DIR", ["seed=1"]),
        (["run", "-o", "DIR", "quickstart", "seed=1"], "quickstart", "DIR", ["seed=1"]),
        (
            ["run", "quickstart", "seed=1", "--quiet", "rank.beta=0.9", "--output", "DIR"],
            "quickstart",
            "DIR",
            ["seed=1", "rank.beta=0.9"],
        ),
        (["run", "quickstart", "seed=1", "rank.beta=0.9"], "quickstart", None, ["seed=1", "rank.beta=0.9"]),
    ],
)
def test_options_and_overrides_in_any_order(argv, recipe, output, overrides):
    from adarl.cli import build_parser

    args = build_parser().parse_args(argv)
    assert (args.recipe, args.output, args.overrides) == (recipe, output, overrides)


def test_unknown_option_still_refused(capsys):
    from adarl.cli import build_parser

    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["run", "quickstart", "--bogus", "seed=1"])
    assert exc.value.code == 2
    assert "--bogus" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, typo, meant, usage",
    [
        (["run", "quickstart", "--ouput", "x"], "--ouput", "--output", "usage: adarl run "),
        (["resume", "runs/x", "--chekpoint", "latest"], "--chekpoint", "--checkpoint", "usage: adarl resume "),
        (["eval", "runs/x", "--episdoes=3"], "--episdoes", "--episodes", "usage: adarl eval "),
    ],
)
def test_a_mistyped_option_gets_the_subcommands_usage_and_a_suggestion(capsys, argv, typo, meant, usage):
    """Issue 31, point 5: not the top-level usage and "unrecognized arguments"."""
    from adarl.cli import build_parser

    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(usage), err
    assert f"unrecognized option {typo!r}; did you mean {meant!r}?" in err, err


def _without_package(monkeypatch, *names):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in names else real(name, *a))
    for name in names:  # `import ray` fails too, as where it is not installed
        monkeypatch.setitem(sys.modules, name, None)


def test_a_missing_logging_extra_is_bad_input_and_leaves_no_runs_folder(tmp_path, monkeypatch, capsys):
    from adarl.cli import main

    _without_package(monkeypatch, "wandb")
    monkeypatch.chdir(tmp_path)
    assert main(["run", "quickstart", "logging.backends=[csv,wandb]", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'adarl[wandb]'" in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []  # no runs/ folder, empty or not


def test_a_missing_launcher_extra_is_bad_input_and_writes_nothing(tmp_path, monkeypatch, capsys):
    from adarl.cli import main

    _without_package(monkeypatch, "ray", "submitit")
    for launcher, extra in (("ray", "ray"), ("submitit", "slurm")):
        out = tmp_path / launcher
        argv = ["experiment", str(REPO / "recipes/experiments/cartpole_rank_sweep.yaml"), "-o", str(out)]
        assert main([*argv, "--launcher", launcher, "--no-live"]) == 2
        assert f"pip install 'adarl[{extra}]'" in capsys.readouterr().err
        assert not out.exists()


def test_show_takes_overrides_after_the_recipe():
    proc = adarl("show", "quickstart", "seed=7", "rank.beta=0.9")
    assert proc.returncode == 0, proc.stderr
    assert "seed: 7" in proc.stdout and "beta: 0.9" in proc.stdout


def test_version():
    proc = adarl("--version")
    assert proc.returncode == 0
    from adarl import __version__

    assert proc.stdout.strip() == f"adarl {__version__}"


def test_help_imports_nothing_heavy_and_answers():
    """--help is fast because it imports none of torch, TorchRL, TensorDict, gymnasium or MuJoCo (checked on the
    modules it loads, an event, not on a clock: a timed window fails on a loaded machine)."""
    code = (
        "import sys, adarl.cli\n"
        "p = adarl.cli.build_parser(); p.format_help()\n"
        "for name in ('run', 'play', 'eval', 'bench', 'experiment'):\n"
        "    p._subparsers._group_actions[0].choices[name].format_help()\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))"
    )
    proc = _python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]", f"--help imported {proc.stdout.strip()}"
    proc = adarl("--help")
    assert proc.returncode == 0 and "usage: adarl" in proc.stdout


def test_import_adarl_is_light_and_names_load_on_use():
    proc = _python(
        "import sys, adarl\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))\n"
        "from adarl import LowRankLinear, load_recipe, load_policy, AdaRLError\n"
        "assert set(adarl.__all__) <= set(dir(adarl))\n"
        "print(LowRankLinear.__module__, load_policy.__module__)"
    )
    assert proc.returncode == 0, proc.stderr
    heavy, modules = proc.stdout.strip().splitlines()
    assert heavy == "[]"
    assert modules == "adarl.core.lowrank adarl.runtime.policy"
    proc = _python("import adarl; adarl.nope")
    assert "has no attribute 'nope'" in proc.stderr


def test_public_namespace_is_all_plus_submodules():
    """``dir(adarl)`` names ``__all__`` and the subpackages imported, nothing of the module's own making
    (``annotations``, ``importlib``; issue 31, point 6)."""
    proc = _python(
        "import types, adarl, adarl.cli\n"
        "from adarl import LowRankLinear\n"
        "public = {n for n in dir(adarl) if not n.startswith('_')}\n"
        "subs = {n for n, v in vars(adarl).items() if isinstance(v, types.ModuleType) and n[0] != '_'}\n"
        "assert subs and all(getattr(adarl, n).__name__ == 'adarl.' + n for n in subs), subs\n"
        "assert public == set(adarl.__all__) | subs, sorted(public ^ (set(adarl.__all__) | subs))\n"
        "assert not {'annotations', 'importlib'} & {n for n in vars(adarl)}\n"
    )
    assert proc.returncode == 0, proc.stderr


def test_unavailable_device_is_one_clear_line(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: device=cuda is available here")
    out = tmp_path / "run"
    proc = adarl("run", "quickstart", "device=cuda", "-o", str(out), "--quiet", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert "device 'cuda' is not available" in proc.stderr and "allowed here: 'cpu'" in proc.stderr
    assert not out.exists()


def test_device_index_beyond_the_visible_gpus(monkeypatch):
    import torch

    from adarl.errors import AdaRLValueError
    from adarl.runtime.builders import check_device

    assert check_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert check_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(
        AdaRLValueError,
        match=r"device 'cuda:3' is not available: this machine has 2 CUDA .*"
        r"'cpu', 'cuda', 'cuda:0', 'cuda:1'",
    ):
        check_device("cuda:3")


@pytest.mark.parametrize("argv", [["recipes"], ["show", "quickstart"]])
def test_a_closed_output_pipe_ends_the_command_quietly(argv):
    """`adarl recipes | head` once `head` has exited: as a Unix tool killed by SIGPIPE, no traceback (before: a
    BrokenPipeError traceback and exit 1). The pipe's read end is closed before the command starts, so its first
    write fails whatever the buffering."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        done = subprocess.run(
            [sys.executable, "-m", "adarl.cli", *argv], cwd=REPO, env=env, stdout=write_end, stderr=subprocess.PIPE
        )
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr.decode()) == (128 + 13, "")


def test_output_into_a_pipe_is_written_line_by_line():
    """`adarl experiment ... | tee log`: each progress line reaches the pipe when printed (Python's default there is
    8 KB blocks: progress appeared in bursts, and a reader that had gone was noticed only when a block filled). The
    command's stdout is a pipe; what it prints after `main` returns reaches the reader while it still runs."""
    script = (
        "import sys; from adarl.cli import main; main(['recipes']); "
        "print('after main'); print(sys.stdout.line_buffering, file=sys.stderr); sys.stdin.read()"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=REPO,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stderr.readline() == "True\n"  # waits for the event, no clock
        lines = []
        while not lines or lines[-1] != "after main\n":  # read while the process waits on its stdin
            line = proc.stdout.readline()
            assert line, "".join(lines)[-500:]
            lines.append(line)
        assert proc.poll() is None
    finally:
        proc.stdin.close()
        proc.wait(timeout=60)


def test_a_broken_pipe_that_is_not_stdouts_is_a_real_failure(monkeypatch):
    """Only a closed stdout is taken for the reader going away: a BrokenPipeError from anything else (a worker's
    pipe) propagates, never a quiet exit."""
    import adarl.cli as cli

    def broken(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cli, "cmd_recipes", broken)
    with pytest.raises(BrokenPipeError):
        cli.main(["recipes"])


def test_bad_input_is_refused_before_torch_is_imported(tmp_path):
    """A wrong recipe key, an output name the file system cannot hold, a run folder that is not there, an override
    resume does not take, an unknown budget: each refused (exit 2, its one line) before torch, TorchRL or TensorDict
    is imported, so the user hears at once, not after their seconds of import; an experiment's driver, which trains
    nothing itself, plans a dry run without them too."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "recipe.yaml").write_text(
        subprocess.run(
            [sys.executable, "-m", "adarl.cli", "show", "quickstart"],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    )
    spec = tmp_path / "exp.yaml"
    spec.write_text("kind: experiment\nname: x\nrecipe: quickstart\nseeds: [0, 1]\n")
    commands = [
        (["run", "quickstart", "rank.betta=0.9", "-o", str(tmp_path / "a")], 2, "unknown key 'rank.betta'"),
        (["run", "quickstart", "-o", str(tmp_path / ("b" * 300))], 2, "at most 255 bytes"),
        (["resume", str(tmp_path / "nope")], 2, "does not exist"),
        (["eval", str(tmp_path / "nope")], 2, "does not exist"),
        (["resume", str(run), "rank.beta=0.5"], 2, "cannot change 'rank.beta'"),
        (["experiment", str(spec), "--budget", "nope", "--no-live"], 2, "budget"),
        (["experiment", str(spec), "-o", str(tmp_path / "e"), "--no-live", "--dry-run"], 0, "2 runs"),
    ]
    code = (
        "import contextlib, io, json, sys\n"
        "from adarl.cli import main\n"
        f"for argv in {[c for c, _, _ in commands]!r}:\n"
        "    err, out = io.StringIO(), io.StringIO()\n"
        "    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):\n"
        "        rc = main(argv)\n"
        "    heavy = sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'torchrl', 'tensordict'})\n"
        "    print(json.dumps([rc, heavy, err.getvalue() + out.getvalue()]))\n"
    )
    proc = _python(code, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(results) == len(commands), proc.stdout[-3000:]
    for (argv, status, words), (rc, heavy, said) in zip(commands, results):
        assert rc == status and words in said, (argv, rc, said)
        assert heavy == [], f"adarl {' '.join(argv)} imported {heavy} before it answered"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml", "run"]  # nothing written
