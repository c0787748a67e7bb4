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

Long because: one extension API, read in one place and imported without torch: the registry, plugin loading, and
the three registries recipes validate against with adarl's own entries.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import metadata
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from adarl.errors import AdaRLValueError, UnknownNameError, did_you_mean, one_of

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

#: the entry-point group installed packages declare their plugins in
ENTRY_POINT_GROUP = "adarl.plugins"

# =====================================================================================================================
# Entry points and provenance
# =====================================================================================================================

_loaded: set[str] = set()  # entry points already loaded (by "name = value")
_current_provider: list[str | None] = [None]
Plugin = Callable[[], None]  # a callable that registers (the value of a "module:function" entry point)


def load_entry_points() -> None:
    """Load every ``adarl.plugins`` entry point not loaded yet: a module is imported, a function is called. A
    plugin that fails to load is an error naming it (a half-registered plugin would run as something else)."""
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        key = f"{ep.name} = {ep.value}"
        if key in _loaded:
            continue
        _loaded.add(key)
        dist = getattr(getattr(ep, "dist", None), "name", None)
        try:
            with providing(dist):
                obj = ep.load()
                if callable(obj) and not isinstance(obj, type):
                    obj()
        except (Exception, SystemExit) as err:  # noqa: BLE001 - any failure of third-party code, named with it;
            # SystemExit too: a plugin calling sys.exit() at import would otherwise end the run with status 0, silently
            raise AdaRLValueError(
                f"the adarl plugin {ep.name!r} ({ep.value}, package {dist or '?'}) failed to load: "
                f"{type(err).__name__}: {err}"
            ) from err


@contextmanager
def providing(provider: str | None):
    """Registrations made inside record ``provider`` (an entry point's distribution, a recipe's local module)."""
    previous, _current_provider[0] = _current_provider[0], provider
    try:
        yield
    finally:
        _current_provider[0] = previous


def current_provider() -> str | None:
    """The distribution whose entry point is loading now: what a registration records as its entry's ``provider``
    (None outside an entry point: adarl's own entries, and those registered in-process)."""
    return _current_provider[0]


def provenance(provider: str | None) -> dict:
    """``{"package", "version"}`` of an entry's provider: the distribution and its installed version, or adarl's."""
    package = provider or "adarl"
    try:
        version = metadata.version(package)
    except metadata.PackageNotFoundError:
        version = None
    return {"package": package, "version": version}


# =====================================================================================================================
# The registry
# =====================================================================================================================

T = TypeVar("T")


