"""The ``td3`` loop (issue 29, point 4): TorchRL's TD3Loss and DDPGLoss run from recipes with rank events, warm
start, exact resume and guards, as SAC does; a registered algorithm names its base, and a loss class that fits no
base is refused at registration with the list of bases.

The end-to-end test writes a TD3-based plugin package (a ``TD3Loss`` with an L2 penalty on the actor, registered as
``l2_td3`` on ``base="td3"`` through the ``adarl.plugins`` entry-point group), installs it with pip into a folder of
its own and runs it from a recipe through the ``adarl`` command: a run killed with SIGKILL twice (each time right
after a new checkpoint is written) and resumed ends with exactly the metrics, evaluations and rank records of an
uninterrupted run, through rank events; then a two-seed ``adarl experiment``.
"""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _helpers import adarl_env, checkpoints, install_plugin, start_adarl, tiny, wait_for
from torchrl.objectives import DDPGLoss, IQLLoss, SACLoss, TD3Loss

from adarl import plugins
from adarl.errors import AdaRLValueError, RecipeError
from adarl.runtime.builders.td3 import TD3Components, build_td3_components
from adarl.runtime.config import load_recipe
from adarl.runtime.guards import NonFiniteGuard
from adarl.runtime.trainers import OffPolicyTrainer, trainer_class
from adarl.runtime.update import DelayedActorStep

REPO = Path(__file__).resolve().parents[1]

# Hopper, tiny: updates from frame 100, a rank event every 150 updates (three of them), a checkpoint every 50 frames
TINY = tiny(
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "algorithm.update_after=100",
    "replay.size=600",
    "replay.warm_start.frames=50",
    "eval.episodes=1",
    "eval.max_steps=20",
    "checkpoint.interval=50",
    "checkpoint.keep_last=2",
    "logging.log_interval=100",
)


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setattr(plugins._algorithm, "_algorithms", dict(plugins._algorithm._algorithms))
    return plugins


# ---------------------------------------------------------------------------------------------------- registration
def test_a_loss_class_that_fits_no_base_is_refused_at_registration_with_the_list_of_bases(registered):
    bases = (
        r"'sac' \(SACLoss or CrossQLoss or REDQLoss and subclasses\); 'ppo' \(PPOLoss and subclasses\); "
        r"'td3' \(TD3Loss or DDPGLoss"
    )
    with pytest.raises(AdaRLValueError, match=rf"IQLLoss fits no base.*bases: {bases}.*docs/custom-loss.md"):
        plugins.register_algorithm("my_iql", IQLLoss, base="td3")
    # a TD3Loss registered without its base (the default is 'sac'): the base it fits is named
    with pytest.raises(AdaRLValueError, match=rf"TD3Loss runs on the 'td3' loop, not on 'sac'.*base='td3'.*{bases}"):
        plugins.register_algorithm("my_td3", TD3Loss)
    with pytest.raises(AdaRLValueError, match="SACLoss runs on the 'sac' loop, not on 'td3'"):
        plugins.register_algorithm("my_sac", SACLoss, base="td3")
    assert "my_iql" not in plugins.algorithm_names(load=False) and "my_td3" not in plugins.algorithm_names(load=False)

    class MyTD3(TD3Loss):
        pass

    class MyDDPG(DDPGLoss):
        pass

    plugins.register_algorithm("my_td3", MyTD3, base="td3")
    plugins.register_algorithm("my_ddpg", MyDDPG, base="td3")
    assert plugins.algorithm("my_td3").base == "td3" and plugins.bases_of(MyDDPG) == ["td3"]
    # a lazy "module:Class" path is checked when a run imports it
    plugins.register_algorithm("lazy_iql", "torchrl.objectives:IQLLoss", base="td3")
    with pytest.raises(AdaRLValueError, match="IQLLoss fits no base"):
        plugins.algorithm("lazy_iql").loss_class()


def test_td3_and_ddpg_are_shipped_algorithms_on_the_td3_loop():
    for name, loss in (("td3", TD3Loss), ("ddpg", DDPGLoss)):
        spec = plugins.algorithm(name)
        assert spec.base == "td3" and spec.loss_class() is loss
        recipe = load_recipe(f"baselines/hopper_{name}")
        assert recipe.algorithm.name == name and trainer_class(recipe) is OffPolicyTrainer
    assert load_recipe("baselines/hopper_ddpg").algorithm.td3.policy_update_delay == 1


