"""The small registry through which the baselines plug into the recipe builders (:mod:`adarl.runtime.builders`).

Why: the builders are generic; they name no baseline. For a recipe's ``network.<net>`` section they ask the
registered *network variants* which arguments they want (the sparsification layer of Tiwari et al., Parseval's
scale layers) and build the network with the registered *variant builder* when any are asked for; for
``network.<net>.init.scheme`` they call the registered *initialisation*; and they add every registered *loss term*
the recipe switches on (Parseval regularisation). Each baseline module registers itself when :mod:`adarl.baselines`
is imported; your own code registers more the same way. Algorithms (``algorithm.name``: a loss, its options and
its base loop) register in :mod:`adarl.plugins` (``register_algorithm``, re-exported here), which installed packages
reach through the ``adarl.plugins`` entry-point group; it lives below every wing because recipes are validated
without torch. Each table here is an :class:`adarl.plugins.Registry` too.

>>> from adarl.baselines import registry
>>> sorted(registry.init_schemes())
['default', 'independent_factors', 'orthogonal']
>>> sorted(registry.loss_term_names())
['parseval']
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from torch import nn

from adarl.errors import AdaRLValueError
from adarl.plugins import Registry, register_algorithm

__all__ = [
    "register_algorithm",
    "Init",
    "register_network_variant",
    "register_variant_builder",
    "register_init",
    "register_loss_term",
    "network_kwargs",
    "build_variant_network",
    "init_scheme",
    "init_schemes",
    "loss_terms",
    "loss_term_names",
]

#: ``(mlp_config, algorithm_config, action_dim) -> dict``: the keyword arguments of the variant builder a recipe's
#: ``network.<net>`` section asks for (``{}``: none).
NetworkVariant = Callable[[Any, Any, int], dict]
#: ``(loss, algorithm_config) -> nn.Module | None``: a term added to the loss (with ``wrap_output(td)``), or None
#: when the recipe does not switch it on.
LossTerm = Callable[[nn.Module, Any], "nn.Module | None"]


@dataclass(frozen=True)
class Init:
    """An initialisation scheme: of one network (``module(net, gain, head_gain)``), and of a network held by a
    TorchRL loss (``loss(loss, network_attribute, gain, head_gain)``: each member of a stacked ensemble apart)."""

    module: Callable[..., Any]
    loss: Callable[..., Any]


# Each a registry of adarl.plugins (by name, in registration order; a later registration of a name replaces it, as
# re-importing a baseline module does). 'default' is an init scheme like the others: each layer keeps its own init.
_variants: Registry[NetworkVariant] = Registry("network variant", plugins=False, order=list)
_variant_builder: Registry[Callable[..., nn.Module]] = Registry("variant builder", plugins=False)
_inits: Registry[Init | None] = Registry("init scheme", plugins=False, order=list)
_loss_terms: Registry[LossTerm] = Registry("loss term", plugins=False, order=list)
_inits.register("default", None)


def register_network_variant(name: str, kwargs: NetworkVariant) -> None:
    """Register a network variant: ``kwargs(mlp_config, algorithm_config, action_dim)`` returns the variant
    builder's arguments it wants for that network section (``{}`` when the recipe does not ask for it)."""
    _variants.register(name, kwargs, replace=True)


def register_variant_builder(build: Callable[..., nn.Module]) -> None:
    """The builder of every variant network: ``build(in_features, out_features, num_cells, activation_class,
    low_rank_layers, rank, device=..., **variant_kwargs)``."""
    _variant_builder.register("network", build, replace=True)


def register_init(scheme: str, module: Callable[..., Any], loss: Callable[..., Any]) -> None:
    """Register ``network.<net>.init.scheme: <scheme>`` (see :class:`Init`)."""
    _inits.register(scheme, Init(module, loss), replace=True)


def register_loss_term(name: str, make: LossTerm) -> None:
    """Register a loss term: ``make(loss, algorithm_config)`` builds it when the recipe switches it on, else None."""
    _loss_terms.register(name, make, replace=True)


def network_kwargs(mlp_config, algorithm_config, action_dim: int) -> dict:
    """The variant builder's arguments for one ``network.<net>`` section (``{}``: a plain or low-rank MLP)."""
    out: dict = {}
    for kwargs in _variants.entries.values():
        out.update(kwargs(mlp_config, algorithm_config, action_dim))
    return out


def build_variant_network(*args, **kwargs) -> nn.Module:
    """Build a network with variants (:func:`register_variant_builder`)."""
    if "network" not in _variant_builder:
        raise AdaRLValueError(
            f"network variants {sorted(kwargs)} asked for, but no variant builder is registered "
            "(import adarl.baselines)"
        )
    return _variant_builder.get("network")(*args, **kwargs)


def init_schemes() -> list[str]:
    """``network.<net>.init.scheme`` values: ``'default'`` (each layer's own init) and the registered ones."""
    return _inits.names(load=False)


def init_scheme(scheme: str) -> Init | None:
    """The registered :class:`Init` of ``scheme``; None for ``'default'`` (each layer keeps its own init)."""
    return _inits.get(scheme)


def loss_term_names() -> list[str]:
    return _loss_terms.names(load=False)


def loss_terms(loss: nn.Module, algorithm_config) -> dict[str, nn.Module]:
    """``{name: term}`` of every registered loss term the recipe's ``algorithm`` section switches on."""
    out = {}
    for name, make in _loss_terms.entries.items():
        term = make(loss, algorithm_config)
        if term is not None:
            out[name] = term
    return out
