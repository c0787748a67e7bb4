"""The one dispatcher (adarl.runtime.families): every base an algorithm may name has a builder and a trainer, the
recipe's base picks both, a builder or trainer refuses a recipe of another loop naming the one to use, the names the
SAC loop's pieces had before the PPO loop had its own are gone (issue 47), and a new family is a builder, an update
step and one registration: a toy family, all three written here, trains end to end through the one off-policy
trainer and its policy loads."""

from __future__ import annotations

import pytest
import torch
from _helpers import tiny
from tensordict import TensorDict
from torchrl.objectives import SACLoss

import adarl
from adarl import plugins
from adarl.errors import AdaRLValueError
from adarl.runtime import builders
from adarl.runtime.builders.off_policy import OffPolicyParts, build_off_policy_components
from adarl.runtime.builders.ppo import build_ppo_components
from adarl.runtime.builders.sac import SACComponents, build_sac_components, make_sac_modules, sac_parameters
from adarl.runtime.builders.td3 import build_td3_components
from adarl.runtime.config import load_recipe
from adarl.runtime.families import FAMILIES, family, register_family
from adarl.runtime.policy import load_policy
from adarl.runtime.run_folder.run_dir import RunDir
from adarl.runtime.trainers import BaseTrainer, OffPolicyTrainer, PPOTrainer, trainer_class
from adarl.runtime.update import UpdateStep


def test_every_base_an_algorithm_may_name_has_a_builder_and_a_trainer():
    assert sorted(FAMILIES.names(load=False)) == sorted(plugins.BASES)
    for base in plugins.BASES:
        fam = family(base)
        assert issubclass(fam.trainer_class(), BaseTrainer)
    # one off-policy trainer: the family's builder is what differs between SAC and TD3/DDPG
    assert family("sac").trainer_class() is family("td3").trainer_class() is OffPolicyTrainer
    assert family("ppo").trainer_class() is PPOTrainer
    assert family("sac").builder_name == "build_sac_components" and family("ppo").builder_name == "build_ppo_components"
    assert family("td3").builder_name == "build_td3_components"
    with pytest.raises(
        AdaRLValueError, match="unknown algorithm base 'td4'; allowed: 'ppo', 'sac', 'td3'; did you mean 'td3'"
    ):
        family("td4")


@pytest.mark.parametrize(
    "name, trainer",
    [
        ("quickstart", OffPolicyTrainer),
        ("baselines/hopper_rnac_ipm", PPOTrainer),
        ("baselines/hopper_td3", OffPolicyTrainer),
    ],
    ids=["sac", "ppo", "td3"],
)
def test_the_recipes_base_picks_the_trainer(name, trainer):
    assert trainer_class(load_recipe(name)) is trainer


def test_a_builder_refuses_a_recipe_of_another_loop_naming_the_one_to_use():
    with pytest.raises(AdaRLValueError, match=r"build_ppo_components builds the 'ppo' loop.*'sac' loop.*build_sac"):
        build_ppo_components(load_recipe("quickstart"))
    with pytest.raises(AdaRLValueError, match=r"build_sac_components builds the 'sac' loop.*build_ppo_components"):
        build_sac_components(load_recipe("baselines/hopper_rnac_ipm"))
    with pytest.raises(AdaRLValueError, match=r"build_td3_components builds the 'td3' loop.*build_sac_components"):
        build_td3_components(load_recipe("quickstart"))
    with pytest.raises(AdaRLValueError, match=r"build_sac_components builds the 'sac' loop.*build_td3_components"):
        build_sac_components(load_recipe("baselines/hopper_td3"))


def test_a_trainer_refuses_a_recipe_of_another_loop_naming_the_one_to_use(tmp_path):
    with pytest.raises(AdaRLValueError, match=r"PPOTrainer runs the 'ppo' loop.*'sac' loop: use OffPolicyTrainer"):
        PPOTrainer(load_recipe("quickstart"), RunDir.create(tmp_path / "a"))
    with pytest.raises(AdaRLValueError, match=r"OffPolicyTrainer runs the 'sac' / 'td3' loop.*use PPOTrainer"):
        OffPolicyTrainer(load_recipe("baselines/hopper_rnac_ipm"), RunDir.create(tmp_path / "b"))


def test_the_old_aliases_are_gone():
    """``Trainer``, ``Components`` and ``build_components`` were second names (issue 47): one name per thing."""
    from adarl.runtime import trainers

    for module, name in [
        (adarl, "Trainer"),
        (adarl, "Components"),
        (adarl, "build_components"),
        (adarl, "SACTrainer"),
        (trainers, "Trainer"),
        (builders, "Components"),
        (builders, "build_components"),
    ]:
        assert not hasattr(module, name), (module.__name__, name)
    assert adarl.OffPolicyTrainer is OffPolicyTrainer and adarl.build_sac_components is build_sac_components