def test_td3_recipe_keys_are_validated_with_did_you_mean():
    with pytest.raises(RecipeError, match=r"algorithm.td3.polcy_noise.*policy_noise"):
        load_recipe("baselines/hopper_td3", ["algorithm.td3.polcy_noise=0.1"])
    with pytest.raises(RecipeError, match=r"algorithm.td3.policy_update_delay"):
        load_recipe("baselines/hopper_td3", ["algorithm.td3.policy_update_delay=0"])
    with pytest.raises(RecipeError, match=r"algorithm.fused.*SAC's fast path.*'td3' loop.*allowed: 'auto' or false"):
        load_recipe("baselines/hopper_td3", ["algorithm.fused=true"])
    with pytest.raises(RecipeError, match=r"algorithm.name.*continuous-action env; CartPole-v1 is discrete"):
        load_recipe("baselines/hopper_td3", ["env.id=CartPole-v1", "env.perturbation.preset=none"])


# ---------------------------------------------------------------------------------------------------- the step
@pytest.mark.parametrize("name, delay", [("td3", 2), ("ddpg", 1)])
def test_the_actor_and_targets_move_every_delay_th_update_the_critic_every_update(name, delay):
    recipe = load_recipe(
        f"baselines/hopper_{name}",
        [*TINY, "rank.interval=3", "rank.rule=fixed", "rank.target_rank=8", "lr_schedule.warmup_steps=0"],
    )
    c = build_td3_components(recipe)
    try:
        assert isinstance(c, TD3Components) and isinstance(c.update, DelayedActorStep)
        assert type(c.collector).__name__ == "Collector"  # TorchRL's plain path: the lean collector is SAC's
        assert c.update.delay == delay
        batches = iter(c.collector)  # the replay buffer holds what the collector collects (the warm start's too)
        for _ in range(2):
            c.replay_buffer.extend(next(batches).reshape(-1))
        loss = c.modules.loss
        critic = "value_network" if name == "ddpg" else "qvalue_network"

        def snap():
            return {
                "actor": loss.actor_network_params.clone(),
                "critic": getattr(loss, f"{critic}_params").clone(),
                "target_actor": loss.target_actor_network_params.clone(),
                "target_critic": getattr(loss, f"target_{critic}_params").clone(),
            }

        def moved(a, b):
            return any(not torch.equal(x, y) for x, y in zip(a.values(True, True), b.values(True, True)))

        guard = NonFiniteGuard(c.guarded_parameters())  # the divergence guard checks the step, as SAC's
        assert {k.split(".")[0] for k in c.guarded_parameters()} == {"actor", "critic"}
        for n in range(2):  # before the rank event at the 3rd update: the shapes stay
            before = snap()
            out = c.update(guard, update=n)
            c.adapter.step()
            after = snap()
            actor_step = (n + 1) % delay == 0
            assert moved(before["critic"], after["critic"])
            assert moved(before["actor"], after["actor"]) == actor_step, (n, "actor")
            assert moved(before["target_actor"], after["target_actor"]) == actor_step, (n, "target actor")
            assert moved(before["target_critic"], after["target_critic"]) == actor_step, (n, "target critic")
            assert "loss_actor" in out and ("loss_qvalue" in out or "loss_value" in out)
        c.update(update=2)
        c.adapter.step()  # the rank event: every layer to rank 8, the warm start refills with the new policy
        assert len(c.adapter.history) == 1 and set(c.adapter.named_ranks.values()) == {8}
        assert c.warm_start.state_dict()["records"][-1]["frames_added"] == 50
        c.update(update=3)  # the step runs on the new shapes
    finally:
        c.close()


