"""Where a recipe becomes objects, in one package: networks, losses, and every component of a run wired together.

* :mod:`~adarl.runtime.builders.common` - the device check, the MLP of a ``network.<net>`` section (plain,
  low-rank, or a registered baseline's variant), the Q(s, a) critic the off-policy families share, the training and
  evaluation envs, an actor's specs;
* :mod:`~adarl.runtime.builders.off_policy` - the off-policy builders' one skeleton
  (:func:`build_off_policy_components` around a family's :class:`OffPolicyParts`) and what they share: replay buffer,
  collector, rank adapter, warm start, rank events, :class:`OffPolicyComponents` (their checkpoint state);
* :mod:`~adarl.runtime.builders.sac` - SAC's actor and ``SACLoss``; :func:`build_sac_components` for AdaRL-SAC and
  the SAC baselines;
* :mod:`~adarl.runtime.builders.sac_variants` - TorchRL's TQC, CrossQ and REDQ losses on the SAC loop
  (``algorithm.name`` ``tqc``, ``crossq``, ``redq``): their networks, loss and update step
  (:class:`~adarl.runtime.builders.sac_variants.VariantParts`);
* :mod:`~adarl.runtime.builders.td3` - TD3's (and DDPG's) deterministic actor, exploration and loss;
  :func:`build_td3_components`;
* :mod:`~adarl.runtime.builders.ppo` - the RNAC baselines' PPO modules; :func:`build_ppo_components`.

The baselines plug in through :mod:`adarl.baselines.registry`; nothing here names one. Which builder a recipe needs is
its loop's (:mod:`adarl.runtime.families`).
"""

from adarl.runtime.builders.common import (
    ACTIVATIONS,
    check_device,
    make_envs,
    make_mlp,
    make_sac_critic,
    policy_specs,
    spec_env,
    train_env_factory,
)
from adarl.runtime.builders.off_policy import OffPolicyComponents, OffPolicyParts, build_off_policy_components
from adarl.runtime.builders.ppo import PPOComponents, PPOModules, build_ppo_components, make_ppo_modules
from adarl.runtime.builders.sac import (
    SACComponents,
    SACModules,
    build_sac_components,
    make_recipe_actor,
    make_sac_actor,
    make_sac_loss,
    make_sac_modules,
    planned_updates,
    reinit_low_rank_ensemble,
    update_after,
)
from adarl.runtime.builders.sac_variants import VariantComponents, VariantParts  # registers VARIANT_PARTS
from adarl.runtime.builders.td3 import TD3Components, TD3Modules, build_td3_components, make_td3_modules

__all__ = [
    "ACTIVATIONS",
    "check_device",
    "make_mlp",
    "make_envs",
    "train_env_factory",
    "policy_specs",
    "spec_env",
    "make_sac_actor",
    "make_sac_critic",
    "make_sac_loss",
    "make_recipe_actor",
    "VariantComponents",
    "VariantParts",
    "make_sac_modules",
    "reinit_low_rank_ensemble",
    "SACModules",
    "SACComponents",
    "build_sac_components",
    "planned_updates",
    "update_after",
    "PPOModules",
    "PPOComponents",
    "make_ppo_modules",
    "build_ppo_components",
    "OffPolicyComponents",
    "OffPolicyParts",
    "build_off_policy_components",
    "TD3Modules",
    "TD3Components",
    "make_td3_modules",
    "build_td3_components",
]
