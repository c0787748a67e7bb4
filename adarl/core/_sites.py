"""Where a TorchRL loss keeps its low-rank layers: the supported / refused loss tables, and site discovery.

Why a module of its own: finding the layers is what makes :class:`~adarl.core.adapter.RankAdapter` work on any
TorchRL loss, and the Parseval term and the warm start use it too. Every network attribute of the loss
(``actor_network``, ``qvalue_network``, ``critic_network``, ``value_network``, ...) lives in the loss's ``__dict__``
(not in ``loss.modules()``); each LowRankLinear's module path is mapped to keys of ``<name>_params`` and, if present,
``target_<name>_params``. Public names are re-exported by :mod:`adarl.core.adapter`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn

from adarl.core.lowrank import LowRankLinear
from adarl.errors import AdaRLValueError

__all__ = [
    "SCOPES",
    "ACTOR_NETWORK_NAMES",
    "SUPPORTED_LOSSES",
    "UNSUPPORTED_LOSSES",
    "check_loss_supported",
    "LowRankSite",
    "network_candidates",
    "layer_indices",
    "find_low_rank_layers",
    "SiteRanks",
]

SCOPES = ("actor", "critic", "both")
#: Network attributes of a loss that count as the actor (everything else with LowRankLinear layers is a critic).
ACTOR_NETWORK_NAMES = ("actor_network", "actor", "policy_network", "policy")

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


class SiteRanks:
    """The read-only rank views of an object holding ``sites`` (its :class:`LowRankSite` list): the surface logs,
    eval.csv, summary.json and reports read, shared by :class:`~adarl.core.adapter.RankAdapter` (which changes the
    ranks) and :class:`~adarl.core.restarts.ScheduledRestarts` (which never does)."""

    sites: list[LowRankSite]

    @property
    def ranks(self) -> dict[str, int]:
        """``{layer_path: current rank}`` of the layers (e.g. ``"actor_network.module.0.module.0.0"``)."""
        return {s.path: s.rank for s in self.sites}

    @property
    def layers(self) -> dict[str, str]:
        """``{layer_path: "actor" | "critic"}`` of the layers."""
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
