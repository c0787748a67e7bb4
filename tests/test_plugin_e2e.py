"""A user's own TorchRL loss, in a package outside adarl, and a rank rule in a local module beside the recipe, run
from a recipe (docs/custom-loss.md, issue 29.5).

The test writes a small plugin package (an RNAC-IPM-style robust SAC: ``SACLoss`` with its TD target lowered by
``kappa * ||theta_critic||``, registered as ``robust_sac`` through the ``adarl.plugins`` entry-point group),
installs it with pip into a folder of its own (``pip install --target``, so the test venv is left as it was) and
puts that folder on ``PYTHONPATH`` of the ``adarl`` commands it runs from another folder: ``adarl show``,
``adarl run`` killed with SIGKILL and ``adarl resume``d, and a two-seed ``adarl experiment`` (on Ray workers when
Ray is installed). At each step the
loss's own metric (``train/target_shift``, ``kappa * ||theta||``) must be logged; without the package, resuming
the run is refused with a message naming the algorithm, and nothing in the run folder changes. The same recipe lists a
local module (``plugins: [my_rule]``, not packaged) whose rank rule the run uses: every run folder records its path
and sha256, and once the module changed or went missing, resume and eval refuse the run by name. One run covers
both kinds of plugin: each end-to-end run here costs tens of seconds.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import signal
import subprocess
import textwrap
from pathlib import Path

import pytest
from _helpers import adarl, adarl_calls, checkpoints, install_plugin, start_adarl, tiny, wait_for

REPO = Path(__file__).resolve().parents[1]

PLUGIN = '''
"""An RNAC-IPM-style robust SAC for adarl: the TD target minus kappa * ||theta_critic||."""
import torch
from pydantic import BaseModel, ConfigDict, Field
from torchrl.objectives import ClipPPOLoss

from adarl import TargetShiftSACLoss, register_algorithm


class RobustSACOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kappa: float = Field(1e-3, ge=0, description="IPM radius: TD-target shift per unit of ||theta_critic||")


@register_algorithm("robust_sac", options=RobustSACOptions, description="SAC with an IPM-shifted TD target")
class RobustSACLoss(TargetShiftSACLoss):
    def __init__(self, *args, kappa: float = 1e-3, **kwargs):
        super().__init__(*args, **kwargs)
        self.kappa = kappa

    def target_shift(self) -> torch.Tensor:
        params = self.qvalue_network_params.flatten_keys().values()
        return self.kappa * torch.stack([p.detach().pow(2).sum() for p in params]).sum().sqrt()


class NormPenaltyOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    weight: float = Field(1e-3, ge=0, description="weight of the critic's squared parameter norm in the loss")


@register_algorithm("norm_ppo", base="ppo", options=NormPenaltyOptions, description="PPO + a critic norm penalty")
class NormPenaltyPPOLoss(ClipPPOLoss):
    def __init__(self, *args, weight: float = 1e-3, **kwargs):
        super().__init__(*args, **kwargs)
        self.weight = weight

    def forward(self, tensordict):
        out = super().forward(tensordict)
        sq = torch.stack([p.pow(2).sum() for p in self.critic_network.parameters()]).sum()
        out.set("loss_norm", self.weight * sq)  # summed into the total (TorchRL's loss_* convention)
        out.set("critic_sq_norm", sq.detach())  # a metric: logged as train/critic_sq_norm
        return out
'''

PYPROJECT = """
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "adarl-robust-sac"
version = "0.1.0"

[project.entry-points."adarl.plugins"]
robust_sac = "adarl_robust_sac"

