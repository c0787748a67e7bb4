"""Algorithms by name, and the entry-point group through which installed packages add names (docs/custom-loss.md).

A recipe's ``algorithm.name`` is looked up here. Each name is *declared* with :func:`register_algorithm`: the
training loop it runs on (``base``: ``"sac"`` or ``"ppo"``), its TorchRL loss class (a class, or a lazy
``"module:Class"`` path), and a pydantic model of its own options (the recipe's ``algorithm.options``,
validated like every other key, written into the run's recipe.yaml). adarl's own algorithms (``sac``, ``ppo`` and
the RNAC baselines ``rnac_ipm`` and ``rnac_ds``, PPO with a hook each) are declared with the same call at the end of
this module.

A package adds names by declaring an entry point in the group ``adarl.plugins`` (pip's and pytest's habit), e.g.
in its pyproject.toml::

    [project.entry-points."adarl.plugins"]
    robust_sac = "adarl_robust_sac"          # a module whose import registers, or a "module:function" to call

Entry points are loaded lazily, only when a recipe names an algorithm that is not registered yet (or when the
registered names are listed): a recipe never imports code that is not installed, and a run whose algorithm is
no longer installed is refused by name (``adarl resume`` included) instead of being rebuilt as another one.

This module imports neither torch nor TorchRL: recipes are validated without them.

>>> sorted(algorithm_names(load=False))
['ppo', 'rnac_ds', 'rnac_ipm', 'sac']
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
from importlib import metadata
from importlib.metadata import entry_points
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from adarl.errors import AdaRLValueError, did_you_mean, one_of

__all__ = [
    "ENTRY_POINT_GROUP",
    "BASES",
    "Algorithm",
    "NoOptions",
    "RNACIPMOptions",
    "RNACDSOptions",
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


class RNACIPMOptions(BaseModel):
    """``algorithm.options`` of ``rnac_ipm``."""

    model_config = ConfigDict(extra="forbid")
    kappa: float = Field(
        1e-5, ge=0, allow_inf_nan=False, description="radius: reward shift per unit of ||theta_critic||"
    )


class RNACDSOptions(BaseModel):
    """``algorithm.options`` of ``rnac_ds``."""

    model_config = ConfigDict(extra="forbid")
    num_candidates: int = Field(2, ge=1, strict=True, description="m: noisy next states probed per step")
    noise: float = Field(5e-3, ge=0, allow_inf_nan=False, description="actuation noise half-width, U[-noise, noise]")


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
    options_to_loss: bool = True
    advantage: Any = None
    env_transform: Any = None
    simulator_steps_per_frame: Callable[[dict], int] | None = None

    @property
    def loss_path(self) -> str:
        return _path_of(self.loss)

    def loss_class(self) -> type:
        """The loss class (a ``"module:Class"`` path is imported now)."""
        return _resolve(self.loss)

    def hook(self, name: str) -> Callable | None:
        """The ``advantage`` or ``env_transform`` hook (a ``"module:function"`` path is imported now), or None."""
        value = getattr(self, name)
        return None if value is None else _resolve(value)

    def steps_per_frame(self, options: dict) -> int:
        """Simulator steps per collected frame under ``options`` (1 unless the algorithm says otherwise)."""
        return 1 if self.simulator_steps_per_frame is None else int(self.simulator_steps_per_frame(options))

    def provenance(self) -> dict:
        """Where this name came from: the package (and its version) whose entry point registered it, the loss."""
        version = None
        if self.provider is not None:
            try:
                version = metadata.version(self.provider)
            except metadata.PackageNotFoundError:
                version = None
        return {
            "name": self.name,
            "base": self.base,
            "loss": self.loss_path,
            "package": self.provider or "adarl",
            "version": version if self.provider else _adarl_version(),
        }


def _path_of(obj: Any) -> str:
    return obj if isinstance(obj, str) else f"{obj.__module__}:{obj.__qualname__}"


def _resolve(obj: Any) -> Any:
    """``obj``, or the object a ``"module:attr.attr"`` path names (imported now)."""
    if not isinstance(obj, str):
        return obj
    module, _, attr = obj.partition(":")
    out = importlib.import_module(module)
    for part in attr.split("."):
        out = getattr(out, part)
    return out


def _adarl_version() -> str | None:
    try:
        return metadata.version("adarl")
    except metadata.PackageNotFoundError:
        return None


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
    options_to_loss: bool = True,
    advantage: Any = None,
    env_transform: Any = None,
    simulator_steps_per_frame: Callable[[dict], int] | None = None,
):
    """Register ``algorithm.name: <name>``; usable as a class decorator on the loss::

        @register_algorithm("robust_sac", options=RobustSACOptions)
        class RobustSACLoss(TargetShiftSACLoss): ...

    A name registered twice is an error (``replace=True`` to override on purpose).

    ``options_to_loss``: pass ``algorithm.options`` to the loss's constructor (else only the hooks see them).
    Hooks of the PPO loop (a callable or a ``"module:function"`` path, imported when a run is built):
    ``advantage(recipe, critic) -> ValueEstimator`` replaces GAE (RNAC-IPM's shifted GAE);
    ``env_transform(recipe, critic) -> Transform | None`` is appended to the training env (RNAC-DS's double
    sampling); ``simulator_steps_per_frame(options) -> int`` is the simulator's cost per collected frame."""
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(f"algorithm name must be an identifier (letters, digits, _), got {name!r}")
    if base not in BASES:
        raise AdaRLValueError(f"register_algorithm({name!r}): unknown base {base!r}; allowed: {one_of(BASES)}")
    if base != "ppo" and (advantage is not None or env_transform is not None):
        raise AdaRLValueError(f"register_algorithm({name!r}): the advantage and env_transform hooks need base='ppo'")
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
            options_to_loss=options_to_loss,
            advantage=advantage,
            env_transform=env_transform,
            simulator_steps_per_frame=simulator_steps_per_frame,
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
    return _lookup(_algorithms, name, "algorithm.name", HOW_TO_REGISTER, sorted)


def _lookup(registry: dict, name: str, key: str, how: str, order: Callable = sorted):
    """``registry[name]``, loading installed plugins first when it is not known; else an error that lists the
    registered names (in ``order``), suggests a close one and says how to register."""
    if name not in registry:
        load_entry_points()
    if name not in registry:
        names = order(registry)
        raise AdaRLValueError(
            f"unknown {key} {name!r}; allowed: {one_of(names)}{did_you_mean(str(name), names)} "
            f"(no installed plugin registers it; {how})"
        )
    return registry[name]


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
        description="TorchRL's ClipPPOLoss + GAE, with RNAC's original trainer settings (the RNAC baselines' base)",
    )
    # The RNAC baselines (Zhou et al., 2023) are registered like any plugin: PPO's loss, and a hook each.
    register_algorithm(
        "rnac_ipm",
        "torchrl.objectives:ClipPPOLoss",
        base="ppo",
        options=RNACIPMOptions,
        options_to_loss=False,
        advantage="adarl.baselines.rnac:make_ipm_advantage",
        description="RNAC-IPM: PPO with GAE on the reward shifted by kappa * ||theta_critic|| (adarl.baselines.rnac)",
    )
    register_algorithm(
        "rnac_ds",
        "torchrl.objectives:ClipPPOLoss",
        base="ppo",
        options=RNACDSOptions,
        options_to_loss=False,
        env_transform="adarl.baselines.rnac:make_double_sampling",
        simulator_steps_per_frame=lambda options: int(options["num_candidates"]) + 1,
        description="RNAC-DS: PPO collecting the worst of m noisy next states w.p. 1/(m+1) (adarl.baselines.rnac)",
    )