class Registry(Generic[T]):
    """Entries by name: what every extension point of adarl is (see the module docstring).

    Args:
        key: what a name is called in messages (``"algorithm.name"``, ``"rank.rule"``, ``"init scheme"``).
        what: what an entry is called in messages about registering (``"algorithm"``; default: ``key``).
        how: how to register one, ending the unknown-name error (None: the error lists the allowed names only).
        plugins: whether a name not known yet loads the installed plugins' entry points before the error.
        order: how names are listed (``sorted``; ``list``: the order they were registered in).
        entries: the dict of entries (default: a new one), or a callable returning it at each call (tests swap it).
        describe: an entry in the name-taken error (``"loss torchrl.objectives:SACLoss, from adarl"``).
        same: whether a registration under a taken name is the same entry again (then allowed without ``replace``).
        protected: names that can never be registered again (adarl's own rank rules).
        noun: what to pick another of, in the name-taken error (``"name"``, ``"id"``).
    """

    def __init__(
        self,
        key: str,
        *,
        what: str | None = None,
        how: str | None = None,
        plugins: bool = True,
        order: Callable[[Iterable[str]], list[str]] = sorted,
        entries: dict[str, T] | Callable[[], dict[str, T]] | None = None,
        describe: Callable[[T], str] | None = None,
        same: Callable[[T, T], bool] | None = None,
        protected: Iterable[str] = (),
        noun: str = "name",
    ) -> None:
        self.key, self.what, self.how, self.plugins, self.order = key, what or key, how, plugins, order
        store = {} if entries is None else entries
        self._entries = store if callable(store) else (lambda: store)
        self.describe, self.same, self.protected, self.noun = describe, same, tuple(protected), noun

    @property
    def entries(self) -> dict[str, T]:
        """``{name: entry}`` as registered (nothing loaded)."""
        return self._entries()

    def __contains__(self, name: object) -> bool:
        return name in self.entries

    def load(self) -> None:
        """Load the installed plugins' entry points (when this registry takes plugins)."""
        if self.plugins:
            load_entry_points()

    def names(self, *, load: bool = True) -> list[str]:
        """The registered names, in :attr:`order` (``load``: the installed plugins' entry points first)."""
        if load:
            self.load()
        return list(self.order(self.entries))

    def get(self, name: str) -> T:
        """The entry registered as ``name``; installed plugins are loaded when it is not known yet, and an unknown
        name is an :class:`~adarl.errors.UnknownNameError` listing the registered ones (:meth:`unknown`)."""
        if name not in self.entries:
            self.load()
        if name not in self.entries:
            raise self.unknown(name)
        return self.entries[name]

    def unknown(self, name: Any) -> UnknownNameError:
        """The error for a name nobody registered: the allowed names, a close one, and how to register (typed:
        ``kind``, ``name`` and ``allowed`` are attributes too)."""
        names = list(self.order(self.entries))
        plugin = "no installed plugin registers it; " if self.plugins else ""
        where = "" if self.how is None else f" ({plugin}{self.how})"
        return UnknownNameError(
            f"unknown {self.key} {name!r}; allowed: {one_of(names)}{did_you_mean(str(name), names)}{where}",
            kind=self.key,
            name=name,
            allowed=names,
            hint=where,
        )

    def check_free(self, name: str, entry: T | None = None, *, replace: bool = False) -> None:
        """Refuse a taken ``name`` (unless ``replace``, or :attr:`same` says ``entry`` is the one registered), and
        a :attr:`protected` one always: before anything is registered."""
        old = self.entries.get(name)
        if old is not None and name in self.protected:
            raise AdaRLValueError(
                f"{self.what} {name!r} is one of adarl's own ({one_of(self.protected)}) and cannot be replaced; "
                f"pick another {self.noun}"
            )
        again = entry is not None and self.same is not None and old is not None and self.same(old, entry)
        if old is not None and not replace and not again:
            detail = f" ({self.describe(old)})" if self.describe is not None else ""
            raise AdaRLValueError(
                f"{self.what} {name!r} is already registered{detail}; pick another {self.noun} or pass replace=True"
            )

    def provenance(self, name: str) -> dict:
        """Where the entry registered as ``name`` came from (its ``provider``, :func:`provenance`): plugins.json's."""
        return provenance(getattr(self.get(name), "provider", None))

    def register(self, name: str, entry: T, *, replace: bool = False) -> T:
        """Add ``entry`` as ``name`` (:meth:`check_free` first); returns it."""
        self.check_free(name, entry, replace=replace)
        self.entries[name] = entry
        return entry


# =====================================================================================================================
# Algorithms by name
# =====================================================================================================================

#: the training loops an algorithm can run on (each is a family of :mod:`adarl.runtime.families`)
BASES = ("sac", "ppo", "td3")
#: the TorchRL losses each base builds and trains: ``{base: class names}``; a registered loss class must subclass one
#: of its base's (checked by name along its MRO, so that this module imports no torch)
BASE_LOSSES: dict[str, tuple[str, ...]] = {
    "sac": ("SACLoss", "CrossQLoss", "REDQLoss"),
    "ppo": ("PPOLoss",),
    "td3": ("TD3Loss", "DDPGLoss"),
}


def bases_of(loss_class: type) -> list[str]:
    """The bases whose loop can build and train ``loss_class``: those one of whose TorchRL losses
    (:data:`BASE_LOSSES`) it is or subclasses.

    >>> from torchrl.objectives import ClipPPOLoss, DDPGLoss, IQLLoss
    >>> bases_of(ClipPPOLoss), bases_of(DDPGLoss), bases_of(IQLLoss)
    (['ppo'], ['td3'], [])
    """
    names = {k.__name__ for k in getattr(loss_class, "__mro__", ()) if k.__module__.startswith("torchrl.")}
    return [base for base in BASES if names & set(BASE_LOSSES[base])]


def _bases_listing() -> str:
    return "; ".join(f"{b!r} ({' or '.join(BASE_LOSSES[b])} and subclasses)" for b in BASES)


