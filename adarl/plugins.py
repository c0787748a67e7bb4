"""Algorithms by name, and the entry-point group through which installed packages add names (docs/custom-loss.md).

A recipe's ``algorithm.name`` is looked up here. Each name is *declared* with :func:`register_algorithm`: the
training loop it runs on (``base``: ``"sac"`` or ``"ppo"``), its TorchRL loss class (a class, or a lazy
``"module:Class"`` path), and a pydantic model of its own options (the recipe's ``algorithm.options``,
validated like every other key, written into the run's recipe.yaml). adarl's own algorithms (``sac``, ``ppo``)
are declared the same way by :mod:`adarl.baselines.registry`'s built-in plugin.

A package adds names by declaring an entry point in the group ``adarl.plugins`` (pip's and pytest's habit), e.g.
in its pyproject.toml::

    [project.entry-points."adarl.plugins"]
    robust_sac = "adarl_robust_sac"          # a module whose import registers, or a "module:function" to call

Entry points are loaded lazily, only when a recipe names an algorithm that is not registered yet (or when the
registered names are listed): a recipe never imports code that is not installed, and a run whose algorithm is
no longer installed is refused by name (``adarl resume`` included) instead of being rebuilt as another one.

This module imports neither torch nor TorchRL: recipes are validated without them.

>>> sorted(algorithm_names(load=False))
['ppo', 'sac']
>>> algorithm("sac").base, algorithm("sac").loss_path
('sac', 'torchrl.objectives:SACLoss')
>>> algorithm("sca")
Traceback (most recent call last):
    ...
adarl.errors.AdaRLValueError: unknown algorithm.name 'sca'; allowed: ...; did you mean 'sac'? (no installed plugin ...
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any

from pydantic import BaseModel, ConfigDict

from adarl.errors import AdaRLValueError, did_you_mean, one_of

__all__ = [
    "ENTRY_POINT_GROUP",
    "BASES",
    "Algorithm",
    "NoOptions",
    "register_algorithm",
    "algorithm",
    "algorithm_names",
    "load_entry_points",
    "HOW_TO_REGISTER",
]

#: the entry-point group installed packages declare their plugins in
ENTRY_POINT_GROUP = "adarl.plugins"
#: the training loops an algorithm can run on
BASES = ("sac", "ppo")
HOW_TO_REGISTER = (
    f"register one with adarl.register_algorithm(...) in a package that declares an {ENTRY_POINT_GROUP!r} entry "
    "point, then pip install it (docs/custom-loss.md)"
)


class NoOptions(BaseModel):
    """The options of an algorithm that has none: ``algorithm.options`` must stay empty."""

    model_config = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class Algorithm:
    """A registered ``algorithm.name``.

    ``base``: the training loop (``"sac"``: the SAC trainer, replay buffer and rank adapter; ``"ppo"``: the PPO
    loop). ``loss``: the TorchRL loss class (for ``base="sac"`` built with ``SACLoss``'s keyword arguments plus
    the options), or a ``"module:Class"`` path imported when a run is built. ``options``: a pydantic model of
    ``algorithm.options`` (unknown keys, types and ranges are its job; give it ``extra="forbid"``).
    ``provider``: the distribution whose entry point registered it (None for adarl's own)."""

    name: str
    base: str
    loss: Any
    options: type[BaseModel] = NoOptions
    description: str = ""
    provider: str | None = None
    extra: dict = field(default_factory=dict)

    @property
    def loss_path(self) -> str:
        if isinstance(self.loss, str):
            return self.loss
        return f"{self.loss.__module__}:{self.loss.__qualname__}"

    def loss_class(self) -> type:
        """The loss class (a ``"module:Class"`` path is imported now)."""
        if not isinstance(self.loss, str):
            return self.loss
        module, _, attr = self.loss.partition(":")
        obj = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part)
        return obj


_algorithms: dict[str, Algorithm] = {}
_loaded: set[str] = set()  # entry points already loaded (by "name = value")
_current_provider: list[str | None] = [None]


