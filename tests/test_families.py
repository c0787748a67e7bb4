"""The one dispatcher (adarl.runtime.families): every base an algorithm may name has a builder and a trainer, the
recipe's base picks both, a builder refuses a recipe of another loop naming the one to use, and the names the SAC
loop's pieces had before the PPO loop had its own are aliases of the per-family ones."""

from __future__ import annotations

import pytest

import adarl
from adarl import plugins
from adarl.errors import AdaRLValueError
from adarl.runtime import builders
from adarl.runtime.builders.ppo import PPOComponents, build_ppo_components
from adarl.runtime.builders.sac import SACComponents, build_sac_components
from adarl.runtime.builders.td3 import build_td3_components
from adarl.runtime.config import load_recipe
from adarl.runtime.families import FAMILIES, family
from adarl.runtime.trainers import BaseTrainer, PPOTrainer, SACTrainer, TD3Trainer, Trainer, trainer_class


def test_every_base_an_algorithm_may_name_has_a_builder_and_a_trainer():
    assert sorted(FAMILIES.names(load=False)) == sorted(plugins.BASES)
    for base in plugins.BASES:
        fam = family(base)
        assert issubclass(fam.trainer_class(), BaseTrainer) and fam.trainer_class().algorithm == base
    assert family("sac").builder_name == "build_sac_components" and family("ppo").builder_name == "build_ppo_components"
    assert family("td3").builder_name == "build_td3_components"
    with pytest.raises(
        AdaRLValueError, match="unknown algorithm base 'td4'; allowed: 'ppo', 'sac', 'td3'; did you mean 'td3'"
    ):
        family("td4")


@pytest.mark.parametrize(
    "name, trainer",
    [("quickstart", SACTrainer), ("baselines/hopper_rnac_ipm", PPOTrainer), ("baselines/hopper_td3", TD3Trainer)],
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


def test_the_old_names_are_aliases_of_the_per_family_ones():
    assert Trainer is SACTrainer and adarl.Trainer is adarl.SACTrainer is SACTrainer
    assert builders.build_components is build_sac_components and adarl.build_components is build_sac_components
    assert builders.Components is SACComponents and adarl.Components is SACComponents
    assert builders.PPOComponents is PPOComponents
