"""The training loops by name: for a registered algorithm's ``base`` (``algorithm.base``: ``"sac"``, ``"ppo"``,
``"td3"``), which builder makes a recipe's components and which trainer runs them. The one dispatcher.

Why one table: an algorithm is registered by name with the loop it runs on (:mod:`adarl.plugins`); everything that
must follow that choice (the builder, the trainer, ``adarl resume`` picking the trainer of a run folder, a builder
refusing a recipe of another loop) asks :func:`family` instead of spelling the loops out. Each family is a
:class:`Family` in a :class:`~adarl.plugins.Registry`, its builder and trainer named by ``"module:attr"`` path and
imported when first used: the table sits below the builders and the trainers it names (they import it), as the
algorithm table names its losses.

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

__all__ = ["Family", "FAMILIES", "register_family", "family", "check_family"]


def _resolve(path: str | Any) -> Any:
    """The object a ``"module:attr"`` path names (imported now), or ``path`` itself when it is not a string."""
    if not isinstance(path, str):
        return path
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class Family:
    """One training loop: ``builder(recipe, **kwargs)`` makes its components, ``trainer`` runs them (each a callable
    and a class, or their ``"module:attr"`` paths)."""

    base: str
    builder: str | Callable[..., Any]
    trainer: str | type

    @property
    def builder_name(self) -> str:
        return self.builder.rpartition(":")[2] if isinstance(self.builder, str) else self.builder.__name__

    @property
    def trainer_path(self) -> str:
        return self.trainer if isinstance(self.trainer, str) else f"{self.trainer.__module__}:{self.trainer.__name__}"

    def build(self, recipe, **kwargs):
        """The recipe's components, built by this family's builder."""
        return _resolve(self.builder)(recipe, **kwargs)

    def trainer_class(self) -> type:
        """The trainer class of this family (imported now)."""
        return _resolve(self.trainer)


FAMILIES: Registry[Family] = Registry("algorithm base", what="training loop", plugins=False)


def register_family(base: str, *, builder, trainer, replace: bool = False) -> Family:
    """Make ``base`` a training loop: ``builder`` and ``trainer`` (objects, or ``"module:attr"`` paths)."""
    return FAMILIES.register(base, Family(base, builder, trainer), replace=replace)


def family(recipe_or_base) -> Family:
    """The :class:`Family` of a recipe (its ``algorithm.base``) or of a base's name."""
    base = recipe_or_base if isinstance(recipe_or_base, str) else recipe_or_base.algorithm.base
    return FAMILIES.get(base)


def check_family(recipe, base: str) -> None:
    """Refuse, naming the builder and trainer to use, a recipe whose algorithm runs on another loop than ``base``
    (a builder's first check: a recipe of another loop would fail deep inside, e.g. on a missing critic)."""
    got = recipe.algorithm.base
    if got == base:
        return
    mine, theirs = family(base), family(got)
    raise AdaRLValueError(
        f"{mine.builder_name} builds the {base!r} loop; algorithm.name {recipe.algorithm.name!r} runs on the {got!r} "
        f"loop: use adarl.runtime.builders.{theirs.builder_name}(recipe) "
        f"(adarl.runtime.trainers.trainer_class(recipe) gives the trainer that runs it)"
    )


# adarl's loops, one per base an algorithm may name (adarl.plugins.BASES; tests/test_families.py checks it)
register_family(
    "sac", builder="adarl.runtime.builders.sac:build_sac_components", trainer="adarl.runtime.trainers.sac:SACTrainer"
)
register_family(
    "ppo", builder="adarl.runtime.builders.ppo:build_ppo_components", trainer="adarl.runtime.trainers.ppo:PPOTrainer"
)
register_family(
    "td3", builder="adarl.runtime.builders.td3:build_td3_components", trainer="adarl.runtime.trainers.td3:TD3Trainer"
)