# ---------------------------------------------------------------------------------------------------- a new family
class ToySACLoss(SACLoss):
    """The toy family's loss (a registered algorithm names its base with its loss)."""


class ToyStep(UpdateStep):
    """The toy family's update step: TorchRL's SAC step with one Adam over everything, counted."""

    def __init__(self, loss, optimizer, replay_buffer, target_updater):
        self.loss, self.optimizer, self.replay_buffer = loss, optimizer, replay_buffer
        self.target_updater = target_updater
        self.calls = 0

    def __call__(self, guard=None, *, update=0):
        td = self.loss(self.replay_buffer.sample())
        losses = {k: td[k] for k in ("loss_actor", "loss_qvalue", "loss_alpha")}
        sum(losses.values()).backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.target_updater.step()
        if guard is not None:
            guard.check_params(update)
        self.calls += 1
        return {k: v.detach() for k, v in losses.items()}


class ToyParts(OffPolicyParts):
    components = SACComponents  # its checkpoint state and guarded parameters are SAC's

    def modules(self, recipe, env):
        return make_sac_modules(recipe, env)

    def optimizers(self, recipe, modules):
        one = torch.optim.Adam(modules.loss.parameters(), lr=recipe.algorithm.lr)
        return {"actor": one, "critic": one}  # schedules are made for the actor's and the critic's

    def update(self, recipe, modules, optimizers, schedulers, replay_buffer, generator):
        return ToyStep(modules.loss, optimizers["actor"], replay_buffer, modules.target_updater)

    def parameters(self, recipe, modules):
        return sac_parameters(modules.loss)


def build_toy_components(recipe, *, init_random_frames=None, scratch_dir=None):
    """The toy family's builder: its parts in the off-policy skeleton."""
    return build_off_policy_components(
        recipe, build_toy_components, ToyParts(), init_random_frames=init_random_frames, scratch_dir=scratch_dir
    )


@pytest.fixture
def toy_family(monkeypatch):
    """The ``toy`` base and its algorithm, registered for one test: a base's TorchRL losses (adarl.plugins, where an
    algorithm's base is checked), the family (one register_family call) and an algorithm on it."""
    monkeypatch.setattr(plugins._algorithm, "BASES", (*plugins.BASES, "toy"))
    monkeypatch.setitem(plugins.BASE_LOSSES, "toy", ("SACLoss",))
    monkeypatch.setattr(plugins._algorithm, "_algorithms", dict(plugins._algorithm._algorithms))
    register_family(
        "toy",
        builder=build_toy_components,
        trainer=OffPolicyTrainer,
        actor="adarl.runtime.builders.sac:make_recipe_actor",
    )
    plugins.register_algorithm("toy_sac", ToySACLoss, base="toy")
    yield
    del FAMILIES.entries["toy"]


TOY = tiny(
    "algorithm.name=toy_sac",
    "algorithm.fused=false",
    "collector.total_frames=400",
    "replay.size=400",
    "rank.interval=100",
    "eval.episodes=1",
    "eval.max_steps=20",
    drop=("algorithm.batch_size", "lr_schedule.warmup_steps", "eval.interval", "checkpoint.interval"),
)


def test_a_new_family_is_a_builder_an_update_step_and_one_registration(toy_family, tmp_path):
    recipe = load_recipe("quickstart", TOY)
    assert recipe.algorithm.base == "toy" and trainer_class(recipe) is OffPolicyTrainer
    trainer = OffPolicyTrainer(recipe, RunDir.create(tmp_path / "run"), quiet=True)
    assert isinstance(trainer.c.update, ToyStep) and isinstance(trainer.c.modules.loss, ToySACLoss)
    summary = trainer.train()
    # 200 frames of updates, 100 of them the warm start's after the rank event at update 100 (the skeleton's)
    assert summary["frames"] == 400 and summary["updates"] == trainer.c.update.calls == 100
    assert summary["rank_events"] == 1 and summary["warm_start_frames"] == 100
    policy = load_policy(tmp_path / "run")  # the family names its actor
    assert policy(TensorDict(observation=torch.zeros(11)))["action"].shape == torch.Size([3])
    # builders called directly with a recipe of another loop are refused, naming the right builder
    with pytest.raises(AdaRLValueError, match=r"build_sac_components builds the 'sac' loop.*'toy' loop.*build_toy_"):
        build_sac_components(recipe)
    with pytest.raises(AdaRLValueError, match=r"build_toy_components builds the 'toy' loop.*build_sac_components"):
        build_toy_components(load_recipe("quickstart"))
