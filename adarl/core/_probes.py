"""The probes of the acceptance step: run one network on a fixed batch with some factors replaced, compare outputs.

Why: Algorithm 1 applies a lower rank only if the truncated network still fits recent data, and
:class:`~adarl.core.rank.PolicyFitRule` trades that fit against the rank. Both measure a candidate on a detached
copy of the network's parameters (nothing the loss trains is touched), at the layer's current width (ranks beyond
the candidate are zero columns/rows), so no shape changes during a measurement. Re-exported by
:mod:`adarl.core.adapter`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adarl.core._sites import LowRankSite
from adarl.core._surgery import _padded_factors
from adarl.core.acceptance import relative_output_error
from adarl.errors import AdaRLValueError

__all__ = ["SiteMeasure", "member_probes", "fit_function"]


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


def member_probes(site: LowRankSite, batch: TensorDictBase, probes: dict) -> list[_NetworkProbe]:
    """One probe per ensemble member of the site's network, shared (through ``probes``) by the layers of that
    network, so that each layer is measured with the earlier layers' accepted truncations in place."""
    out = []
    for m in itertools.product(*[range(n) for n in site.batch_shape]):
        key = (site.network_name, tuple(m))
        if key not in probes:
            probes[key] = _NetworkProbe(site.network_name, site.network, site.params, tuple(m), batch)
        out.append(probes[key])
    return out


class SiteMeasure:
    """The relative output error of a site's network with the layer at a given rank (the worst ensemble member).

    ``u, s, vh``: the layer's SVD; ``members``: the ensemble indices (``[()]`` for a single network)."""

    def __init__(self, site: LowRankSite, u, s, vh, members: list[tuple], batch: TensorDictBase, probes: dict):
        self.site, self.u, self.s, self.vh, self.members = site, u, s, vh, members
        self.probes = member_probes(site, batch, probes)
        self._keys = (site.key + ("w1",), site.key + ("w2",))

    @property
    def finite(self) -> bool:
        """Whether the network's outputs on the batch are finite (else there is nothing to compare against)."""
        return all(bool(torch.isfinite(p.reference).all()) for p in self.probes)

    def replacement(self, rank: int) -> list[dict]:
        """Per member, the layer's factors at ``rank`` (stored at the current width)."""
        site = self.site
        w1, w2 = _padded_factors(self.u, self.s, self.vh, int(rank), site.rank, site.w1.dtype)
        w1, w2 = w1.to(site.w1.device), w2.to(site.w1.device)
        key1, key2 = self._keys
        return [{key1: w1[m], key2: w2[m]} for m in self.members]

    def error_at(self, rank: int) -> float:
        errs = [p.relative_error(r) for p, r in zip(self.probes, self.replacement(rank))]
        return math.nan if any(math.isnan(e) for e in errs) else max(errs)

    def commit(self, rank: int) -> None:
        """Keep the layer at ``rank`` in the probes: later layers of this network are measured with it in place."""
        for p, r in zip(self.probes, self.replacement(rank)):
            p.commit(r)


def fit_function(site: LowRankSite, member: tuple, u, s, vh, batch: TensorDictBase) -> Callable[[int], float]:
    """``fit(rank)``: the mean output distance of one member's network with the layer at ``rank`` (what a
    ``needs_fit`` rule such as :class:`~adarl.core.rank.PolicyFitRule` trades against the rank)."""
    probe = _NetworkProbe(site.network_name, site.network, site.params, member, batch)
    width = site.rank
    dtype = site.w1.dtype
    device = site.w1.device
    key1, key2 = site.key + ("w1",), site.key + ("w2",)

    def fit(rank: int) -> float:
        w1, w2 = _padded_factors(u, s, vh, int(rank), width, dtype)
        return probe.distance({key1: w1.to(device), key2: w2.to(device)})

    return fit
