"""Algorithms by name: a recipe's ``algorithm.name`` (:func:`register_algorithm`, :func:`algorithm`), the training
loops they run on (``BASES``) and adarl's own algorithms, declared as a plugin would declare them. Private module of
:mod:`adarl.plugins`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from adarl.errors import AdaRLValueError, one_of
from adarl.plugins._registry import (
    ENTRY_POINT_GROUP,
    NoOptions,
    Registry,
    _path_of,
    _resolve,
    current_provider,
    provenance,
)

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