def check_fits_base(name: str, loss_class: Any, base: str) -> None:
    """Refuse a loss class whose loop is not ``base``, naming the base it fits, or every base when it fits none
    (a ``"module:Class"`` path is checked when a run imports it: :meth:`Algorithm.loss_class`)."""
    if not isinstance(loss_class, type):
        raise AdaRLValueError(
            f"register_algorithm({name!r}): the loss must be a class or a 'module:Class' path, got {loss_class!r}"
        )
    fits = bases_of(loss_class)
    if base in fits:
        return
    what = f"register_algorithm({name!r}, {loss_class.__name__}, base={base!r})"
    if fits:
        raise AdaRLValueError(
            f"{what}: {loss_class.__name__} runs on the {fits[0]!r} loop, not on {base!r}; register it with "
            f"base={fits[0]!r} (bases: {_bases_listing()})"
        )
    raise AdaRLValueError(
        f"{what}: {loss_class.__name__} fits no base, so no recipe loop can train it; bases: {_bases_listing()}. "
        "Another TorchRL loss family runs in Python, composed with adarl's components (docs/custom-loss.md)"
    )


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


class TQCOptions(BaseModel):
    """``algorithm.options`` of ``tqc``: Kuznetsov et al. (2020)'s defaults (5 critics of 25 atoms, 2 dropped per
    critic: 10 of the 125 pooled target atoms)."""

    model_config = ConfigDict(extra="forbid")
    num_critics: int = Field(5, ge=1, strict=True, description="N: quantile critics (sets algorithm.num_qvalue_nets)")
    num_quantiles: int = Field(25, ge=1, strict=True, description="M: atoms (quantiles) each critic outputs")
    top_quantiles_to_drop_per_net: int = Field(
        2, ge=0, strict=True, description="d: largest pooled target atoms dropped per critic (d * N in all)"
    )

    @field_validator("top_quantiles_to_drop_per_net")
    @classmethod
    def _keeps_an_atom(cls, v: int, info: ValidationInfo) -> int:
        atoms = info.data.get("num_quantiles")
        if atoms is not None and v >= atoms:
            raise ValueError(f"must be < num_quantiles ({atoms}): the target keeps N * (num_quantiles - d) atoms")
        return v


class CrossQOptions(BaseModel):
    """``algorithm.options`` of ``crossq``: Bhatt et al. (2024)'s defaults (Batch Renormalization in critic and
    actor, no target network, Adam with beta1 = 0.5 at 1e-3, the actor updated every 3rd critic step)."""

    model_config = ConfigDict(extra="forbid")
    lr: float = Field(
        1e-3,
        gt=0,
        allow_inf_nan=False,
        description="Adam learning rate of actor, critic and alpha (sets algorithm.lr and algorithm.alpha_lr)",
    )
    adam_beta1: float = Field(0.5, ge=0, lt=1, description="Adam's beta1 (the authors' 0.5; Adam's own is 0.9)")
    adam_beta2: float = Field(0.999, ge=0, lt=1, description="Adam's beta2")
    policy_delay: int = Field(3, ge=1, strict=True, description="critic steps per actor (and alpha) step")
    actor_batch_norm: bool = Field(True, description="Batch Renormalization in the actor too (the authors' default)")
    batch_norm_momentum: float = Field(
        0.01, gt=0, le=1, description="running-statistics rate of BatchRenorm1d (the authors' 0.99 in flax's terms)"
    )
    renorm_warmup_steps: int = Field(
        100_000, ge=0, strict=True, description="BatchRenorm1d's steps of plain batch norm before renormalising"
    )


class REDQOptions(BaseModel):
    """``algorithm.options`` of ``redq``: Chen et al. (2021)'s defaults (N = 10 critics, a random M = 2 of them in
    each target, G = 20 updates per frame, the actor once per frame)."""

    model_config = ConfigDict(extra="forbid")
    ensemble_size: int = Field(10, ge=2, strict=True, description="N: critics (sets algorithm.num_qvalue_nets)")
    subset_size: int = Field(2, ge=1, strict=True, description="M: critics drawn for each target's minimum")
    utd_ratio: float = Field(
        20.0, gt=0, allow_inf_nan=False, description="G: updates per collected frame (sets algorithm.utd_ratio)"
    )
    policy_delay: int = Field(
        20, ge=1, strict=True, description="critic steps per actor (and alpha) step (the authors' code: 20 = G)"
    )

    @field_validator("subset_size")
    @classmethod
    def _subset_of_ensemble(cls, v: int, info: ValidationInfo) -> int:
        n = info.data.get("ensemble_size")
        if n is not None and v >= n:
            raise ValueError(
                f"must be < ensemble_size ({n}): TorchRL's REDQLoss draws at most N - 1 critics (it would cut M "
                "down silently)"
            )
        return v