def register_algorithm(
    name: str,
    loss: Any = None,
    *,
    base: str = "sac",
    options: type[BaseModel] | None = None,
    description: str = "",
    replace: bool = False,
):
    """Register ``algorithm.name: <name>``; usable as a class decorator on the loss::

        @register_algorithm("robust_sac", options=RobustSACOptions)
        class RobustSACLoss(TargetShiftSACLoss): ...

    A name registered twice is an error (``replace=True`` to override on purpose)."""
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(f"algorithm name must be an identifier (letters, digits, _), got {name!r}")
    if base not in BASES:
        raise AdaRLValueError(f"register_algorithm({name!r}): unknown base {base!r}; allowed: {one_of(BASES)}")
    if options is not None and not (isinstance(options, type) and issubclass(options, BaseModel)):
        raise AdaRLValueError(
            f"register_algorithm({name!r}): options must be a pydantic BaseModel class, got {options!r}"
        )

    def _register(cls):
        if cls is None:
            raise AdaRLValueError(f"register_algorithm({name!r}) needs a loss class or a 'module:Class' path")
        old = _algorithms.get(name)
        if old is not None and not replace and old.loss_path != Algorithm(name, base, cls).loss_path:
            raise AdaRLValueError(
                f"algorithm {name!r} is already registered (loss {old.loss_path}, from "
                f"{old.provider or 'adarl'}); pick another name or pass replace=True"
            )
        _algorithms[name] = Algorithm(
            name=name,
            base=base,
            loss=cls,
            options=options or NoOptions,
            description=description,
            provider=_current_provider[0],
        )
        return cls

    if loss is None:
        return _register
    return _register(loss)


def load_entry_points() -> None:
    """Load every ``adarl.plugins`` entry point not loaded yet: a module is imported, a function is called. A
    plugin that fails to load is an error naming it (a half-registered plugin would run as something else)."""
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        key = f"{ep.name} = {ep.value}"
        if key in _loaded:
            continue
        _loaded.add(key)
        dist = getattr(getattr(ep, "dist", None), "name", None)
        _current_provider[0] = dist
        try:
            obj = ep.load()
            if callable(obj) and not isinstance(obj, type):
                obj()
        except Exception as err:  # noqa: BLE001 - any failure of third-party code, named with its plugin
            raise AdaRLValueError(
                f"the adarl plugin {ep.name!r} ({ep.value}, package {dist or '?'}) failed to load: "
                f"{type(err).__name__}: {err}"
            ) from err
        finally:
            _current_provider[0] = None


def algorithm_names(*, load: bool = True) -> list[str]:
    """The registered algorithm names (``load``: installed plugins first)."""
    if load:
        load_entry_points()
    return sorted(_algorithms)


def algorithm(name: str) -> Algorithm:
    """The :class:`Algorithm` registered as ``name``; installed plugins are loaded when it is not known yet."""
    if name not in _algorithms:
        load_entry_points()
    if name not in _algorithms:
        names = sorted(_algorithms)
        raise AdaRLValueError(
            f"unknown algorithm.name {name!r}; allowed: {one_of(names)}{did_you_mean(str(name), names)} "
            f"(no installed plugin registers it; {HOW_TO_REGISTER})"
        )
    return _algorithms[name]


def _builtin() -> None:
    register_algorithm(
        "sac",
        "torchrl.objectives:SACLoss",
        base="sac",
        description="SAC as in the paper (DiscreteSACLoss for discrete-action envs); AdaRL and the SAC baselines",
    )
    register_algorithm(
        "ppo",
        "torchrl.objectives:ClipPPOLoss",
        base="ppo",
        description="TorchRL's ClipPPOLoss + GAE: the RNAC baselines' base (algorithm.rnac)",
    )


_builtin()

#: a callable that registers (the value of a "module:function" entry point)
Plugin = Callable[[], None]
