"""Extension points by name: the generic :class:`Registry`, the ``adarl.plugins`` entry-point group, and the three
registries recipes validate against: algorithms, rank rules (docs/custom-loss.md) and training callbacks
(docs/callbacks.md). No torch, nor TorchRL, here.

Every name-based extension point of adarl is a :class:`Registry` (here; env ids in :mod:`adarl.envs.registry`; the
baselines' variants, init schemes and loss terms in :mod:`adarl.baselines.registry`; the training loops in
:mod:`adarl.runtime.families`): lookup by name, an unknown name's error listing the allowed ones with a close one,
installed plugins loaded first, a name taken twice refused unless ``replace=True``, and provenance (the package
that registered an entry: a run folder's plugins.json). adarl's own entries register through the same calls.

A recipe's ``algorithm.name`` is looked up here. Each name is *declared* with :func:`register_algorithm`: the
training loop it runs on (``base``: ``"sac"``, ``"ppo"`` or ``"td3"``), its TorchRL loss class (a class, or a lazy
``"module:Class"`` path), and a pydantic model of its own options (the recipe's ``algorithm.options``,
validated like every other key, written into the run's recipe.yaml). adarl's own algorithms (``sac``, ``td3``,
``ddpg``, ``ppo``, the RNAC baselines ``rnac_ipm`` and ``rnac_ds`` (PPO with a hook each), and ``tqc``, ``crossq``
and ``redq`` (TorchRL's TQCLoss, CrossQLoss and REDQLoss on the ``sac`` loop) are declared with the
same call at the end of their section.

A package adds names by declaring an entry point in the group ``adarl.plugins`` (pip's and pytest's habit), e.g.
in its pyproject.toml::

    [project.entry-points."adarl.plugins"]
    robust_sac = "adarl_robust_sac"          # a module whose import registers, or a "module:function" to call

Entry points are loaded lazily, only when a recipe names an algorithm that is not registered yet (or when the
registered names are listed): a recipe never imports code that is not installed, and a run whose algorithm is
no longer installed is refused by name (``adarl resume`` included) instead of being rebuilt as another one.

>>> sorted(algorithm_names(load=False))
['crossq', 'ddpg', 'ppo', 'redq', 'rnac_ds', 'rnac_ipm', 'sac', 'td3', 'tqc']
>>> algorithm("sac").base, algorithm("sac").loss_path
('sac', 'torchrl.objectives:SACLoss')
>>> algorithm("sca")
Traceback (most recent call last):
    ...
adarl.errors.UnknownNameError: unknown algorithm.name 'sca'; allowed: ...; did you mean 'sac'? (no installed plugin ...

This module is the hub (import from here); each idea lives in a private module behind it, as TorchRL's transforms
do: ``_registry`` (:class:`Registry`, the entry-point group, provenance), ``_algorithm`` (``algorithm.name`` and
the bases), ``_rank_rule`` (``rank.rule``) and ``_callback`` (``callbacks``). No torch is imported by any of them.
"""

from __future__ import annotations

from adarl.plugins._algorithm import (
    ALGORITHMS,
    BASE_LOSSES,
    BASES,
    HOW_TO_REGISTER,
    SAC_VARIANTS,
    Algorithm,
    CrossQOptions,
    REDQOptions,
    RNACDSOptions,
    RNACIPMOptions,
    TQCOptions,
    algorithm,
    algorithm_names,
    bases_of,
    register_algorithm,
    sac_variant,
)
from adarl.plugins._callback import (
    BUILTIN_CALLBACKS,
    CALLBACKS,
    HOW_TO_REGISTER_CALLBACK,
    CallbackSpec,
    StopOnReturnOptions,
    callback,
    callback_names,
    register_callback,
)
from adarl.plugins._rank_rule import (
    BUILTIN_RANK_RULE_KEYS,
    BUILTIN_RANK_RULES,
    HOW_TO_REGISTER_RANK_RULE,
    RANK_RULES,
    RankRuleSpec,
    rank_rule,
    rank_rule_names,
    register_rank_rule,
)
from adarl.plugins._registry import (
    ENTRY_POINT_GROUP,
    NoOptions,
    Registry,
    current_provider,
    load_entry_points,
    provenance,
    providing,
)

__all__ = [
    "ENTRY_POINT_GROUP",
    "Registry",
    "load_entry_points",
    "current_provider",
    "providing",
    "provenance",
    "BASES",
    "BASE_LOSSES",
    "bases_of",
    "Algorithm",
    "NoOptions",
    "RNACIPMOptions",
    "RNACDSOptions",
    "TQCOptions",
    "CrossQOptions",
    "REDQOptions",
    "register_algorithm",
    "algorithm",
    "algorithm_names",
    "SAC_VARIANTS",
    "sac_variant",
    "HOW_TO_REGISTER",
    "ALGORITHMS",
    "BUILTIN_RANK_RULES",
    "BUILTIN_RANK_RULE_KEYS",
    "HOW_TO_REGISTER_RANK_RULE",
    "RANK_RULES",
    "RankRuleSpec",
    "register_rank_rule",
    "rank_rule",
    "rank_rule_names",
    "BUILTIN_CALLBACKS",
    "HOW_TO_REGISTER_CALLBACK",
    "CALLBACKS",
    "CallbackSpec",
    "StopOnReturnOptions",
    "register_callback",
    "callback",
    "callback_names",
]