# ---------------------------------------------------------------------------------------------------- end to end
PLUGIN = '''
"""TD3 with an L2 penalty on the actor's parameters, for adarl's td3 loop."""
import torch
from pydantic import BaseModel, ConfigDict, Field
from torchrl.objectives import TD3Loss

from adarl import register_algorithm


class L2TD3Options(BaseModel):
    model_config = ConfigDict(extra="forbid")
    weight: float = Field(1e-4, ge=0, description="weight of the actor's squared parameter norm in the loss")


@register_algorithm("l2_td3", base="td3", options=L2TD3Options, description="TD3 + an actor L2 penalty")
class L2TD3Loss(TD3Loss):
    def __init__(self, *args, weight: float = 1e-4, **kwargs):
        super().__init__(*args, **kwargs)
        self.weight = weight

    def forward(self, tensordict):
        out = super().forward(tensordict)
        sq = torch.stack([p.pow(2).sum() for p in self.actor_network_params.flatten_keys().values()]).sum()
        out.set("loss_actor_l2", self.weight * sq)  # summed into the total (TorchRL's loss_* convention)
        out.set("actor_sq_norm", sq.detach())  # a metric: logged as train/actor_sq_norm
        return out
'''

LOAD_POLICY = """
import sys, torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from adarl import ExportedPolicy, export_policy, load_policy
actor = load_policy(sys.argv[1])
action = actor(TensorDict(observation=torch.randn(11)))["action"]
assert type(actor).__name__ == "TensorDictSequential" and action.shape == (3,) and action.abs().max() <= 1, action
# `adarl export`: the truncated actor as a program torch alone loads, the same deterministic action
result = export_policy(sys.argv[1], sys.argv[2])
assert result.metadata["policy"] == "deterministic_tanh", result.metadata
assert any(layer["rank"] < layer["max_rank"] for layer in result.metadata["layers"]), result.metadata  # truncated
obs = 2 * torch.randn(64, 11)
with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
    want = actor(TensorDict(observation=obs, batch_size=[64]))["action"]
assert float((torch.jit.load(sys.argv[2])(obs) - want).abs().max()) <= 1e-5
assert float((ExportedPolicy(sys.argv[2])(obs) - want).abs().max()) <= 1e-5
print("ok")
"""

PYPROJECT = """
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "adarl-l2-td3"
version = "0.1.0"

[project.entry-points."adarl.plugins"]
l2_td3 = "adarl_l2_td3"

[tool.setuptools]
packages = ["adarl_l2_td3"]
"""


@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> Path:
    """The plugin package, pip-installed into a folder of its own; returns that folder."""
    return install_plugin(tmp_path_factory.mktemp("td3_plugin"), "adarl_l2_td3", PLUGIN, PYPROJECT)


def _new_checkpoint(run: Path, seen: set[str], after: int):
    """A checkpoint of more than ``after`` frames, not in ``seen``, is written (what :func:`wait_for` polls)."""
    return lambda: any(int(name[5:17]) > after for name in checkpoints(run) - seen)


def _results(run: Path) -> dict[str, str]:
    """Every metric file and the evaluation/rank records, as text (wall-clock fields left out)."""
    root = run / "metrics" / "scalars"
    out = {
        f"metrics/{p.relative_to(root).as_posix()}": p.read_text()
        for p in sorted(root.rglob("*.csv"))
        if p.relative_to(root).parts[0] != "time"
    }
    out["eval.csv"] = (run / "eval.csv").read_text()
    out["ranks.json"] = (run / "ranks.json").read_text()
    summary = json.loads((run / "summary.json").read_text())
    for k in ("wall_time_s", "updates_per_s"):
        summary.pop(k)
    out["summary.json"] = json.dumps(summary, sort_keys=True)
    return out


def _metric(run: Path, name: str) -> list[float]:
    path = run / "metrics" / "scalars" / "train" / f"{name}.csv"
    assert path.is_file(), f"train/{name} was not logged: {sorted(p.name for p in path.parent.glob('*'))}"
    with path.open() as f:
        return [float(row[-1]) for row in csv.reader(f) if row and row != ["step", "value"]]  # after the header


