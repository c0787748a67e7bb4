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

This module is the hub: the adapter itself, and every public name of its parts, each a private module with one job
(as TorchRL splits its transforms): ``_sites`` (finding the layers; the supported and refused loss tables),
``_records`` (:class:`LayerRecord`, :class:`RankEvent`), ``_surgery`` (the in-place resize, targets and optimiser
state; :func:`resize_to_ranks`), ``_probes`` (the acceptance step's measurements), ``_adapter_args`` (the
constructor's checks). Import from here.
"""

from __future__ import annotations

import itertools
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.trainers.trainers import TrainerHookBase

from adarl.core._adapter_args import check_adapter_args
from adarl.core._probes import SiteMeasure, _NetworkProbe, fit_function
from adarl.core._records import LayerRecord, RankEvent
from adarl.core._sites import (
    ACTOR_NETWORK_NAMES,
    SCOPES,
    SUPPORTED_LOSSES,
    UNSUPPORTED_LOSSES,
    LowRankSite,
    SiteRanks,
    _name_sites,
    check_loss_supported,
    find_low_rank_layers,
    layer_indices,
    network_candidates,
)
from adarl.core._surgery import (
    PROJECT_COND_LIMIT,
    TARGET_MODES,
    _erase_loss_caches,
    _padded_factors,
    apply_rank,
    follow_shared,
    resize_to_ranks,
)
from adarl.core.acceptance import ProjectionAcceptance
from adarl.core.lowrank import factor_svd, truncation_error
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

#: reached here before the split (the Parseval term, tests, the calibration benchmark): kept importable from here
_ALSO_HERE = (network_candidates, PROJECT_COND_LIMIT, _name_sites, _NetworkProbe, _padded_factors)
#: every live adapter: an event on factors another adapter's loss shares (one actor, two losses) brings that loss's
#: targets, caches and optimiser state along (:func:`~adarl.core._surgery.follow_shared`)
_LIVE: weakref.WeakSet = weakref.WeakSet()


@dataclass
class _Proposal:
    """What the rule proposes for one layer: its SVD, each member's choice (and why a member kept its rank)."""

    u: torch.Tensor
    s: torch.Tensor
    vh: torch.Tensor
    members: list[tuple]
    choices: list[int]
    reasons: list[str]

    @property
    def candidate(self) -> int:
        """The layer's candidate: the largest member's choice (no member is cut below what it asks for)."""
        return max(self.choices)

    @property
    def svd(self) -> tuple:
        return self.u, self.s, self.vh


@dataclass
class _Verdict:
    """The rank a layer gets, and what was measured to decide it (``None``: nothing measured)."""

    rank: int
    candidate_error: float | None = None
    error: float | None = None
    tolerance: float | None = None
    tried: list | None = None
    note: str | None = None


class RankAdapter(SiteRanks, TrainerHookBase):
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
        check_loss_supported(loss_module)  # first: its warning points at the caller's line (stacklevel)
        args = check_adapter_args(
            optimizers=optimizers,
            rule=rule,
            interval=interval,
            scope=scope,
            min_rank=min_rank,
            target_mode=target_mode,
            lr_schedulers=lr_schedulers,
            on_truncate=on_truncate,
            on_event=on_event,
            fit_data=fit_data,
            num_threads=num_threads,
            acceptance=acceptance,
            log_step=log_step,
        )
        self.loss_module = loss_module
        self.optimizers = args.optimizers
        self.rule = rule
        self.interval = args.interval
        self.scope = args.scope
        self.min_rank = args.min_rank
        self.target_mode = args.target_mode
        self.lr_schedulers = args.lr_schedulers
        self.on_truncate = args.on_truncate
        self.on_event = args.on_event
        self.acceptance = acceptance
        self.fit_data = fit_data
        self.logger = logger
        self.log_step = log_step
        self.num_threads = args.num_threads
        self.sites, searched = find_low_rank_layers(loss_module, scope)
        if not self.sites:
            raise AdaRLValueError(
                f"no LowRankLinear layer found in scope {scope!r} of {type(loss_module).__name__}; networks searched: "
                f"{searched or 'none'} (build them with adarl.low_rank_mlp or LowRankLinear)"
            )
        self._check_optimizers(self.sites)
        self.step_count = 0
        self.history: list[RankEvent] = []
        _LIVE.add(self)

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

    def _all_sites(self) -> list[LowRankSite]:
        """Every low-rank layer of the loss, in scope or not: another adapter's event on factors this loss shares
        must reach this loss's targets whatever this adapter's scope."""
        if self.scope == "both":
            return self.sites
        try:
            return find_low_rank_layers(self.loss_module, "both")[0]
        except AdaRLValueError:
            return self.sites

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
            others = [a for a in list(_LIVE) if a is not self] if any(r.changed for _, r, _ in plans) else []
            peers = [(a._all_sites(), a.loss_module, a.optimizers) for a in others]
            for site, record, svd in plans:
                if record.changed:
                    record.target = apply_rank(site, record.new_rank, *svd, self.target_mode, self.optimizers)
                    follow_shared(site, peers)  # another loss training these factors: its targets follow
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

    def _decide(self, site: LowRankSite, step: int, batch, probes: dict) -> tuple[LayerRecord, tuple | None]:
        """One layer's rank at an event: the rule proposes, the probes measure, the acceptance step accepts, the
        record says what happened and why. Returns the record and the SVD the change is applied from."""
        nonfinite = [name for name, t in (("w1", site.w1), ("w2", site.w2)) if not bool(torch.isfinite(t).all())]
        if nonfinite:  # the SVD would raise; the event must not act on a diverged layer
            reason = f"non-finite values in {' and '.join(nonfinite)} (training diverged?); rank kept"
            return LayerRecord(
                step=step,
                layer=site.path,
                network=site.role,
                old_rank=site.rank,
                new_rank=site.rank,
                singular_values=[],
                retained_energy=float("nan"),
                truncation_error=float("nan"),
                skipped=reason,
                name=site.name,
            ), None
        proposal = self._propose(site, batch)
        verdict = self._accept(site, proposal, batch, probes)
        return self._record(site, step, proposal, verdict), proposal.svd

    def _propose(self, site: LowRankSite, batch) -> _Proposal:
        """The rule's choice for every ensemble member, from the layer's singular values."""
        current = site.rank
        lead = site.batch_shape
        u, s, vh = factor_svd(site.w1, site.w2)
        members = list(itertools.product(*[range(n) for n in lead]))  # [()] for a single network
        choices, reasons = [], []
        for m in members:
            idx = tuple(m)
            fit = fit_function(site, idx, u[idx], s[idx], vh[idx], batch) if self.rule.needs_fit else None
            d = self.rule(s[idx], current, min_rank=self.min_rank, fit=fit)
            choices.append(int(d.rank))
            if d.skipped:
                reasons.append(d.skipped if not lead else f"member {idx}: {d.skipped}")
        return _Proposal(u, s, vh, members, choices, reasons)

    def _measure(self, site: LowRankSite, proposal: _Proposal, batch, probes: dict) -> SiteMeasure:
        """The network's output error with the layer at a given rank (on ``fit_data``, every member)."""
        return SiteMeasure(site, proposal.u, proposal.s, proposal.vh, proposal.members, batch, probes)

    def _accept(self, site: LowRankSite, proposal: _Proposal, batch, probes: dict) -> _Verdict:
        """The rank the layer gets: the candidate, unless the acceptance step refuses it (``r_new = r_old``) or
        settles on another. A lower rank is measured when ``fit_data`` is given (recorded even without acceptance)."""
        current, candidate = site.rank, proposal.candidate
        if batch is None or proposal.reasons:
            return _Verdict(candidate)  # nothing to measure on, or the rule kept the rank: nothing measured
        if candidate >= current:
            return _Verdict(candidate, candidate_error=0.0, error=0.0)
        measure = self._measure(site, proposal, batch, probes)
        if self.acceptance is not None and not measure.finite:  # nothing to compare against: keep it, say why
            verdict = _Verdict(
                current,
                note=(
                    f"the {site.role}'s outputs on fit_data are non-finite (NaN/inf weights "
                    f"elsewhere in the network, or in the batch); rank kept"
                ),
            )
        elif self.acceptance is not None:
            result = self.acceptance.resolve(candidate, current, measure.error_at, site.role)
            verdict = _Verdict(
                result.rank,
                candidate_error=result.candidate_error,
                error=result.error,
                tolerance=result.tolerance,
                tried=[list(t) for t in result.tried],
                note=result.reason,
            )
        else:
            err = measure.error_at(candidate)
            verdict = _Verdict(candidate, candidate_error=err, error=err, tried=[[candidate, err]])
        if verdict.rank < current:  # later layers of this network are measured with this truncation in place
            measure.commit(verdict.rank)
        return verdict

    def _record(self, site: LowRankSite, step: int, proposal: _Proposal, verdict: _Verdict) -> LayerRecord:
        """The event's record of one layer: spectrum, energy and error at the new rank, and why it kept its rank."""
        current, candidate, new = site.rank, proposal.candidate, verdict.rank
        lead = site.batch_shape
        flat_s = proposal.s.reshape(-1, proposal.s.shape[-1])
        energies = [energy_share(row, new) for row in flat_s]
        errors = [float(truncation_error(row, new)) for row in flat_s]
        skipped = None
        if new == current:
            if proposal.reasons:
                skipped = "; ".join(proposal.reasons)
            elif candidate < current:
                skipped = verdict.note
            else:
                skipped = f"rule kept rank {current}"
        return LayerRecord(
            step=step,
            layer=site.path,
            network=site.role,
            old_rank=current,
            new_rank=new,
            singular_values=[row.tolist() for row in flat_s] if lead else flat_s[0].tolist(),
            retained_energy=energies if lead else energies[0],
            truncation_error=errors if lead else errors[0],
            skipped=skipped,
            member_ranks=proposal.choices if lead else None,
            candidate=candidate,
            candidate_error=verdict.candidate_error,
            error=verdict.error,
            tolerance=verdict.tolerance,
            tried=verdict.tried,
            note=verdict.note if new != current else None,
            name=site.name,
        )

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
