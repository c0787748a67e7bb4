"""Everything a rank event sets off besides the truncation itself, assembled in one place.

:class:`~adarl.core.adapter.RankAdapter` changes the factors' shapes in place and restarts the LR schedules; the
rest of a run must follow. :class:`RankEventEffects` holds that rest, in order, and is registered on the adapter
as one ``on_truncate`` and one ``on_event`` callback (:func:`~adarl.runtime.builders.sac.build_components` does
it, so a loop of your own gets the same effects as the recipe's trainer):

after an event that changed a rank (``on_truncate``):

1. the update step re-binds to the new shapes (a compiled step compiles once per event);
2. a lean collector finishes and drops the batch it is prefetching: nothing may step the env under the warm start;
3. every low-rank factor is checked alive: finite, non-zero, of rank >= 1
   (:func:`~adarl.runtime.guards.check_live_layers`);
4. the warm start refills (or empties) the replay buffer with the truncated policy, then each ``after_warm_start``
   hook gets its :class:`~adarl.core.warmstart.WarmStartRecord` (``None`` without a warm start): the trainer counts
   the frames and logs them;
5. the lean collector starts a fresh episode (the warm start stepped the env);

after every event, changed or not (``on_event``): each ``after_event`` hook (the trainer's rank records and logs: a
refused candidate is a result too).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch

from adarl.core.warmstart import ReplayWarmStart, WarmStartRecord
from adarl.fast.collector import LeanCollector
from adarl.runtime.guards import check_live_layers
from adarl.runtime.update import UpdateStep

__all__ = ["RankEventEffects"]


class RankEventEffects:
    """The side effects of rank events in a run, in their order (see the module docstring).

    Args:
        update: the run's update step (re-bound after each event).
        collector: the run's collector; a :class:`~adarl.fast.collector.LeanCollector` is reset around the warm start.
        warm_start: the replay warm start, or None.
        factors: ``{name: w1 or w2 tensor}`` of every low-rank layer the loss trains (checked after each event).
    """

    def __init__(
        self, update: UpdateStep, collector, warm_start: ReplayWarmStart | None, factors: Mapping[str, torch.Tensor]
    ) -> None:
        self.update, self.collector, self.warm_start = update, collector, warm_start
        self.factors = dict(factors)
        self._reset = collector.reset if isinstance(collector, LeanCollector) else None
        self.after_warm_start: list[Callable[[WarmStartRecord | None], None]] = []
        self.after_event: list[Callable[[object], None]] = []

    def register(self, adapter) -> None:
        """Put the effects on ``adapter``: this object as an ``on_truncate`` callback (its :meth:`check_event` runs
        before anything changes), :meth:`on_event` as an ``on_event`` one."""
        adapter.on_truncate.append(self)
        adapter.on_event.append(self.on_event)

    def check_event(self, event) -> None:
        """Called by the adapter before anything changes: the warm start may refuse the event (its policy must run
        the loss's own factors)."""
        if self.warm_start is not None:
            self.warm_start.check_event(event)

    def on_truncate(self, event) -> None:
        self.update.on_rank_event(event)
        if self._reset is not None:  # nothing may step the env under the warm start (a prefetched batch is dropped)
            self._reset()
        check_live_layers(self.factors, event_step=getattr(event, "step", None))
        record = self.warm_start(event) if self.warm_start is not None else None
        for hook in self.after_warm_start:
            hook(record)
        if self._reset is not None:  # the warm start stepped the env under it
            self._reset()

    __call__ = on_truncate

    def on_event(self, event) -> None:
        for hook in self.after_event:
            hook(event)