@dataclass(frozen=True)
class Algorithm:
    """A registered ``algorithm.name``.

    ``base``: the training loop (``"sac"``: the SAC trainer, replay buffer and rank adapter; ``"td3"``: the same
    off-policy loop with TD3's delayed actor updates and Gaussian exploration, for ``TD3Loss`` and ``DDPGLoss``;
    ``"ppo"``: the PPO loop). ``loss``: the TorchRL loss class (built with the keyword arguments of its base's
    loss, ``SACLoss``, ``TD3Loss``/``DDPGLoss`` or ``ClipPPOLoss``, plus the options), or a ``"module:Class"`` path
    imported when a run is built (and refused there if it fits no base). ``options``: a pydantic model of
    ``algorithm.options`` (unknown keys, types and ranges are its job; give it ``extra="forbid"``).
    ``provider``: the distribution whose entry point registered it (None for adarl's own). ``sets``: the
    ``algorithm`` keys its options decide, ``{key: option}`` (REDQ's ``utd_ratio``: the loop reads the key, the
    recipe states it once, as an option; the recipe validation copies it and refuses a key set to another value)."""

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
    sets: dict[str, str] = field(default_factory=dict)

    @property
    def loss_path(self) -> str:
        return _path_of(self.loss)

    def loss_class(self) -> type:
        """The loss class (a ``"module:Class"`` path is imported now, and refused if it does not fit the base)."""
        cls = _resolve(self.loss)
        if isinstance(self.loss, str):
            check_fits_base(self.name, cls, self.base)
        return cls

    def hook(self, name: str) -> Callable | None:
        """The ``advantage`` or ``env_transform`` hook (a ``"module:function"`` path is imported now), or None."""
        value = getattr(self, name)
        return None if value is None else _resolve(value)

    def steps_per_frame(self, options: dict) -> int:
        """Simulator steps per collected frame under ``options`` (1 unless the algorithm says otherwise)."""
        return 1 if self.simulator_steps_per_frame is None else int(self.simulator_steps_per_frame(options))

    def provenance(self) -> dict:
        """Where this name came from (the run folder's plugins.json): the loss, the package whose entry point
        registered it and its version."""
        return {"name": self.name, "base": self.base, "loss": self.loss_path, **provenance(self.provider)}


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


_algorithms: dict[str, Algorithm] = {}
ALGORITHMS: Registry[Algorithm] = Registry(
    "algorithm.name",
    what="algorithm",
    how=HOW_TO_REGISTER,
    entries=lambda: _algorithms,
    describe=lambda old: f"loss {old.loss_path}, from {old.provider or 'adarl'}",
    same=lambda old, new: old.loss_path == new.loss_path,
)


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
    sets: dict[str, str] | None = None,
):
    """Register ``algorithm.name: <name>``; usable as a class decorator on the loss::

        @register_algorithm("robust_sac", options=RobustSACOptions)
        class RobustSACLoss(TargetShiftSACLoss): ...

    A name registered twice is an error (``replace=True`` to override on purpose).

    ``options_to_loss``: pass ``algorithm.options`` to the loss's constructor (else only the hooks see them).
    Hooks of the PPO loop (a callable or a ``"module:function"`` path, imported when a run is built):
    ``advantage(recipe, critic) -> ValueEstimator`` replaces GAE (RNAC-IPM's shifted GAE);
    ``env_transform(recipe, critic) -> Transform | None`` is appended to the training env (RNAC-DS's double
    sampling); ``simulator_steps_per_frame(options) -> int`` is the simulator's cost per collected frame.
    ``sets={"utd_ratio": "utd_ratio"}``: ``algorithm`` keys whose value an option gives (:class:`Algorithm`)."""
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
        if not isinstance(cls, str):
            check_fits_base(name, cls, base)
        entry = Algorithm(
            name=name,
            base=base,
            loss=cls,
            options=options or NoOptions,
            description=description,
            provider=current_provider(),
            options_to_loss=options_to_loss,
            advantage=advantage,
            env_transform=env_transform,
            simulator_steps_per_frame=simulator_steps_per_frame,
            sets=dict(sets or {}),
        )
        ALGORITHMS.register(name, entry, replace=replace)
        return cls

    if loss is None:
        return _register
    return _register(loss)