_builtin()

#: a callable that registers (the value of a "module:function" entry point)
Plugin = Callable[[], None]


# =====================================================================================================================
# Rank rules by name
#
# A recipe's ``rank.rule`` is looked up here the same way as ``algorithm.name``: each name is declared with
# :func:`register_rank_rule` (its :class:`adarl.core.rank.RankRule` subclass, or a lazy ``"module:Class"`` path, and a
# pydantic model of the rule's own keyword arguments: the recipe's ``rank.rule_options``), and installed packages add
# names through the same ``adarl.plugins`` entry-point group. adarl's five rules are declared below; they keep their
# own recipe keys (``rank.beta``, ``rank.target_rank``, ``rank.lam``) and take no ``rank.rule_options``.
# =====================================================================================================================

#: adarl's own rank rules, in the order error messages list them (their recipe keys: rank.beta, target_rank, lam)
BUILTIN_RANK_RULES = ("energy", "energy_inclusive", "ratio", "fixed", "policy_fit")
HOW_TO_REGISTER_RANK_RULE = (
    f"register one with adarl.register_rank_rule(...) in a package that declares an {ENTRY_POINT_GROUP!r} entry "
    "point, then pip install it (docs/adding-a-component.md)"
)


@dataclass(frozen=True)
class RankRuleSpec:
    """A registered ``rank.rule``.

    ``rule``: the :class:`adarl.core.rank.RankRule` subclass, or a ``"module:Class"`` path imported when a run is
    built (so this module never imports torch). ``options``: a pydantic model of ``rank.rule_options``, the rule's
    own keyword arguments (unknown keys, types and ranges are its job; give it ``extra="forbid"``); a run builds
    ``rule_class()(**rank.rule_options)``. ``provider``: the distribution whose entry point registered it (None for
    adarl's own and for rules registered in-process). ``builtin``: one of adarl's five rules, built from
    ``rank.beta`` / ``rank.target_rank`` / ``rank.lam`` instead of ``rank.rule_options``."""

    name: str
    rule: Any
    options: type[BaseModel] = NoOptions
    description: str = ""
    provider: str | None = None
    builtin: bool = False

    @property
    def rule_path(self) -> str:
        if isinstance(self.rule, str):
            return self.rule
        return f"{self.rule.__module__}:{self.rule.__qualname__}"

    def rule_class(self) -> type:
        """The rule class (a ``"module:Class"`` path is imported now; a failure is an error naming the rule)."""
        if not isinstance(self.rule, str):
            return self.rule
        module, _, attr = self.rule.partition(":")
        try:
            obj = importlib.import_module(module)
            for part in attr.split("."):
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as err:
            raise AdaRLValueError(
                f"rank rule {self.name!r} (from {self.provider or 'adarl'}) names {self.rule!r}, which cannot be "
                f"imported: {type(err).__name__}: {err}"
            ) from err
        return obj