[tool.setuptools]
packages = ["adarl_robust_sac"]
"""

LOCAL_RULE = '''
"""Eq. 10 under a name of its own, from a module beside the recipe (not packaged), registered at import."""
from adarl import register_rank_rule
from adarl.core.rank import EnergyRule


@register_rank_rule("local_energy", description="Eq. 10 from a module beside the recipe")
class LocalEnergyRule(EnergyRule):
    name = "local_energy"
'''

# Hopper, tiny: 600 frames, a checkpoint every 50, one rank event
TINY = tiny(
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "rank.interval=200",
    "replay.size=600",
    "replay.warm_start.frames=50",
    "eval.episodes=1",
    "eval.max_steps=20",
    "checkpoint.interval=50",
    "checkpoint.keep_last=2",
    "logging.log_interval=100",
)


@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> Path:
    """The plugin package, pip-installed into a folder of its own; returns that folder."""
    return install_plugin(tmp_path_factory.mktemp("plugin"), "adarl_robust_sac", PLUGIN, PYPROJECT)


def _target_shift(run: Path) -> list[float]:
    path = run / "metrics" / "scalars" / "train" / "target_shift.csv"
    assert path.is_file(), f"the custom loss's metric was not logged: {sorted(p.name for p in path.parent.glob('*'))}"
    with path.open() as f:
        return [float(row[-1]) for row in csv.reader(f) if row and row != ["step", "value"]]


def _error_line(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    (line,) = [line for line in proc.stderr.splitlines() if line.startswith("adarl: error:")]
    return line


def _snapshot(run: Path) -> dict[str, bytes]:
    return {p.relative_to(run).as_posix(): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_a_plugin_loss_runs_resumes_and_goes_into_an_experiment(plugin: Path, tmp_path: Path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    recipe = elsewhere / "robust_hopper.yaml"
    (elsewhere / "my_rule.py").write_text(textwrap.dedent(LOCAL_RULE))
    recipe.write_text(
        "extends: quickstart\nname: robust_hopper\nplugins: [my_rule]\nrank: {rule: local_energy}\n"
        "algorithm:\n  name: robust_sac\n  options: {kappa: 0.002}\n"
    )

    # show: the plugin's options are recipe keys, validated, with their defaults spelled out (the five command lines
    # in one process: each pays the plugin's torch import otherwise)
    bads = (
        ("algorithm.options.kapa=1", ["kapa", "kappa"]),
        ("algorithm.options.kappa=-1", ["kappa", "greater than or equal to 0"]),
        ("algorithm.options.kappa=big", ["kappa", "number"]),
        ("algorithm.name=robust_sca", ["robust_sca", "robust_sac", "adarl.plugins"]),
    )
    shown, *refused = adarl_calls(
        ("show", str(recipe)), *[("show", str(recipe), bad) for bad, _ in bads], site=plugin, cwd=elsewhere
    )
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert "name: robust_sac" in shown.stdout and "kappa: 0.002" in shown.stdout
    for (bad, words), proc in zip(bads, refused, strict=True):
        assert proc.returncode != 0 and all(w in proc.stderr for w in words), (bad, proc.stderr[-2000:])
    # without the package the name is unknown, and the error says how to get one
    proc = adarl("show", str(recipe), cwd=elsewhere)
    assert proc.returncode != 0 and "robust_sac" in proc.stderr and "adarl.plugins" in proc.stderr

    # run, killed with SIGKILL once it has checkpointed
    run = tmp_path / "run"
    proc = start_adarl("run", str(recipe), *TINY, "-o", str(run), "--quiet", cwd=elsewhere, site=plugin)
    wait_for(lambda: len(checkpoints(run)) >= 2, proc, timeout=300)
    killed = proc.poll() is None
    if killed:
        proc.send_signal(signal.SIGKILL)
    _, err = proc.communicate(timeout=60)
    assert killed, f"the run ended before it could be killed: {err[-2000:]}"
    text = (run / "recipe.yaml").read_text()
    assert "name: robust_sac" in text and "kappa: 0.002" in text  # what the run used, recorded
    assert "rule: local_energy" in text
    provenance = json.loads((run / "plugins.json").read_text())
    [module] = provenance["modules"]
    assert module["module"] == "my_rule" and module["path"] == str(elsewhere / "my_rule.py") and module["sha256"]

    # resume without the plugin: refused, naming the algorithm; nothing in the run folder changes
    before = _snapshot(run)
    proc = adarl("resume", str(run), "--quiet", cwd=elsewhere)
    assert proc.returncode != 0
    assert "robust_sac" in proc.stderr and "adarl.plugins" in proc.stderr, proc.stderr[-2000:]
    assert "'adarl-robust-sac' 0.1.0" in proc.stderr and "pip install adarl-robust-sac" in proc.stderr
    assert _snapshot(run) == before

    # resume with it: the run finishes as the same algorithm, on the fused update (a TD-target shift only)
    proc = adarl("resume", str(run), "--quiet", site=plugin, cwd=elsewhere)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "FusedFallbackWarning" not in proc.stderr and "not the fused update" not in proc.stderr
    shifts = _target_shift(run)
    assert shifts and all(s > 0 for s in shifts)
    assert (run / "summary.json").is_file()

    # a two-seed experiment of the same recipe
    spec = elsewhere / "robust_seeds.yaml"
    spec.write_text(
        "kind: experiment\nname: robust_seeds\nrecipe: "
        + str(recipe)
        + "\noverrides: ["
        + ", ".join(o for o in TINY if not o.startswith("checkpoint"))
        + ", checkpoint.interval=300]\nseeds: [0, 1]\n"
    )
    out = tmp_path / "experiment"
    # on Ray workers when Ray is installed (CI installs it): the plugin reaches them through the environment
    launcher = ["--launcher", "ray"] if importlib.util.find_spec("ray") else ["--workers", "1"]
    proc = adarl("experiment", str(spec), "-o", str(out), *launcher, "--no-live", site=plugin, cwd=elsewhere)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    runs = sorted(p.parent for p in out.rglob("summary.json") if (p.parent / "recipe.yaml").is_file())
    assert len(runs) == 2, sorted(p.as_posix() for p in out.rglob("*"))[:50]
    for r in runs:
        assert "name: robust_sac" in (r / "recipe.yaml").read_text()
        assert _target_shift(r)
        assert json.loads((r / "summary.json").read_text())["rank_events"] >= 1  # the local rule ran there too
        [recorded] = json.loads((r / "plugins.json").read_text())["modules"]
        assert recorded["sha256"] == module["sha256"] and recorded["path"] == module["path"]

    # the local module changed, then went missing: resume and eval refuse the run by name, nothing written
    before = _snapshot(run)
    (elsewhere / "my_rule.py").write_text(textwrap.dedent(LOCAL_RULE) + "\nCHANGED = True\n")  # code: a comment is none
    for proc in adarl_calls(("resume", str(run)), ("eval", str(run)), site=plugin, cwd=elsewhere):
        line = _error_line(proc)
        assert "local plugin module 'my_rule'" in line and "has changed" in line, line
    (elsewhere / "my_rule.py").unlink()
    line = _error_line(adarl("resume", str(run), "--quiet", site=plugin, cwd=elsewhere))
    assert "local plugin module 'my_rule'" in line and "missing" in line, line
    assert _snapshot(run) == before


@pytest.mark.slow
def test_a_plugin_loss_on_the_ppo_loop_runs_and_logs_its_own_terms(plugin: Path, tmp_path: Path):
    """base='ppo': the plugin's loss gets ClipPPOLoss's arguments plus its options; its extra loss_* entry is part of
    the total and logged, its other scalars are logged as train/<key>."""
    recipe = tmp_path / "norm_ppo.yaml"
    recipe.write_text(
        f"extends: {REPO / 'recipes' / 'baselines' / 'ppo_base.yaml'}\nname: norm_ppo\nenv: {{id: Hopper-v5}}\n"
        "algorithm:\n  name: norm_ppo\n  options: {weight: 0.01}\n"
    )
    run = tmp_path / "run"
    tiny = ["collector.total_frames=256", "collector.frames_per_batch=128", "algorithm.ppo.epochs=1"]
    tiny += ["eval.interval=256", "eval.episodes=1", "eval.max_steps=20", "checkpoint.interval=128"]
    tiny += ["logging.log_interval=128"]
    proc = adarl("run", str(recipe), *tiny, "-o", str(run), "--quiet", site=plugin, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    scalars = run / "metrics" / "scalars" / "train"
    for name in ("loss_norm", "critic_sq_norm", "policy_gradient_loss", "value_loss"):  # ClipPPOLoss's: SB3's names
        assert (scalars / f"{name}.csv").is_file(), sorted(p.name for p in scalars.glob("*"))
    with (scalars / "critic_sq_norm.csv").open() as f:
        assert all(float(row[-1]) > 0 for row in csv.reader(f) if row and row != ["step", "value"])
    assert '"package": "adarl-robust-sac"' in (run / "plugins.json").read_text()