#: the TorchRL losses the ``sac`` loop builds besides SACLoss (adarl.runtime.builders.sac_variants), by class name
SAC_VARIANTS = ("TQCLoss", "CrossQLoss", "REDQLoss")


def sac_variant(name: str) -> str | None:
    """Which of :data:`SAC_VARIANTS` the loss of ``algorithm.name`` ``name`` is or subclasses (None: SAC's own or
    another loop's), read from its class path and, for a class, its MRO (nothing imported).

    >>> sac_variant("tqc"), sac_variant("sac"), sac_variant("td3")
    ('TQCLoss', None, None)
    """
    spec = algorithm(name)
    names = {k.__name__ for k in getattr(spec.loss, "__mro__", ())} | {spec.loss_path.rpartition(":")[2]}
    return next((v for v in SAC_VARIANTS if v in names), None)


def algorithm_names(*, load: bool = True) -> list[str]:
    """The registered algorithm names (``load``: installed plugins first)."""
    return ALGORITHMS.names(load=load)


def algorithm(name: str) -> Algorithm:
    """The :class:`Algorithm` registered as ``name``; installed plugins are loaded when it is not known yet."""
    return ALGORITHMS.get(name)


# adarl's own, declared as a plugin would
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
register_algorithm(
    "td3",
    "torchrl.objectives:TD3Loss",
    base="td3",
    description="TorchRL's TD3Loss: deterministic actor, Gaussian exploration, delayed actor and target updates",
)
register_algorithm(
    "ddpg",
    "torchrl.objectives:DDPGLoss",
    base="td3",
    description="TorchRL's DDPGLoss on the td3 loop (one critic; algorithm.td3.policy_update_delay=1 is DDPG's own)",
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
# TorchRL's TQC, CrossQ and REDQ losses on the SAC loop (adarl.runtime.builders.sac_variants builds their networks,
# loss and update step): the authors' hyperparameters are their options, the loop's own keys copied from them.
register_algorithm(
    "tqc",
    "torchrl.objectives:TQCLoss",
    base="sac",
    options=TQCOptions,
    options_to_loss=False,
    sets={"num_qvalue_nets": "num_critics"},
    description="TQC (Kuznetsov et al., 2020): TorchRL's TQCLoss, quantile critics, the top target atoms dropped",
)
register_algorithm(
    "crossq",
    "torchrl.objectives:CrossQLoss",
    base="sac",
    options=CrossQOptions,
    options_to_loss=False,
    sets={"lr": "lr", "alpha_lr": "lr"},
    description="CrossQ (Bhatt et al., 2024): TorchRL's CrossQLoss, Batch Renormalization, no target network",
)
register_algorithm(
    "redq",
    "torchrl.objectives:REDQLoss",
    base="sac",
    options=REDQOptions,
    options_to_loss=False,
    sets={"num_qvalue_nets": "ensemble_size", "utd_ratio": "utd_ratio"},
    description="REDQ (Chen et al., 2021): TorchRL's REDQLoss, N critics, targets on a random M, G updates per frame",
)


# =====================================================================================================================
# Rank rules by name: ``rank.rule`` is looked up as ``algorithm.name`` is. A rule's keyword arguments are the
# recipe's ``rank.rule_options`` (a pydantic model per rule); adarl's five rules read their own rank-section keys
# instead (``rank.beta``, ``rank.target_rank``, ``rank.lam``: :data:`BUILTIN_RANK_RULE_KEYS`).
# =====================================================================================================================

#: adarl's own rank rules, in the order error messages list them (their recipe keys: rank.beta, target_rank, lam)
BUILTIN_RANK_RULES = ("energy", "energy_inclusive", "ratio", "fixed", "policy_fit")
#: the rank-section keys each of adarl's own rules is built from: ``{rule: {keyword argument: rank.<key>}}``
BUILTIN_RANK_RULE_KEYS: dict[str, dict[str, str]] = {
    "energy": {"beta": "beta"},
    "energy_inclusive": {"beta": "beta"},
    "ratio": {"beta": "beta"},
    "fixed": {"target_rank": "target_rank"},
    "policy_fit": {"lam": "lam"},
}
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
    ``rule_class()(**arguments(rank))``. ``provider``: the distribution whose entry point registered it (None for
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
        return _path_of(self.rule)

    def rule_class(self) -> type:
        """The rule class (a ``"module:Class"`` path is imported now; a failure is an error naming the rule)."""
        try:
            return _resolve(self.rule)
        except (ImportError, AttributeError) as err:
            raise AdaRLValueError(
                f"rank rule {self.name!r} (from {self.provider or 'adarl'}) names {self.rule!r}, which cannot be "
                f"imported: {type(err).__name__}: {err}"
            ) from err

    def arguments(self, rank) -> dict:
        """The keyword arguments a recipe's ``rank`` section builds the rule with: adarl's own rules read their keys
        of the section (:data:`BUILTIN_RANK_RULE_KEYS`), a plugin's rule its ``rank.rule_options``."""
        keys = BUILTIN_RANK_RULE_KEYS.get(self.name) if self.builtin else None
        if keys is None:
            return dict(rank.rule_options)
        return {arg: getattr(rank, key) for arg, key in keys.items()}


_rank_rules: dict[str, RankRuleSpec] = {}
RANK_RULES: Registry[RankRuleSpec] = Registry(
    "rank.rule",
    what="rank rule",
    how=HOW_TO_REGISTER_RANK_RULE,
    order=list,
    entries=lambda: _rank_rules,
    describe=lambda old: f"rule {old.rule_path}, from {old.provider or 'adarl'}",
    same=lambda old, new: old.rule_path == new.rule_path,
    protected=BUILTIN_RANK_RULES,
)


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
        entry = RankRuleSpec(
            name=name,
            rule=cls,
            options=options or NoOptions,
            description=description,
            provider=current_provider(),
            builtin=name in BUILTIN_RANK_RULES,
        )
        RANK_RULES.register(name, entry, replace=replace)
        return cls

    if rule is None:
        return _register
    return _register(rule)


def rank_rule_names(*, load: bool = True) -> list[str]:
    """The registered rank rule names, adarl's own first (``load``: installed plugins first)."""
    return RANK_RULES.names(load=load)


def rank_rule(name: str) -> RankRuleSpec:
    """The :class:`RankRuleSpec` registered as ``name``; installed plugins are loaded when it is not known yet.

    >>> rank_rule("energy").rule_path, rank_rule("energy").builtin
    ('adarl.core.rank:EnergyRule', True)
    >>> rank_rule("enrgy")
    Traceback (most recent call last):
        ...
    adarl.errors.UnknownNameError: unknown rank.rule 'enrgy'; allowed: 'energy', ...; did you mean 'energy'? ...
    """
    return RANK_RULES.get(name)


# adarl's own, declared as a plugin's would be
for _name, _cls, _what in (
    ("energy", "EnergyRule", "paper Eq. 10 (rank.beta)"),
    ("energy_inclusive", "InclusiveEnergyRule", "smallest rank with energy share >= rank.beta"),
    ("ratio", "RatioRule", "paper Eq. 33, App. D.4 (rank.beta)"),
    ("fixed", "FixedRank", "truncate to rank.target_rank"),
    ("policy_fit", "PolicyFitRule", "fit/penalty trade-off of Eq. 8 (rank.lam)"),
):
    register_rank_rule(_name, f"adarl.core.rank:{_cls}", description=_what)


# =====================================================================================================================
# Training callbacks by name: each entry of a recipe's ``callbacks`` list is looked up as ``algorithm.name`` is, and
# its ``options`` validated by the callback's pydantic model. A callback is a TorchRL ``TrainerHookBase``-style
# object (:class:`adarl.runtime.callbacks.Callback`), built with its options as keyword arguments (docs/callbacks.md).
# =====================================================================================================================

#: adarl's own callbacks (their names cannot be registered again)
BUILTIN_CALLBACKS = ("stop_on_return",)
HOW_TO_REGISTER_CALLBACK = (
    "register one with adarl.register_callback(...) in a module the recipe's plugins list names, or in a package "
    f"that declares an {ENTRY_POINT_GROUP!r} entry point (docs/callbacks.md)"
)


class StopOnReturnOptions(BaseModel):
    """``options`` of the ``stop_on_return`` callback (SB3's ``StopTrainingOnRewardThreshold``)."""

    model_config = ConfigDict(extra="forbid")
    threshold: float = Field(
        allow_inf_nan=False, description="stop after the first evaluation whose mean return is >= this"
    )
    min_frames: int = Field(0, ge=0, description="no stop before this many frames, whatever the return")


@dataclass(frozen=True)
class CallbackSpec:
    """A registered callback name (an entry of a recipe's ``callbacks``).

    ``callback``: the class (a subclass of :class:`adarl.runtime.callbacks.Callback`, or any TorchRL
    ``TrainerHookBase`` with ``register``, ``state_dict`` and ``load_state_dict``), or a ``"module:Class"`` path
    imported when a run is built (this module imports no torch). ``options``: a pydantic model of the entry's
    ``options``, which the class is built with as keyword arguments. ``provider``: the distribution whose entry point
    registered it (None for adarl's own and for a recipe's local module, which plugins.json records by sha256)."""

    name: str
    callback: Any
    options: type[BaseModel] = NoOptions
    description: str = ""
    provider: str | None = None
    builtin: bool = False

    @property
    def callback_path(self) -> str:
        return _path_of(self.callback)

    def callback_class(self) -> type:
        """The callback class (a ``"module:Class"`` path is imported now; a failure is an error naming it)."""
        try:
            return _resolve(self.callback)
        except (ImportError, AttributeError) as err:
            raise AdaRLValueError(
                f"callback {self.name!r} (from {self.provider or 'adarl'}) names {self.callback!r}, which cannot be "
                f"imported: {type(err).__name__}: {err}"
            ) from err

    def provenance(self) -> dict:
        """Where this name came from (the run folder's plugins.json): the class, the package and its version."""
        return {"name": self.name, "callback": self.callback_path, **provenance(self.provider)}


_callbacks: dict[str, CallbackSpec] = {}
CALLBACKS: Registry[CallbackSpec] = Registry(
    "callbacks.name",
    what="callback",
    how=HOW_TO_REGISTER_CALLBACK,
    order=list,
    entries=lambda: _callbacks,
    describe=lambda old: f"class {old.callback_path}, from {old.provider or 'adarl'}",
    same=lambda old, new: old.callback_path == new.callback_path,
    protected=BUILTIN_CALLBACKS,
)


def register_callback(
    name: str,
    callback: Any = None,
    *,
    options: type[BaseModel] | None = None,
    description: str = "",
    replace: bool = False,
):
    """Register a recipe's ``callbacks: [{name: <name>, options: {...}}]``; usable as a class decorator::

        class EveryNOptions(BaseModel):
            model_config = ConfigDict(extra="forbid")
            n: int = Field(100, ge=1)

        @register_callback("every_n", options=EveryNOptions)
        class EveryN(Callback):
            def __init__(self, n: int = 100): ...
            def post_optim(self, losses): ...

    A name registered twice is an error (``replace=True`` to override on purpose); adarl's own cannot be replaced."""
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(f"callback name must be an identifier (letters, digits, _), got {name!r}")
    if options is not None and not (isinstance(options, type) and issubclass(options, BaseModel)):
        raise AdaRLValueError(
            f"register_callback({name!r}): options must be a pydantic BaseModel class, got {options!r}"
        )

    def _register(cls):
        if not isinstance(cls, (str, type)):
            raise AdaRLValueError(
                f"register_callback({name!r}): callback must be a class or a 'module:Class' path, got {cls!r}"
            )
        entry = CallbackSpec(
            name=name,
            callback=cls,
            options=options or NoOptions,
            description=description,
            provider=current_provider(),
            builtin=name in BUILTIN_CALLBACKS,
        )
        CALLBACKS.register(name, entry, replace=replace)
        return cls

    if callback is None:
        return _register
    return _register(callback)


def callback_names(*, load: bool = True) -> list[str]:
    """The registered callback names, adarl's own first (``load``: installed plugins first)."""
    return CALLBACKS.names(load=load)


def callback(name: str) -> CallbackSpec:
    """The :class:`CallbackSpec` registered as ``name``; installed plugins are loaded when it is not known yet.

    >>> callback("stop_on_return").callback_path
    'adarl.runtime.callbacks:StopOnReturn'
    >>> callback("stop_on_retrun")
    Traceback (most recent call last):
        ...
    adarl.errors.UnknownNameError: unknown callbacks.name 'stop_on_retrun'; allowed: 'stop_on_return'; did you mean ...
    """
    return CALLBACKS.get(name)


register_callback(
    "stop_on_return",
    "adarl.runtime.callbacks:StopOnReturn",
    options=StopOnReturnOptions,
    description="stop training after the evaluation whose mean return reaches options.threshold",
)
