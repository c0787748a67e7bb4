"""The training loops by name: for a registered algorithm's ``base`` (``algorithm.base``: ``"sac"``, ``"ppo"``,
``"td3"``), everything that follows that choice. The one dispatcher.

Why one table: an algorithm is registered by name with the loop it runs on (:mod:`adarl.plugins`); everything that
must follow that choice asks :func:`family` instead of spelling the loops out: the builder that makes a recipe's
components (it picks the update step: SAC's fused or TorchRL's, TD3's delayed-actor step), the trainer that runs
them, the actor :func:`~adarl.runtime.policy.load_policy` and ``adarl export`` rebuild and where a checkpoint holds its
tensors, the recipe keys that fix a checkpoint's shapes, the recipe combinations the loop refuses, and a builder or
trainer refusing a recipe of another loop (:func:`check_builder`, :func:`check_trainer`). Each family is a
:class:`Family` in a :class:`~adarl.plugins.Registry`, its callables named by ``"module:attr"`` path and imported
when first used: the table sits below the builders and the trainers it names (they import it), as the algorithm
table names its losses. A new loop is a builder, an update step, a schema section and one :func:`register_family`
(docs/adding-a-component.md counts the files).

>>> family("sac").builder_name, family("ppo").trainer_path
('build_sac_components', 'adarl.runtime.trainers.ppo:PPOTrainer')
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from adarl.errors import AdaRLValueError
from adarl.plugins import Registry

__all__ = ["Family", "FAMILIES", "register_family", "family", "check_builder", "check_trainer"]


def _resolve(path: str | Any) -> Any:
    """The object a ``"module:attr"`` path names (imported now), or ``path`` itself when it is not a string."""
    if not isinstance(path, str):
        return path
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


def _path(obj: str | Any) -> str:
    """``"module:attr"`` of a path or an object (what a builder or trainer is compared by: nothing is imported)."""
    return obj if isinstance(obj, str) else f"{obj.__module__}:{obj.__qualname__}"


@dataclass(frozen=True)
class Family:
    """One training loop, each part a callable or class or its ``"module:attr"`` path.

    ``builder(recipe, **kwargs)`` makes its components, the update step included; ``trainer`` runs them;
    ``actor(recipe, env)`` is the policy network a checkpoint's tensors load into (``load_policy``, ``adarl export``),
    found in the checkpoint's ``actor_state`` entry (``"entry"`` or ``"entry:key prefix"``); ``fingerprint``: the
    recipe keys (dotted) beyond the common ones that fix its checkpoints' shapes; ``checks(recipe)``: the
    ``(key, value, why)`` problems of a recipe on this loop (its schema section's combinations); ``owns``: the
    ``algorithm`` keys only this loop implements (a recipe on another loop must leave them at their defaults)."""

    base: str
    builder: str | Callable[..., Any]
    trainer: str | type
    actor: str | Callable[..., Any]
    actor_state: str = "loss:actor_network_params."
    fingerprint: tuple[str, ...] = ()
    checks: str | Callable[..., list] | None = None
    owns: tuple[str, ...] = ()

    @property
    def builder_name(self) -> str:
        return _path(self.builder).rpartition(":")[2]

    @property
    def builder_path(self) -> str:
        """The builder as code names it: ``adarl.runtime.builders.sac.build_sac_components``."""
        return _path(self.builder).replace(":", ".")

    @property
    def trainer_path(self) -> str:
        return _path(self.trainer)

    def build(self, recipe, **kwargs):
        """The recipe's components, built by this family's builder."""
        return _resolve(self.builder)(recipe, **kwargs)

    def trainer_class(self) -> type:
        """The trainer class of this family (imported now)."""
        return _resolve(self.trainer)

    def make_actor(self, recipe, env):
        """The (untrained) actor of ``recipe`` for ``env``'s specs."""
        return _resolve(self.actor)(recipe, env)

    def actor_params(self, state: dict) -> dict:
        """The actor's tensors in checkpoint ``state``, named as the actor's own ``state_dict``."""
        entry, _, prefix = self.actor_state.partition(":")
        return {k[len(prefix) :]: v for k, v in state[entry].items() if k.startswith(prefix)}

    def problems(self, recipe) -> list:
        """The ``(key, value, why)`` problems of ``recipe`` on this loop (:attr:`checks`)."""
        return [] if self.checks is None else list(_resolve(self.checks)(recipe))


FAMILIES: Registry[Family] = Registry("algorithm base", what="training loop", plugins=False)


def register_family(
    base: str,
    *,
    builder,
    trainer,
    actor,
    actor_state: str = "loss:actor_network_params.",
    fingerprint: tuple[str, ...] = (),
    checks=None,
    owns: tuple[str, ...] = (),
    replace: bool = False,
) -> Family:
    """Make ``base`` a training loop (:class:`Family`'s fields; objects, or ``"module:attr"`` paths)."""
    entry = Family(base, builder, trainer, actor, actor_state, tuple(fingerprint), checks, tuple(owns))
    return FAMILIES.register(base, entry, replace=replace)


def family(recipe_or_base) -> Family:
    """The :class:`Family` of a recipe (its ``algorithm.base``) or of a base's name."""
    base = recipe_or_base if isinstance(recipe_or_base, str) else recipe_or_base.algorithm.base
    return FAMILIES.get(base)


def _loops_of(attr: str, obj) -> str:
    """The loops whose ``attr`` is ``obj``, for an error (``"'sac'"``, ``"'sac' / 'td3'"``)."""
    path = _path(obj)
    bases = [f.base for f in FAMILIES.entries.values() if _path(getattr(f, attr)) == path]
    return " / ".join(repr(b) for b in bases) or "no registered"


def check_builder(recipe, builder: Callable) -> Family:
    """The recipe's :class:`Family`, after refusing, naming the builder to use, a recipe whose loop another builder
    builds (a builder's first check: a recipe of another loop would fail deep inside, e.g. on a missing critic)."""
    mine = family(recipe)
    if _path(mine.builder) == _path(builder):
        return mine
    raise AdaRLValueError(
        f"{builder.__name__} builds the {_loops_of('builder', builder)} loop; algorithm.name "
        f"{recipe.algorithm.name!r} runs on the {mine.base!r} loop: use {mine.builder_path}(recipe) "
        f"(adarl.runtime.trainers.trainer_class(recipe) gives the trainer that runs it)"
    )


def check_trainer(recipe, trainer: type) -> Family:
    """The recipe's :class:`Family`, after refusing a trainer that is not its loop's (nor a subclass of it), naming
    the one to use."""
    mine = family(recipe)
    expected = mine.trainer_class()
    if issubclass(trainer, expected):
        return mine
    raise AdaRLValueError(
        f"{trainer.__name__} runs the {_loops_of('trainer', trainer)} loop; algorithm.name {recipe.algorithm.name!r} "
        f"runs on the {mine.base!r} loop: use {expected.__name__} (adarl.runtime.trainers.trainer_class(recipe))"
    )


# adarl's loops, one per base an algorithm may name (adarl.plugins.BASES; tests/test_families.py checks it)
_OFF_POLICY = "adarl.runtime.trainers.off_policy:OffPolicyTrainer"
register_family(
    "sac",
    builder="adarl.runtime.builders.sac:build_sac_components",
    trainer=_OFF_POLICY,
    actor="adarl.runtime.builders.sac:make_recipe_actor",
    checks="adarl.runtime.config.schema:sac_problems",  # TQC, CrossQ, REDQ (adarl.runtime.builders.sac_variants)
    owns=("polyak", "factor_lr_scale"),  # SAC's factorised critics (Polyak on the products, the factors' LR)
)
register_family(
    "ppo",
    builder="adarl.runtime.builders.ppo:build_ppo_components",
    trainer="adarl.runtime.trainers.ppo:PPOTrainer",
    actor="adarl.runtime.builders.ppo:make_recipe_ppo_actor",
    actor_state="actor",
    fingerprint=("algorithm.ppo.obs_norm", "algorithm.ppo.policy"),
    checks="adarl.runtime.config.schema:ppo_problems",
)
register_family(
    "td3",
    builder="adarl.runtime.builders.td3:build_td3_components",
    trainer=_OFF_POLICY,
    actor="adarl.runtime.builders.td3:make_recipe_td3_actor",
    checks="adarl.runtime.config.schema:td3_problems",
)