@pytest.mark.slow
def test_a_td3_plugin_runs_from_a_recipe_through_rank_events_kill_9_resume_and_a_two_seed_experiment(
    plugin: Path, tmp_path: Path
):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    recipe = elsewhere / "l2_td3_hopper.yaml"
    recipe.write_text(
        f"extends: {REPO / 'recipes' / 'baselines' / 'hopper_td3.yaml'}\nname: l2_td3_hopper\n"
        "algorithm:\n  name: l2_td3\n  options: {weight: 0.001}\n"
    )
    ref, killed = tmp_path / "reference", tmp_path / "killed"
    reference = start_adarl("run", str(recipe), *TINY, "-o", str(ref), "--quiet", site=plugin, cwd=elsewhere)
    proc = start_adarl("run", str(recipe), *TINY, "-o", str(killed), "--quiet", site=plugin, cwd=elsewhere)
    # kill -9 right after the first checkpoint past 200 frames (past the first rank event, at 150 updates = 250
    # frames) and again right after the first one past 400 (past the second), resuming each time
    kills = []
    for after in (200, 400):
        assert wait_for(_new_checkpoint(killed, checkpoints(killed), after), proc, timeout=600, poll=0.02), (
            proc.communicate()[1][-3000:]
        )
        proc.send_signal(signal.SIGKILL)
        assert proc.wait() == -signal.SIGKILL, "the run ended before it could be killed"
        kills.append(sorted(checkpoints(killed))[-1])
        proc = start_adarl("resume", str(killed), "--quiet", site=plugin, cwd=elsewhere)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    _, err = reference.communicate(timeout=600)
    assert reference.returncode == 0, err[-3000:]

    summary = json.loads((ref / "summary.json").read_text())
    # 50 warm-start frames at each of the first two events; the third falls at the end of the 600-frame budget, where
    # a counted warm start collects nothing (issue 46: it never runs past the budget)
    assert summary["rank_events"] == 3 and summary["warm_start_frames"] == 100, summary
    assert json.loads((ref / "plugins.json").read_text())["algorithm"]["package"] == "adarl-l2-td3"
    assert all(v > 0 for v in _metric(ref, "actor_sq_norm")) and _metric(ref, "loss_actor_l2")
    # the trained deterministic actor loads without the training stack, acts in the action box, and exports
    with subprocess.Popen(
        [sys.executable, "-c", LOAD_POLICY, str(ref), str(tmp_path / "l2_td3.pt")],
        env=adarl_env(plugin),
        stdout=subprocess.PIPE,
        text=True,
    ) as loaded:
        assert loaded.communicate(timeout=300)[0].split()[-1] == "ok"
    want, got = _results(ref), _results(killed)
    assert set(want) == set(got), set(want) ^ set(got)
    for name in want:  # bit-identical, not approximately equal
        assert got[name] == want[name], f"kills after {kills}: {name} differs from the uninterrupted run"

    # a two-seed experiment of the same recipe, shorter: 300 frames, rank events every 100 updates
    spec = elsewhere / "l2_td3_seeds.yaml"
    short = {"collector.total_frames": "300", "rank.interval": "100", "eval.interval": "300"}
    overrides = ", ".join(
        f"{o.split('=')[0]}={short.get(o.split('=')[0], o.split('=')[1])}"
        for o in TINY
        if not o.startswith("checkpoint")
    )
    spec.write_text(
        f"kind: experiment\nname: l2_td3_seeds\nrecipe: {recipe}\noverrides: [{overrides}, checkpoint.interval=300]\n"
        "seeds: [0, 1]\n"
    )
    out = tmp_path / "experiment"
    proc = start_adarl(
        "experiment", str(spec), "-o", str(out), "--workers", "2", "--no-live", site=plugin, cwd=elsewhere
    )
    stdout, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, stdout[-2000:] + err[-3000:]
    runs = sorted(p.parent for p in out.rglob("summary.json") if (p.parent / "recipe.yaml").is_file())
    assert len(runs) == 2, sorted(p.as_posix() for p in out.rglob("*"))[:50]
    returns = []
    for r in runs:
        assert "name: l2_td3" in (r / "recipe.yaml").read_text()
        assert json.loads((r / "summary.json").read_text())["rank_events"] >= 1
        returns.append((r / "metrics" / "scalars" / "rollout" / "ep_rew_mean.csv").read_text())
    assert returns[0] != returns[1]  # two seeds, two runs