_rank_rules: dict[str, RankRuleSpec] = {}
_registering_builtins = [False]  # True while adarl declares its own five


def register_rank_rule(
    name: str,
    rule: Any = None,
    *,
    options: type[BaseModel] | None = None,
    description: str = "",
    replace: bool = False,
):
    """Register ``rank.rule: <name>``; usable as a class decorator on the rule::

        class TopKOptions(BaseModel):
            model_config = ConfigDict(extra="forbid")
            k: int = Field(8, ge=1)

        @register_rank_rule("top_k", options=TopKOptions, description="keep the k largest singular values")
        class TopK(RankRule):
            def __init__(self, k: int = 8):
                super().__init__()
                self.k = k

            def select(self, s, current_rank, min_rank, fit):
                return self.k

    A recipe then says ``rank: {rule: top_k, rule_options: {k: 4}}``. A name registered twice is an error
    (``replace=True`` to override on purpose); adarl's own five names cannot be replaced."""
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(f"rank rule name must be an identifier (letters, digits, _), got {name!r}")
    if options is not None and not (isinstance(options, type) and issubclass(options, BaseModel)):
        raise AdaRLValueError(
            f"register_rank_rule({name!r}): options must be a pydantic BaseModel class, got {options!r}"
        )

    def _register(cls):
        if cls is None:
            raise AdaRLValueError(f"register_rank_rule({name!r}) needs a RankRule subclass or a 'module:Class' path")
        if not isinstance(cls, (str, type)):
            raise AdaRLValueError(
                f"register_rank_rule({name!r}): rule must be a RankRule subclass or a 'module:Class' path, got {cls!r}"
            )
        new = RankRuleSpec(
            name=name,
            rule=cls,
            options=options or NoOptions,
            description=description,
            provider=_current_provider[0],
            builtin=_registering_builtins[0],
        )
        old = _rank_rules.get(name)
        if old is not None and old.builtin and not new.builtin:
            raise AdaRLValueError(
                f"rank rule {name!r} is one of adarl's own ({one_of(BUILTIN_RANK_RULES)}) and cannot be replaced; "
                "pick another name"
            )
        if old is not None and not replace and old.rule_path != new.rule_path:
            raise AdaRLValueError(
                f"rank rule {name!r} is already registered (rule {old.rule_path}, from {old.provider or 'adarl'}); "
                "pick another name or pass replace=True"
            )
        _rank_rules[name] = new
        return cls

    if rule is None:
        return _register
    return _register(rule)


def rank_rule_names(*, load: bool = True) -> list[str]:
    """The registered rank rule names, adarl's own first (``load``: installed plugins first)."""
    if load:
        load_entry_points()
    return list(_rank_rules)


def rank_rule(name: str) -> RankRuleSpec:
    """The :class:`RankRuleSpec` registered as ``name``; installed plugins are loaded when it is not known yet.

    >>> rank_rule("energy").rule_path, rank_rule("energy").builtin
    ('adarl.core.rank:EnergyRule', True)
    >>> rank_rule("enrgy")
    Traceback (most recent call last):
        ...
    adarl.errors.AdaRLValueError: unknown rank.rule 'enrgy'; allowed: 'energy', ...; did you mean 'energy'? ...
    """
    return _lookup(_rank_rules, name, "rank.rule", HOW_TO_REGISTER_RANK_RULE, list)


def _builtin_rank_rules() -> None:
    _registering_builtins[0] = True
    try:
        for name, cls, what in (
            ("energy", "EnergyRule", "paper Eq. 10 (rank.beta)"),
            ("energy_inclusive", "InclusiveEnergyRule", "smallest rank with energy share >= rank.beta"),
            ("ratio", "RatioRule", "paper Eq. 33, App. D.4 (rank.beta)"),
            ("fixed", "FixedRank", "truncate to rank.target_rank"),
            ("policy_fit", "PolicyFitRule", "fit/penalty trade-off of Eq. 8 (rank.lam)"),
        ):
            register_rank_rule(name, f"adarl.core.rank:{cls}", description=what)
    finally:
        _registering_builtins[0] = False


_builtin_rank_rules()

__all__ += [
    "BUILTIN_RANK_RULES",
    "HOW_TO_REGISTER_RANK_RULE",
    "RankRuleSpec",
    "register_rank_rule",
    "rank_rule",
    "rank_rule_names",
]
