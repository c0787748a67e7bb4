"""RankAdapter: the rank adaptation step of Algorithm 1 (step 6) on a TorchRL loss module.

Every ``interval`` optimisation steps the adapter SVDs each :class:`~adarl.core.lowrank.LowRankLinear` of the actor
and/or critic, asks a rank rule (:mod:`adarl.core.rank`) for a new rank, and re-factorises the layer at that rank
(paper App. D.2) *in place*, so that everything holding the parameters keeps working:

* the online factors get new ``.data`` (the ``Parameter`` objects keep their identity: the loss, the policy a
  collector runs and :class:`~torchrl.objectives.SoftUpdate` all see the new tensors), ``.grad`` is cleared and the
  optimiser state of exactly those parameters is dropped in every optimiser (Adam moments of the old basis mean
  nothing in the new one);
* target factors get the same shape: ``target_mode="sync"`` copies the new online factors, ``"project"`` applies
  the same change of basis to the target factors (keeping the Polyak lag);
* the loss's cached detached/stacked parameter views are erased, the given learning-rate schedulers are restarted
  (warm-up from zero, :mod:`adarl.core.lr_schedule`) and the ``on_truncate`` callbacks run (e.g.
  :class:`adarl.core.warmstart.ReplayWarmStart`).

The layers are found generically, not only for SAC: every network attribute of the loss (``actor_network``,
``qvalue_network``, ``critic_network``, ``value_network``, ...) lives in the loss's ``__dict__`` (not in
``loss.modules()``); each LowRankLinear's module path is mapped to keys of ``<name>_params`` and, if present,
``target_<name>_params``. Stacked ensembles (the ``[num_qvalue_nets, ...]`` Q parameters run under vmap) get one
rank per layer: the largest of the members' choices, so no member is cut below what its own spectrum asks for.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import numbers
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.trainers.trainers import TrainerHookBase

from adarl.core.acceptance import ProjectionAcceptance, relative_output_error
from adarl.core.lowrank import LowRankLinear, factor_svd, is_integer, refactorize, truncation_error
from adarl.core.lowrank import replace_data as _set_data
from adarl.core.lr_schedule import restart_lr_scheduler, warmup_cosine_lambdas
from adarl.core.rank import RankRule, energy_share
from adarl.errors import AdaRLValueError, CheckpointError

__all__ = [
    "RankAdapter",
    "RankEvent",
    "LayerRecord",
    "LowRankSite",
    "find_low_rank_layers",
    "layer_indices",
    "resize_to_ranks",
    "SCOPES",
    "TARGET_MODES",
    "ACTOR_NETWORK_NAMES",
    "SUPPORTED_LOSSES",
    "UNSUPPORTED_LOSSES",
    "check_loss_supported",
]

SCOPES = ("actor", "critic", "both")
TARGET_MODES = ("sync", "project")
#: Network attributes of a loss that count as the actor (everything else with LowRankLinear layers is a critic).
ACTOR_NETWORK_NAMES = ("actor_network", "actor", "policy_network", "policy")
#: ``target_mode="project"`` falls back to "sync" when cond(R1) or cond(R2) exceeds this (float64).
PROJECT_COND_LIMIT = 1e6

_ENSEMBLE = "stacked ensemble"
#: Stock TorchRL losses RankAdapter is tested on (tests/test_adapter_losses.py runs a truncation through each one:
#: shapes, optimiser state, target updates, the user's actor): ``{class name: the networks adapted (role)}``.
#: docs/rank-adapter.md's "Supported losses" table is this dict (a test checks it).
SUPPORTED_LOSSES: dict[str, str] = {
    "SACLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE}, targets)",
    "DiscreteSACLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE}, targets)",
    "REDQLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE} of num_qvalue_nets, targets)",
    "TQCLoss": f"actor_network (actor); qvalue_network (critic: quantile critics, {_ENSEMBLE}, targets)",
    "CrossQLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE}, no targets)",
    "TD3Loss": f"actor_network (actor, targets); qvalue_network (critic, {_ENSEMBLE}, targets)",
    "TD3BCLoss": f"actor_network (actor, targets); qvalue_network (critic, {_ENSEMBLE}, targets)",
    "DDPGLoss": "actor_network (actor); value_network (critic, targets)",
    "IQLLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE}, targets); value_network (critic)",
    "DiscreteIQLLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE}, targets); value_network (critic)",
    "CQLLoss": f"actor_network (actor); qvalue_network (critic, {_ENSEMBLE}, targets)",
    "DiscreteCQLLoss": "value_network (critic: the Q-network the policy acts greedily on, targets)",
    "DQNLoss": "value_network (critic: the Q-network the policy acts greedily on, targets)",
    "DistributionalDQNLoss": "value_network (critic: the distributional Q-network the policy acts on, targets)",
    "PPOLoss": "actor_network (actor); critic_network (critic)",
    "ClipPPOLoss": "actor_network (actor); critic_network (critic)",
    "KLPENPPOLoss": "actor_network (actor); critic_network (critic)",
    "A2CLoss": "actor_network (actor); critic_network (critic)",
    "ReinforceLoss": "actor_network (actor); critic_network (critic)",
    "BCLoss": "actor_network (actor)",
}
#: Stock TorchRL losses RankAdapter refuses, by name: ``{class name: why}``. Subclasses are refused too.
UNSUPPORTED_LOSSES: dict[str, str] = {
    "ACTLoss": "trains an action-chunking transformer (a CVAE over action sequences); untested",
    "DTLoss": "trains a decision transformer (a sequence model over trajectories); untested",
    "OnlineDTLoss": "trains a decision transformer (a sequence model over trajectories); untested",
    "DiffusionBCLoss": "trains a diffusion denoiser by behaviour cloning; untested",
    "DreamerActorLoss": "model-based: the actor learns in imagination through a world-model env; untested",
    "DreamerModelLoss": "trains a world model, not a policy or a critic",
    "DreamerValueLoss": "model-based: the value is learnt in imagination through a world-model env; untested",
    "DreamerV3ActorLoss": "model-based: the actor learns in imagination through a world-model env; untested",
    "DreamerV3Loss": "model-based: combines the world-model, actor and value losses of DreamerV3; untested",
    "DreamerV3ModelLoss": "trains a world model, not a policy or a critic",
    "DreamerV3ValueLoss": "model-based: the value is learnt in imagination through a world-model env; untested",
    "WorldModelLoss": "trains a world model, not a policy or a critic",
    "GAILLoss": "trains a discriminator only (another loss trains the policy); nothing of the paper's actor/critic",
    "RNDLoss": "trains an exploration-bonus predictor against a fixed random network, not a policy or a critic",
    "ExponentialQuadraticCost": "a fixed cost function (PILCO) with no trained network",
    "QMixerLoss": "multi-agent: per-agent Q-networks mixed by a mixer network; untested",
    "IPPOLoss": "multi-agent: agent-stacked parameters would get one rank per layer across agents; untested",
    "MAPPOLoss": "multi-agent: agent-stacked parameters would get one rank per layer across agents; untested",
}


def check_loss_supported(loss_module: nn.Module) -> None:
    """Refuse, by name, a stock TorchRL loss adarl does not support; warn about a stock one it has not been tested on.

    The first TorchRL loss class in the loss's method resolution order decides, so a subclass of ``SACLoss`` is a
    ``SACLoss`` and a subclass of ``IPPOLoss`` is refused. Losses of your own (subclassing ``LossModule``
    directly) are not refused: the adapter finds their networks by TorchRL's ``convert_to_functional``
    convention (docs/custom-loss.md).
    """
    for cls in type(loss_module).__mro__:
        if not cls.__module__.startswith("torchrl.objectives") or cls.__name__.startswith("_"):
            continue
        name = cls.__name__
        if name in UNSUPPORTED_LOSSES:
            raise AdaRLValueError(
                f"RankAdapter does not support TorchRL's {name}: {UNSUPPORTED_LOSSES[name]}. Supported TorchRL losses: "
                f"{sorted(SUPPORTED_LOSSES)} (docs/rank-adapter.md, 'Supported losses'); a loss of your own built with "
                f"convert_to_functional works too (docs/custom-loss.md)"
            )
        if name in SUPPORTED_LOSSES or name == "LossModule":
            return
        warnings.warn(
            f"RankAdapter has not been tested on TorchRL's {name} (tested: {sorted(SUPPORTED_LOSSES)}); check that "
            f"adapter.layers lists the layers you expect and that a truncation keeps training working",
            UserWarning,
            stacklevel=3,
        )
        return


# ----------------------------------------------------------------------------------------------------------------
# Finding the layers behind a loss's functional parameters
# ----------------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class LowRankSite:
    """One LowRankLinear as the loss trains it: its online and target factor tensors.

    ``w1``/``w2`` are the tensors the optimiser steps (the ``Parameter`` objects in ``<network>_params``, stacked
    ``[members, ...]`` for an ensemble); ``target_w1``/``target_w2`` those of ``target_<network>_params`` or
    ``None``; ``template`` the module the loss runs under ``to_module``; ``extra`` parameters of that module that
    are distinct objects from ``w1``/``w2`` (the Q template's own, unused parameters), resized to stay consistent.
    """

    path: str  # "<network attribute>.<module path>", e.g. "qvalue_network.module.mlp.0"
    network_name: str  # the loss attribute, e.g. "qvalue_network"
    role: str  # "actor" | "critic"
    module_path: str
    network: nn.Module
    template: LowRankLinear
    params: TensorDictBase | None  # <network>_params (None for a non-functional network)
    w1: torch.Tensor
    w2: torch.Tensor
    target_w1: torch.Tensor | None
    target_w2: torch.Tensor | None
    extra: tuple[torch.Tensor, torch.Tensor] | None
    name: str = ""  # what a person reads: "<role>.layer<k>" (see layer_names), e.g. "actor.layer0"

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(self.module_path.split(".")) if self.module_path else ()

    @property
    def batch_shape(self) -> torch.Size:
        """Leading (ensemble) dimensions of the factors; empty for a single network."""
        return self.w1.shape[:-2]

    @property
    def rank(self) -> int:
        return int(self.w2.shape[-2])

    @property
    def max_rank(self) -> int:
        return self.template.max_rank


def network_candidates(loss: nn.Module) -> list[tuple[str, nn.Module]]:
    """``(attribute name, network)`` of every network a TorchRL loss holds (``actor_network``, ``qvalue_network``,
    ...), those with functional parameters first: how :class:`RankAdapter` (and the Parseval term) find layers."""
    found: dict[int, tuple[str, nn.Module]] = {}
    items = list(vars(loss).items()) + list(getattr(loss, "_modules", {}).items())
    for name, mod in items:
        if name.startswith("_") or not isinstance(mod, nn.Module) or isinstance(mod, TensorDictBase):
            continue
        if name.endswith("_params"):
            continue
        prev = found.get(id(mod))
        # The same module under two names: keep the one with functional parameters.
        if prev is None or (
            getattr(loss, f"{prev[0]}_params", None) is None and getattr(loss, f"{name}_params", None) is not None
        ):
            found[id(mod)] = (name, mod)
    # Networks with functional parameters first: a layer reachable from two networks belongs to the one the loss
    # trains. (DDPGLoss also keeps a wrapper, actor_critic = [actor_network, value_network], without parameters of
    # its own: found first, it would claim every layer as a critic's, without the value network's targets.)
    return sorted(found.values(), key=lambda nm: getattr(loss, f"{nm[0]}_params", None) is None)


def _role(name: str) -> str:
    return "actor" if name in ACTOR_NETWORK_NAMES else "critic"


def layer_indices(network: nn.Module) -> dict[str, int]:
    """``{module path: k}`` of the network's weight layers in forward order (``nn.Linear``, ``LowRankLinear``; a
    layer inside another counted one is not counted again): ``k`` is the hidden-layer index a recipe's
    ``low_rank_layers`` uses."""
    out: dict[str, int] = {}
    for path, module in network.named_modules():
        if isinstance(module, (nn.Linear, LowRankLinear)) and not any(path.startswith(p + ".") for p in out):
            out[path] = len(out)
    return out


def _name_sites(sites: list[LowRankSite]) -> None:
    """Give each site its human name, ``<role>.layer<k>`` (``actor.layer0``, ``critic.layer1``). Where two networks
    of a loss share a role (IQL's Q and V critics), the network's attribute less ``_network`` stands for the role
    (``qvalue.layer0``, ``value.layer0``)."""
    roles: dict[str, set[str]] = {}
    for s in sites:
        roles.setdefault(s.role, set()).add(s.network_name)
    indices: dict[int, dict[str, int]] = {}
    for s in sites:
        idx = indices.setdefault(id(s.network), layer_indices(s.network))
        prefix = s.role if len(roles[s.role]) == 1 else s.network_name.removesuffix("_network")
        k = idx.get(s.module_path)
        s.name = f"{prefix}.layer{k}" if k is not None else f"{prefix}.{s.module_path or s.network_name}"


def find_low_rank_layers(loss_module: nn.Module, scope: str = "both") -> tuple[list[LowRankSite], list[str]]:
    """All :class:`LowRankSite` of ``loss_module`` in ``scope``, and the networks searched (for error messages).

    Works for any TorchRL loss that keeps its networks as attributes (``convert_to_functional``: module in
    ``__dict__``, parameters in ``<name>_params``, optional ``target_<name>_params``) and for plain modules
    registered on the loss (non-functional losses, e.g. ``ClipPPOLoss(functional=False)``).
    """
    if scope not in SCOPES:
        raise AdaRLValueError(f"scope must be one of {list(SCOPES)}, got {scope!r}")
    sites: list[LowRankSite] = []
    searched: list[str] = []
    seen_params: set[int] = set()
    seen_layers: set[int] = set()
    for name, network in network_candidates(loss_module):
        role = _role(name)
        searched.append(f"{name} ({role})")
        if scope != "both" and role != scope:  # out of scope, but its layers are its own (not a wrapper's)
            seen_layers.update(id(m) for m in network.modules() if isinstance(m, LowRankLinear))
            continue
        params = getattr(loss_module, f"{name}_params", None)
        if params is not None and not isinstance(params, TensorDictBase):
            params = None
        target = loss_module._modules.get(f"target_{name}_params") if hasattr(loss_module, "_modules") else None
        if target is not None and not isinstance(target, TensorDictBase):
            target = None
        for module_path, layer in network.named_modules():
            if not isinstance(layer, LowRankLinear) or id(layer) in seen_layers:
                continue
            seen_layers.add(id(layer))
            path = f"{name}.{module_path}" if module_path else name
            key = tuple(module_path.split(".")) if module_path else ()
            if params is not None:
                w1 = params.get(key + ("w1",), None)
                w2 = params.get(key + ("w2",), None)
                if w1 is None or w2 is None:
                    raise AdaRLValueError(
                        f"cannot map LowRankLinear {path!r} to keys of {name}_params (looked for "
                        f"{key + ('w1',)} and {key + ('w2',)}; "
                        f"available: {sorted(map(str, params.keys(True, True)))[:8]}...)"
                    )
            else:
                w1, w2 = layer.w1, layer.w2
            if not isinstance(w1, nn.Parameter) or not isinstance(w2, nn.Parameter):
                raise AdaRLValueError(
                    f"LowRankLinear {path!r}: its factors in {name}_params are not trainable Parameters (a view of "
                    f"another network's parameters: shared layers are not supported by RankAdapter)"
                )
            if id(w1) in seen_params:
                continue  # the same parameters reached through another network: handled once
            seen_params.add(id(w1))
            tw1 = tw2 = None
            if target is not None:
                tw1 = target.get(key + ("w1",), None)
                tw2 = target.get(key + ("w2",), None)
                if (tw1 is None) != (tw2 is None):
                    raise AdaRLValueError(f"target_{name}_params holds only one factor of {path!r}")
            extra = None
            if layer.w1 is not w1 and isinstance(layer.w1, nn.Parameter) and id(layer.w1) not in seen_params:
                extra = (layer.w1, layer.w2)
            sites.append(LowRankSite(path, name, role, module_path, network, layer, params, w1, w2, tw1, tw2, extra))
    _name_sites(sites)
    return sites, searched


# ----------------------------------------------------------------------------------------------------------------
# Records
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class LayerRecord:
    """What one rank event did to one layer.

    For a stacked ensemble, ``singular_values``, ``retained_energy`` and ``truncation_error`` are per member
    (lists), and ``member_ranks`` holds each member's own choice (the layer takes the largest).
    ``retained_energy`` and ``truncation_error`` (``||W - Pi_r(W)||_F``) are at the applied ``new_rank``.
    ``skipped`` is ``None`` when the layer changed, otherwise why not. ``target`` says how the target factors were
    given the new shape (``"sync"``, ``"project"``, ``"sync (fallback: ...)"``) or ``None`` (no target / no change).

    The acceptance step (:mod:`adarl.core.acceptance`) fills the rest: ``candidate`` is the rule's proposal (the
    largest member's), ``candidate_error`` and ``error`` the relative output error of the layer's network with the
    layer at the candidate and at ``new_rank`` (the truncations already accepted for earlier layers of the same
    network in place; ``None`` when nothing was measured, ``0`` when the rank is kept), ``tolerance`` the bound
    (``None`` without an acceptance step: every candidate is applied), ``tried`` every ``[rank, error]``
    measured and ``note`` why a refused candidate led to another rank.
    """

    step: int
    layer: str
    network: str  # "actor" | "critic"
    old_rank: int
    new_rank: int
    singular_values: list
    retained_energy: Any
    truncation_error: Any
    skipped: str | None = None
    member_ranks: list[int] | None = None
    target: str | None = None
    candidate: int | None = None
    candidate_error: float | None = None
    error: float | None = None
    tolerance: float | None = None
    tried: list | None = None
    note: str | None = None
    name: str | None = None  # the layer's human name ("actor.layer0"); ``layer`` keeps the module path

    @property
    def changed(self) -> bool:
        return self.new_rank != self.old_rank

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class RankEvent:
    """One call of :meth:`RankAdapter.adapt`: the optimisation step it ran at and one record per layer."""

    step: int
    index: int
    layers: list[LayerRecord] = field(default_factory=list)
    #: the adapter that ran the event (``None`` for an event read back from a checkpoint): callbacks such as
    #: :class:`~adarl.core.warmstart.ReplayWarmStart` use it to check that their policy holds the loss's tensors.
    adapter: Any = field(default=None, repr=False, compare=False)

    @property
    def changed(self) -> bool:
        """Whether any layer's rank changed (only then are caches, schedulers and callbacks touched)."""
        return any(r.changed for r in self.layers)

    @property
    def ranks(self) -> dict[str, int]:
        return {r.layer: r.new_rank for r in self.layers}

    def as_dict(self) -> dict:
        return {"step": self.step, "index": self.index, "layers": [r.as_dict() for r in self.layers]}

    @classmethod
    def from_dict(cls, d: Mapping, names: Mapping[str, str] | None = None) -> RankEvent:
        """An event from :meth:`as_dict`; ``names`` (``{layer_path: human name}``) fills the names of records saved
        before layers had them."""
        layers = []
        for r in d["layers"]:
            rec = LayerRecord(**r)
            if rec.name is None and names:
                rec.name = names.get(rec.layer)
            layers.append(rec)
        return cls(int(d["step"]), int(d["index"]), layers)


# ----------------------------------------------------------------------------------------------------------------
# In-place tensor surgery
# ----------------------------------------------------------------------------------------------------------------


def _erase_loss_caches(loss: nn.Module) -> None:
    """Drop the loss's cached detached / stacked parameter views (they would still point at the old tensors)."""
    cache = loss.__dict__.get("_cache")
    if isinstance(cache, dict):
        cache.clear()
    erase = getattr(loss, "_erase_cache", None)
    if callable(erase):
        erase()


def _forget_optimizer_state(optimizers: Iterable[torch.optim.Optimizer], tensors: Iterable[torch.Tensor]) -> None:
    tensors = list(tensors)
    for opt in optimizers:
        for t in tensors:
            opt.state.pop(t, None)


def _project_basis(w1: torch.Tensor, w2: torch.Tensor, rank: int):
    """The online rank-``rank`` factors and the change of basis that produced them (float64, batched).

    ``W1 = Q1 R1``, ``W2^T = Q2 R2``, ``R1 R2^T = Uc S Vch``. The new online factors are
    ``W1' = Q1 Uc_k sqrt(S_k) = W1 T'`` and ``W2' = sqrt(S_k) Vch_k Q2^T = T W2`` with
    ``T' = R1^-1 Uc_k sqrt(S_k)`` (r x k) and ``T = sqrt(S_k) Vch_k R2^-T`` (k x r). Returns
    ``(W1', W2', T', T, cond)`` where ``cond`` is the worst condition number of R1/R2. The online factors come
    from this same decomposition (not from :func:`factor_svd`, whose singular vectors may differ by signs) so that
    the target factors ``W1t T'``, ``T W2t`` stay in the online factors' basis: SoftUpdate lerps them elementwise.
    """
    a = w1.detach().to(torch.float64)
    b = w2.detach().to(torch.float64)
    q1, r1 = torch.linalg.qr(a, mode="reduced")
    q2, r2 = torch.linalg.qr(b.transpose(-1, -2), mode="reduced")
    cond = max(float(torch.linalg.cond(r1).max()), float(torch.linalg.cond(r2).max()))
    uc, s, vhc = torch.linalg.svd(r1 @ r2.transpose(-1, -2), full_matrices=False)
    root = s[..., :rank].sqrt()
    left = uc[..., :, :rank] * root.unsqueeze(-2)  # Uc_k sqrt(S_k), r x k
    right = root.unsqueeze(-1) * vhc[..., :rank, :]  # sqrt(S_k) Vch_k, k x r
    new_w1 = q1 @ left
    new_w2 = right @ q2.transpose(-1, -2)
    if not math.isfinite(cond):
        return new_w1, new_w2, None, None, cond
    t_right = torch.linalg.solve_triangular(r1, left, upper=True)
    t_left = torch.linalg.solve_triangular(r2, right.transpose(-1, -2), upper=True).transpose(-1, -2)
    return new_w1, new_w2, t_right, t_left, cond


def _resize_site(site: LowRankSite, w1: torch.Tensor, w2: torch.Tensor, optimizers) -> None:
    """Give a site's online, target and template factors new values (in place, identities kept)."""
    _set_data(site.w1, w1)
    _set_data(site.w2, w2)
    _forget_optimizer_state(optimizers, (site.w1, site.w2))
    if site.extra is not None:
        e1, e2 = site.extra
        lead = (0,) * len(site.batch_shape)
        _set_data(e1, w1[lead].clone())
        _set_data(e2, w2[lead].clone())
        _forget_optimizer_state(optimizers, (e1, e2))


def _padded_factors(u, s, vh, rank: int, width: int, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Rank-``rank`` factors stored at width ``width`` (zero columns/rows beyond ``rank``)."""
    s = s.clone()
    s[..., rank:] = 0
    return refactorize(u, s, vh, width, dtype)


def resize_to_ranks(
    loss_module: nn.Module,
    ranks: Mapping,
    optimizers: torch.optim.Optimizer | Sequence[torch.optim.Optimizer] = (),
) -> dict[str, tuple[int, int]]:
    """Give a freshly built loss the ranks of a checkpoint, so ``loss.load_state_dict`` can load it.

    A rank event changes parameter *shapes*; ``loss.load_state_dict`` of a truncated checkpoint into a freshly
    built (full-rank) loss fails, even with ``strict=False``. Call this first::

        resize_to_ranks(loss, checkpoint["adapter"], optimizer)   # or checkpoint["loss"], or {path: rank}
        loss.load_state_dict(checkpoint["loss"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        adapter.load_state_dict(checkpoint["adapter"])

    ``ranks`` may be ``{layer_path: rank}`` (see :attr:`RankAdapter.ranks`), a :meth:`RankAdapter.state_dict`
    (its ``"ranks"``) or the loss's own ``state_dict()`` (ranks read from the ``w2`` shapes). Every LowRankLinear of
    the loss (actor and critics, online, stacked ensemble, targets, template) is resized in place (``.data``; the
    values are a truncated projection, or zero-padded when growing, and are meant to be overwritten by the load),
    and the optimiser state of resized parameters is dropped (``optimizer.load_state_dict`` restores it).
    Returns ``{layer_path: (old_rank, new_rank)}`` for the resized layers.
    """
    if isinstance(optimizers, torch.optim.Optimizer):
        optimizers = [optimizers]
    sites, searched = find_low_rank_layers(loss_module, "both")
    if not sites:
        raise CheckpointError(f"no LowRankLinear layers found in {type(loss_module).__name__}; searched {searched}")
    by_path = {s.path: s for s in sites}
    wanted = _ranks_from_source(ranks, sites)
    unknown = sorted(set(wanted) - set(by_path))
    if unknown:
        raise CheckpointError(f"checkpoint has ranks for unknown layers {unknown}; this model has {sorted(by_path)}")
    changed: dict[str, tuple[int, int]] = {}
    with torch.no_grad():
        for path, rank in wanted.items():
            site = by_path[path]
            if isinstance(rank, bool) or not isinstance(rank, int) or not 1 <= rank <= site.max_rank:
                raise CheckpointError(f"rank for {path!r} must be an integer in [1, {site.max_rank}], got {rank!r}")
            old = site.rank
            if rank == old:
                continue
            w1, w2 = _resized(site.w1, site.w2, rank)
            _resize_site(site, w1, w2, optimizers)
            if site.target_w1 is not None:
                t1, t2 = _resized(site.target_w1, site.target_w2, rank)
                _set_data(site.target_w1, t1)
                _set_data(site.target_w2, t2)
            changed[path] = (old, rank)
    if changed:
        _erase_loss_caches(loss_module)
    return changed


def _resized(w1: torch.Tensor, w2: torch.Tensor, rank: int) -> tuple[torch.Tensor, torch.Tensor]:
    old = int(w2.shape[-2])
    u, s, vh = factor_svd(w1, w2)
    a, b = refactorize(u, s, vh, min(rank, old), w1.dtype)
    if rank > old:
        pad = rank - old
        a = torch.cat([a, a.new_zeros(*a.shape[:-1], pad)], -1)
        b = torch.cat([b, b.new_zeros(*b.shape[:-2], pad, b.shape[-1])], -2)
    return a, b


def _ranks_from_source(source: Mapping, sites: list[LowRankSite]) -> dict[str, int]:
    if not isinstance(source, Mapping):
        raise CheckpointError(
            f"ranks must be a mapping (ranks, adapter state_dict or loss state_dict), got {type(source)}"
        )
    if "ranks" in source and isinstance(source["ranks"], Mapping):
        source = source["ranks"]
    if any(isinstance(v, torch.Tensor) for v in source.values()):
        out = {}
        for site in sites:
            owner = f"{site.network_name}_params" if site.params is not None else site.network_name
            key = ".".join(p for p in (owner, site.module_path, "w2") if p)
            if key in source:
                out[site.path] = int(source[key].shape[-2])
        if not out:
            raise CheckpointError(
                "the state_dict holds no LowRankLinear factor of this model (no '...w2' keys matched)"
            )
        return out
    bad = {k: v for k, v in source.items() if isinstance(v, bool) or not isinstance(v, numbers.Integral)}
    if bad:
        raise CheckpointError(f"ranks must be integers, got {bad}")
    try:
        return {str(k): int(v) for k, v in source.items()}
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"cannot read ranks from {type(source).__name__}: {err}") from None


# ----------------------------------------------------------------------------------------------------------------
# Policy-fit measurement (PolicyFitRule)
# ----------------------------------------------------------------------------------------------------------------


def _float_keys(td: TensorDictBase, keys) -> list:
    return [k for k in keys if k in td.keys(True) and torch.is_floating_point(td.get(k))]


class _NetworkProbe:
    """Runs one network (one ensemble member) on a fixed batch with some factors replaced; compares its outputs.

    Used by the acceptance step and :class:`~adarl.core.rank.PolicyFitRule`. The network runs on a detached copy of its
    parameters, so nothing the loss trains is touched. Replacement factors keep the current width (ranks beyond
    the projected one are zero columns/rows), so no shape changes during the measurement. :meth:`commit` makes a
    replacement permanent for the later measurements of this probe: the layers of one network are decided in
    order, each with the earlier layers' accepted truncations in place.
    """

    def __init__(
        self, network_name: str, network: nn.Module, params: TensorDictBase | None, member: tuple, batch: TensorDictBase
    ) -> None:
        self.network_name = network_name
        self.network = network
        if params is not None:
            base = params.detach().clone()
        else:
            base = TensorDict.from_module(network, as_module=False).detach().clone()
        if member:
            base = base[member] if len(base.batch_size) >= len(member) else base.apply(lambda t: t[member])
        self.base = base
        self.batch = batch
        self.reference = self._run()

    def _run(self) -> torch.Tensor:
        net = self.network
        in_keys = getattr(net, "in_keys", None)
        x = self.batch.select(*in_keys, strict=False) if in_keys is not None else self.batch.clone(False)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC), self.base.to_module(net):
            if hasattr(net, "get_dist_params") and hasattr(net, "dist_params_keys"):
                out = net.get_dist_params(x)
                keys = list(net.dist_params_keys)
            else:
                out = net(x)
                keys = list(getattr(net, "out_keys", []))
        keys = _float_keys(out, keys)
        if not keys:
            raise AdaRLValueError(
                f"network {self.network_name!r} produced no float outputs to compare (out keys "
                f"{list(getattr(net, 'out_keys', []))})"
            )
        n = out.batch_size.numel()
        return torch.cat([out.get(k).reshape(n, -1).to(torch.float64) for k in keys], -1)

    def outputs(self, replace: Mapping[tuple, torch.Tensor]) -> torch.Tensor:
        """The network's outputs with the factors in ``replace`` (``{key: tensor}``) swapped in."""
        old = {k: self.base.get(k) for k in replace}
        for k, v in replace.items():
            self.base.set(k, v)
        try:
            return self._run()
        finally:
            for k, v in old.items():
                self.base.set(k, v)

    def distance(self, replace: Mapping[tuple, torch.Tensor]) -> float:
        """Mean L2 distance between the outputs with ``replace`` and the reference (PolicyFitRule's fit)."""
        return float((self.outputs(replace) - self.reference).norm(dim=-1).mean())

    def relative_error(self, replace: Mapping[tuple, torch.Tensor]) -> float:
        """:func:`adarl.core.acceptance.relative_output_error` of the outputs with ``replace`` against the reference."""
        return relative_output_error(self.outputs(replace), self.reference)

    def commit(self, replace: Mapping[tuple, torch.Tensor]) -> None:
        for k, v in replace.items():
            self.base.set(k, v)


# ----------------------------------------------------------------------------------------------------------------
# The adapter
# ----------------------------------------------------------------------------------------------------------------


class RankAdapter(TrainerHookBase):
    """Rank adaptation (Algorithm 1, step 6) for the LowRankLinear layers behind a TorchRL loss.

    Args:
        loss_module: a TorchRL loss (``SACLoss``, ``DiscreteSACLoss``, ``TD3Loss``, ``ClipPPOLoss``, ...) whose
            actor and/or critic contain :class:`~adarl.core.lowrank.LowRankLinear` layers.
        optimizers: the optimiser(s) training the loss's parameters; the state of truncated parameters is dropped
            in each (plain, ``foreach`` and ``fused`` Adam alike).
        rule: a :class:`~adarl.core.rank.RankRule` (``EnergyRule(0.98)`` is the paper's Eq. 10): it proposes each
            layer's candidate rank. A :class:`~adarl.core.rank.PolicyFitRule` needs ``fit_data``.
        acceptance: Algorithm 1's acceptance step (:class:`~adarl.core.acceptance.ProjectionAcceptance`): a candidate
            is applied only if the truncated network's outputs on ``fit_data`` stay within a tolerance of the
            current ones, otherwise the layer keeps its rank (paper Sec. 4.2, "r_new = r_old"). ``None`` applies
            every candidate (with ``EnergyRule``: Eq. 10 alone, which lowers every rank at every event). Needs
            ``fit_data``.
        interval: run an event every ``interval`` calls of :meth:`step` (paper: 0.7e6 or 1e6 optimisation steps).
        scope: ``"actor"``, ``"critic"`` or ``"both"`` (paper Table 2): which networks are adapted. The actor is
            the loss's ``actor_network``; every other network attribute is a critic.
        min_rank: no layer goes below this rank.
        target_mode: ``"sync"`` copies the new online factors into the target factors; ``"project"`` applies the
            online change of basis to the target factors (keeps the Polyak lag; falls back to "sync", with the
            reason in the history, when the factors are ill-conditioned).
        lr_schedulers: ``LambdaLR`` schedulers built with :class:`~adarl.core.lr_schedule.WarmupCosine` (e.g. by
            :func:`~adarl.core.lr_schedule.make_lr_scheduler`), or objects with a ``restart()`` method; restarted
            (learning rate to 0, then warm-up) after every event that changed a rank.
        on_truncate: callables ``fn(event)`` run after every event that changed a rank (e.g.
            :class:`~adarl.core.warmstart.ReplayWarmStart`). A callback with a ``check_event(event)`` method gets it
            called before anything changes (the ranks decided), so that it can refuse the event.
        on_event: callables ``fn(event)`` run after every event, whether or not a rank changed (after the
            ``on_truncate`` ones): records, logs.
        fit_data: the batch the outputs are measured on (acceptance, :class:`~adarl.core.rank.PolicyFitRule`, and the
            error recorded for every truncation when given): a callable returning a TensorDict batch (e.g.
            :class:`~adarl.core.acceptance.RecentTransitions`, the recent transitions of a replay buffer, as recipes
            use; for an on-policy loss, the last batch), or a TorchRL replay buffer (``.sample()`` is called).
        logger: a TorchRL logger; the rank of each layer is logged as ``rank/<layer name>`` (``rank/actor.layer0``,
            see :attr:`names`) at every event.
        log_step: a callable giving the x-axis value the ranks are logged at (e.g. ``lambda: frames``, to plot them
            against collected frames like the returns); default: the optimisation step. :meth:`register` sets it
            (and ``logger``, if none was given) from the TorchRL ``Trainer``: its collected frames and its logger.
        num_threads: torch threads for the decompositions of an event (restored afterwards); ``None`` keeps the
            process's setting. Training at (64, 64) is fastest on one thread, but an event on 1024-wide layers
            is a few float64 eigendecompositions that scale with cores, and it pauses training anyway.

    Call :meth:`step` after every optimisation step, at a clean point (after the optimiser step and the target
    update, with no live autograd graph), or register the adapter on a ``torchrl.trainers.Trainer``
    (:meth:`register`, stage ``"post_optim"``).

    Refused with :class:`~adarl.errors.AdaRLValueError`, so that nothing trains on silently: a stock TorchRL loss
    in :data:`UNSUPPORTED_LOSSES`; optimisers that do not train every adapted factor (their stale state would
    fail later, deep in Adam); and, at an event, a change to factors that another process maps in shared memory
    (a multi-process collector's workers would go on acting with the old factors next to the new biases) unless
    an ``on_truncate`` callback rebuilds that collector (:class:`adarl.core.collector_rebuild.CollectorRebuild`).

    >>> from tensordict.nn import NormalParamExtractor, TensorDictModule
    >>> from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
    >>> from torchrl.objectives import SACLoss
    >>> from adarl.core.lowrank import low_rank_mlp
    >>> from adarl.core.rank import FixedRank
    >>> actor = ProbabilisticActor(
    ...     TensorDictModule(nn.Sequential(low_rank_mlp(3, 4), NormalParamExtractor()), ["observation"],
    ...                      ["loc", "scale"]),
    ...     in_keys=["loc", "scale"], distribution_class=TanhNormal)
    >>> loss = SACLoss(actor, ValueOperator(low_rank_mlp(3 + 2, 1), in_keys=["observation", "action"]))
    >>> optimizer = torch.optim.Adam(loss.parameters())
    >>> adapter = RankAdapter(loss, optimizer, FixedRank(16), interval=1)
    >>> adapter.named_ranks
    {'actor.layer0': 3, 'actor.layer1': 64, 'critic.layer0': 5, 'critic.layer1': 64}
    >>> event = adapter.step()  # after each optimisation step: every `interval` steps, a rank event
    >>> event.step, event.changed
    (1, True)
    >>> [(r.name, r.old_rank, r.new_rank) for r in event.layers if r.new_rank != r.old_rank]
    [('actor.layer1', 64, 16), ('critic.layer1', 64, 16)]
    """

    def __init__(
        self,
        loss_module: nn.Module,
        optimizers: torch.optim.Optimizer | Sequence[torch.optim.Optimizer],
        rule: RankRule,
        interval: int,
        *,
        scope: str = "both",
        min_rank: int = 1,
        target_mode: str = "sync",
        lr_schedulers: Sequence = (),
        on_truncate: Sequence[Callable] | Callable = (),
        fit_data: Callable[[], TensorDictBase] | Any = None,
        logger: Any = None,
        num_threads: int | None = None,
        acceptance: ProjectionAcceptance | None = None,
        on_event: Sequence[Callable] | Callable = (),
        log_step: Callable[[], int] | None = None,
    ) -> None:
        check_loss_supported(loss_module)
        if num_threads is not None and (not is_integer(num_threads) or num_threads < 1):
            raise AdaRLValueError(
                f"num_threads must be an integer >= 1 or None (keep the process's), got {num_threads!r}"
            )
        if not is_integer(interval) or interval < 1:
            raise AdaRLValueError(
                f"interval must be an integer >= 1 (optimisation steps between events), got {interval!r}"
            )
        if scope not in SCOPES:
            raise AdaRLValueError(f"scope must be one of {list(SCOPES)}, got {scope!r}")
        if target_mode not in TARGET_MODES:
            raise AdaRLValueError(f"target_mode must be one of {list(TARGET_MODES)}, got {target_mode!r}")
        if not is_integer(min_rank) or min_rank < 1:
            raise AdaRLValueError(f"min_rank must be an integer >= 1, got {min_rank!r}")
        if log_step is not None and not callable(log_step):
            raise AdaRLValueError(
                f"log_step must be a callable returning the x-axis value (e.g. collected frames) or "
                f"None (the optimisation step), got {type(log_step).__name__}"
            )
        if not isinstance(rule, RankRule):
            raise AdaRLValueError(
                f"rule must be an adarl.core.rank.RankRule (e.g. EnergyRule(0.98)), got {type(rule).__name__}"
            )
        if isinstance(optimizers, torch.optim.Optimizer):
            optimizers = [optimizers]
        optimizers = list(optimizers)
        bad = [type(o).__name__ for o in optimizers if not isinstance(o, torch.optim.Optimizer)]
        if bad:
            raise AdaRLValueError(f"optimizers must be torch.optim.Optimizer instances, got {bad}")
        lr_schedulers = list(lr_schedulers)
        for sch in lr_schedulers:
            if not warmup_cosine_lambdas(sch) and not callable(getattr(sch, "restart", None)):
                raise AdaRLValueError(
                    f"lr_schedulers must be LambdaLR schedulers with WarmupCosine lambdas (adarl.make_lr_scheduler) "
                    f"or objects with a restart() method, got {type(sch).__name__}"
                )
        if callable(on_truncate):
            on_truncate = [on_truncate]
        on_truncate = list(on_truncate)
        for cb in on_truncate:
            if not callable(cb):
                raise AdaRLValueError(f"on_truncate entries must be callables fn(event), got {type(cb).__name__}")
        if callable(on_event):
            on_event = [on_event]
        on_event = list(on_event)
        for cb in on_event:
            if not callable(cb):
                raise AdaRLValueError(f"on_event entries must be callables fn(event), got {type(cb).__name__}")
        if acceptance is not None and not isinstance(acceptance, ProjectionAcceptance):
            raise AdaRLValueError(
                f"acceptance must be an adarl.ProjectionAcceptance or None (apply every candidate), "
                f"got {type(acceptance).__name__}"
            )
        for needs, what in (
            (rule.needs_fit, f"{type(rule).__name__} measures"),
            (acceptance is not None, "the acceptance step measures"),
        ):
            if needs and fit_data is None:
                raise AdaRLValueError(
                    f"{what} the network's outputs: pass fit_data (a callable returning a TensorDict batch, e.g. "
                    f"adarl.RecentTransitions(replay_buffer, 2048), or a replay buffer)"
                )
        if fit_data is not None and not callable(fit_data) and not callable(getattr(fit_data, "sample", None)):
            raise AdaRLValueError(f"fit_data must be a callable or a replay buffer, got {type(fit_data).__name__}")

        self.loss_module = loss_module
        self.optimizers = optimizers
        self.rule = rule
        self.interval = int(interval)
        self.scope = scope
        self.min_rank = int(min_rank)
        self.target_mode = target_mode
        self.lr_schedulers = lr_schedulers
        self.on_truncate = on_truncate
        self.on_event = on_event
        self.acceptance = acceptance
        self.fit_data = fit_data
        self.logger = logger
        self.log_step = log_step
        self.num_threads = None if num_threads is None else int(num_threads)
        self.sites, searched = find_low_rank_layers(loss_module, scope)
        if not self.sites:
            raise AdaRLValueError(
                f"no LowRankLinear layer found in scope {scope!r} of {type(loss_module).__name__}; networks searched: "
                f"{searched or 'none'} (build them with adarl.low_rank_mlp or LowRankLinear)"
            )
        self._check_optimizers(self.sites)
        self.step_count = 0
        self.history: list[RankEvent] = []

    # -- properties ---------------------------------------------------------------------------------------------

    @property
    def ranks(self) -> dict[str, int]:
        """``{layer_path: current rank}`` of the adapted layers (e.g. ``"actor_network.module.0.module.0.0"``)."""
        return {s.path: s.rank for s in self.sites}

    @property
    def layers(self) -> dict[str, str]:
        """``{layer_path: "actor" | "critic"}`` of the adapted layers."""
        return {s.path: s.role for s in self.sites}

    @property
    def names(self) -> dict[str, str]:
        """``{layer_path: human name}``, e.g. ``{"actor_network.module.0.module.0.0": "actor.layer0"}``: the names
        logs, tables and plots show (``<role>.layer<k>``, ``k`` the recipe's hidden-layer index)."""
        return {s.path: s.name for s in self.sites}

    @property
    def named_ranks(self) -> dict[str, int]:
        """:attr:`ranks` keyed by human name (``{"actor.layer0": 11, ...}``)."""
        return {s.name: s.rank for s in self.sites}

    # -- hooks --------------------------------------------------------------------------------------------------

    def step(self) -> RankEvent | None:
        """Count one optimisation step; every ``interval`` steps run :meth:`adapt` and return its event."""
        self.step_count += 1
        if self.step_count % self.interval == 0:
            return self.adapt()
        return None

    __call__ = step

    def register(self, trainer, name: str = "rank_adapter") -> None:
        """Register :meth:`step` at the trainer's ``"post_optim"`` stage and the adapter as a checkpointed module.

        The ranks are then logged on the trainer's x-axis, its collected frames (as everything else the Trainer
        logs), to the adapter's logger or, if it has none, the trainer's.
        """
        trainer.register_op("post_optim", self.step)
        trainer.register_module(name, self)
        if self.logger is None:
            self.logger = getattr(trainer, "logger", None)
        if self.log_step is None:
            self.log_step = lambda: int(trainer.collected_frames)

    # -- checks -------------------------------------------------------------------------------------------------

    def _check_optimizers(self, sites: Sequence[LowRankSite]) -> None:
        """Every trainable factor must be in one of ``optimizers``: an event must drop its stale Adam state."""
        given = {id(p) for opt in self.optimizers for group in opt.param_groups for p in group["params"]}
        missing = [s.path for s in sites if any(t.requires_grad and id(t) not in given for t in (s.w1, s.w2))]
        if missing:
            raise AdaRLValueError(
                f"RankAdapter: the optimizers given ({len(self.optimizers)}) do not train the factors of {missing}; an "
                f"event drops the optimiser state of every factor it resizes, and an optimiser it does not know would "
                f"fail at its next step on the old shapes. Pass every optimizer that trains the loss's parameters "
                f"(e.g. [actor_optimizer, critic_optimizer]); leave a layer out with scope= or requires_grad_(False)"
            )

    def _check_shared(self, plans) -> None:
        """Refuse to resize factors another process maps in shared memory, unless a callback rebuilds that process."""
        shared = [
            site.path
            for site, record, _ in plans
            if record.changed and any(t.device.type == "cpu" and t.is_shared() for t in (site.w1, site.w2))
        ]
        if shared and not any(getattr(cb, "rebuilds_collector", False) for cb in self.on_truncate):
            raise AdaRLValueError(
                f"RankAdapter: the factors of {shared} are in shared memory, which a multi-process collector "
                f"(MultiSyncCollector, MultiAsyncCollector, AsyncCollector, Collector(num_collectors=...)) maps for "
                f"its workers; a rank change gives them new tensors the workers never see, so they would act with the "
                f"old factors next to the new biases. Nothing was changed. Rebuild the collector after each event: "
                f"collector = adarl.CollectorRebuild(lambda: MultiSyncCollector(...)), iterate it instead of the "
                f"collector and pass it in on_truncate (docs/rank-adapter.md, 'Supported collectors')"
            )

    # -- the event ----------------------------------------------------------------------------------------------

    def _fit_batch(self) -> TensorDictBase:
        src = self.fit_data
        batch = src.sample() if callable(getattr(src, "sample", None)) else src()
        if isinstance(batch, tuple):  # ReplayBuffer.sample(return_info=True)
            batch = batch[0]
        if not isinstance(batch, TensorDictBase):
            raise AdaRLValueError(f"fit_data must give a TensorDict batch, got {type(batch).__name__}")
        return batch.reshape(-1) if batch.batch_dims != 1 else batch

    @torch.no_grad()
    def adapt(self) -> RankEvent:
        """Run a rank event now: decide every layer's rank from the current network, then apply the changes.

        Decisions are made on the network as it is before the event; with an acceptance step, the layers of one
        network are decided in order, each measured with the earlier layers' accepted truncations in place.
        """
        event = RankEvent(step=self.step_count, index=len(self.history), adapter=self)
        batch = self._fit_batch() if self.fit_data is not None else None
        threads = torch.get_num_threads()
        if self.num_threads is not None:
            torch.set_num_threads(self.num_threads)
        try:
            plans = []
            probes: dict[tuple, _NetworkProbe] = {}
            for site in self.sites:
                record, svd = self._decide(site, event.step, batch, probes)
                event.layers.append(record)
                plans.append((site, record, svd))
            if any(record.changed for _, record, _ in plans):
                # refusals before anything changes: the model stays as it was
                self._check_optimizers(self.sites)  # param groups may have been added since construction
                self._check_shared(plans)
                for cb in self.on_truncate:
                    check = getattr(cb, "check_event", None)
                    if callable(check):
                        check(event)  # e.g. ReplayWarmStart: its policy must run the loss's own factors
            for site, record, svd in plans:
                if record.changed:
                    record.target = self._apply(site, record.new_rank, *svd)
        finally:
            torch.set_num_threads(threads)
        self.history.append(event)
        if event.changed:
            _erase_loss_caches(self.loss_module)
            for sch in self.lr_schedulers:
                if warmup_cosine_lambdas(sch):
                    restart_lr_scheduler(sch)
                else:
                    sch.restart()
        if self.logger is not None:
            x = int(self.log_step()) if self.log_step is not None else event.step
            for record in event.layers:
                self.logger.log_scalar(f"rank/{record.name or record.layer}", float(record.new_rank), step=x)
        if event.changed:
            for cb in self.on_truncate:
                cb(event)
        for cb in self.on_event:
            cb(event)
        return event

    def _member_probes(self, site: LowRankSite, batch, probes: dict) -> list[_NetworkProbe]:
        """One probe per ensemble member of the site's network, shared by the layers of that network."""
        out = []
        for m in itertools.product(*[range(n) for n in site.batch_shape]):
            key = (site.network_name, tuple(m))
            if key not in probes:
                probes[key] = _NetworkProbe(site.network_name, site.network, site.params, tuple(m), batch)
            out.append(probes[key])
        return out

    def _decide(self, site: LowRankSite, step: int, batch, probes: dict) -> tuple[LayerRecord, tuple | None]:
        current = site.rank
        lead = site.batch_shape
        nonfinite = [name for name, t in (("w1", site.w1), ("w2", site.w2)) if not bool(torch.isfinite(t).all())]
        if nonfinite:  # the SVD would raise; the event must not act on a diverged layer
            reason = f"non-finite values in {' and '.join(nonfinite)} (training diverged?); rank kept"
            return LayerRecord(
                step=step,
                layer=site.path,
                network=site.role,
                old_rank=current,
                new_rank=current,
                singular_values=[],
                retained_energy=float("nan"),
                truncation_error=float("nan"),
                skipped=reason,
                name=site.name,
            ), None
        u, s, vh = factor_svd(site.w1, site.w2)
        members = list(itertools.product(*[range(n) for n in lead]))  # [()] for a single network
        choices, reasons = [], []
        for m in members:
            idx = tuple(m)
            fit = None
            if self.rule.needs_fit:
                fit = self._make_fit(site, idx, u[idx], s[idx], vh[idx], batch)
            d = self.rule(s[idx], current, min_rank=self.min_rank, fit=fit)
            choices.append(int(d.rank))
            if d.skipped:
                reasons.append(d.skipped if not lead else f"member {idx}: {d.skipped}")
        candidate = max(choices)
        new = candidate
        measured = batch is not None and not reasons and candidate < current
        cand_err = err_new = tol = tried = note = None
        if measured:
            member_probes = self._member_probes(site, batch, probes)
            key1, key2 = site.key + ("w1",), site.key + ("w2",)

            def replacement(rank: int) -> list[dict]:
                w1, w2 = _padded_factors(u, s, vh, int(rank), current, site.w1.dtype)
                w1, w2 = w1.to(site.w1.device), w2.to(site.w1.device)
                return [{key1: w1[m], key2: w2[m]} for m in members]

            def error_at(rank: int) -> float:
                errs = [p.relative_error(r) for p, r in zip(member_probes, replacement(rank))]
                return math.nan if any(math.isnan(e) for e in errs) else max(errs)

            broken = not all(bool(torch.isfinite(p.reference).all()) for p in member_probes)
            if broken and self.acceptance is not None:  # nothing to compare against: keep the rank, say why
                new, note = (
                    current,
                    (
                        f"the {site.role}'s outputs on fit_data are non-finite (NaN/inf weights "
                        f"elsewhere in the network, or in the batch); rank kept"
                    ),
                )
            elif self.acceptance is not None:
                result = self.acceptance.resolve(candidate, current, error_at, site.role)
                new, cand_err, err_new = result.rank, result.candidate_error, result.error
                tol, tried, note = result.tolerance, [list(t) for t in result.tried], result.reason
            else:
                cand_err = err_new = error_at(candidate)
                tried = [[candidate, cand_err]]
            if new < current:  # later layers of this network are measured with this truncation in place
                for p, r in zip(member_probes, replacement(new)):
                    p.commit(r)
        elif batch is not None and not reasons:
            cand_err = err_new = 0.0
        flat_s = s.reshape(-1, s.shape[-1])
        energies = [energy_share(row, new) for row in flat_s]
        errors = [float(truncation_error(row, new)) for row in flat_s]
        skipped = None
        if new == current:
            if reasons:
                skipped = "; ".join(reasons)
            elif candidate < current:
                skipped = note
            else:
                skipped = f"rule kept rank {current}"
        record = LayerRecord(
            step=step,
            layer=site.path,
            network=site.role,
            old_rank=current,
            new_rank=new,
            singular_values=[row.tolist() for row in flat_s] if lead else flat_s[0].tolist(),
            retained_energy=energies if lead else energies[0],
            truncation_error=errors if lead else errors[0],
            skipped=skipped,
            member_ranks=choices if lead else None,
            candidate=candidate,
            candidate_error=cand_err,
            error=err_new,
            tolerance=tol,
            tried=tried,
            note=note if new != current else None,
            name=site.name,
        )
        return record, (u, s, vh)

    def _make_fit(self, site, member, u, s, vh, batch) -> Callable[[int], float]:
        probe = _NetworkProbe(site.network_name, site.network, site.params, member, batch)
        width = site.rank
        dtype = site.w1.dtype
        device = site.w1.device
        key1, key2 = site.key + ("w1",), site.key + ("w2",)

        def fit(rank: int) -> float:
            w1, w2 = _padded_factors(u, s, vh, int(rank), width, dtype)
            return probe.distance({key1: w1.to(device), key2: w2.to(device)})

        return fit

    def _apply(self, site: LowRankSite, rank: int, u, s, vh) -> str | None:
        dtype = site.w1.dtype
        mode = None
        w1 = w2 = t1 = t2 = None
        if site.target_w1 is not None:
            mode = self.target_mode
            if mode == "project":
                p1, p2, t_right, t_left, cond = _project_basis(site.w1, site.w2, rank)
                if not math.isfinite(cond) or cond > PROJECT_COND_LIMIT:
                    mode = f"sync (fallback: cond(R1, R2) = {cond:.3g} > {PROJECT_COND_LIMIT:.0g})"
                else:
                    tw1 = site.target_w1.detach().to(torch.float64)
                    tw2 = site.target_w2.detach().to(torch.float64)
                    t1, t2 = tw1 @ t_right, t_left @ tw2
                    if torch.isfinite(t1).all() and torch.isfinite(t2).all():
                        w1, w2 = p1.to(dtype), p2.to(dtype)
                    else:
                        mode, t1, t2 = "sync (fallback: non-finite projected target)", None, None
        if w1 is None:
            w1, w2 = refactorize(u, s, vh, rank, dtype)
        _resize_site(site, w1, w2, self.optimizers)
        if site.target_w1 is not None:
            if t1 is None:
                t1, t2 = w1.clone(), w2.clone()
            _set_data(site.target_w1, t1)
            _set_data(site.target_w2, t2)
        return mode

    # -- checkpointing ------------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Ranks, step counter, history and the schedulers' state (with their WarmupCosine restart points)."""
        return {
            "version": 1,
            "step_count": self.step_count,
            "ranks": self.ranks,
            "history": [e.as_dict() for e in self.history],
            "lr_schedulers": [sch.state_dict() for sch in self.lr_schedulers if hasattr(sch, "state_dict")],
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        """Restore the counter, history and schedulers. The live ranks must already match (:func:`resize_to_ranks`)."""
        ranks = dict(state_dict.get("ranks", {}))
        live = self.ranks
        mismatch = {p: (live.get(p), r) for p, r in ranks.items() if live.get(p) != r}
        if mismatch:
            raise CheckpointError(
                f"the model's ranks differ from the checkpoint's ({{layer: (model, checkpoint)}} = {mismatch}); call "
                f"adarl.core.adapter.resize_to_ranks(loss, checkpoint_state) before loss.load_state_dict and "
                f"adapter.load_state_dict"
            )
        self.step_count = int(state_dict.get("step_count", 0))
        self.history = [RankEvent.from_dict(e, self.names) for e in state_dict.get("history", [])]
        saved = list(state_dict.get("lr_schedulers", []))
        with_state = [sch for sch in self.lr_schedulers if hasattr(sch, "load_state_dict")]
        if saved and len(saved) != len(with_state):
            raise CheckpointError(
                f"checkpoint has {len(saved)} scheduler states but the adapter holds {len(with_state)} schedulers"
            )
        for sch, sd in zip(with_state, saved):
            sch.load_state_dict(sd)

    def __repr__(self) -> str:
        return (
            f"RankAdapter(rule={self.rule!r}, interval={self.interval}, scope={self.scope!r}, "
            f"target_mode={self.target_mode!r}, layers={self.ranks}, step_count={self.step_count})"
        )
