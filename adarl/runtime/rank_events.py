"""Everything a rank event sets off besides the truncation itself, assembled and wired in one place.

:class:`~adarl.core.adapter.RankAdapter` changes the factors' shapes in place and restarts the LR schedules; the
rest of a run must follow. :class:`RankEventEffects` holds that rest, in order, and is registered on the adapter
as one ``on_truncate`` and one ``on_event`` callback (:func:`~adarl.runtime.builders.sac.build_sac_components` does
it, so a loop of your own gets the same effects as the recipe's trainer); a trainer adds its records with
:meth:`RankEventEffects.record_run` (:class:`RunRecords`: the only other place rank events are handled):

after an event that changed a rank (``on_truncate``):

1. the update step re-binds to the new shapes (a compiled step compiles once per event);
2. a lean collector finishes and drops the batch it is prefetching: nothing may step the env under the warm start;
3. every low-rank factor is checked alive: finite, non-zero, of rank >= 1
   (:func:`~adarl.runtime.guards.check_live_layers`);
4. the warm start refills (or empties) the replay buffer with the truncated policy (when its frames count towards
   the frame budget, at most what the budget has left: :attr:`RankEventEffects.frames_left`), then each
   ``after_warm_start`` hook gets its :class:`~adarl.core.warmstart.WarmStartRecord` (``None`` without a warm start):
   the trainer counts the frames and logs them (:meth:`RunRecords.count_warm_start`);
5. the lean collector starts a fresh episode (the warm start stepped the env);

after every event, changed or not (``on_event``): each ``after_event`` hook (the trainer's rank records and logs: a
refused candidate is a result too; :meth:`RunRecords.record_event`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch

from adarl.core.warmstart import ReplayWarmStart, WarmStartRecord
from adarl.fast.collector import LeanCollector
from adarl.runtime import metrics
from adarl.runtime.guards import check_live_layers
from adarl.runtime.update import UpdateStep

__all__ = ["RankEventEffects", "RunRecords"]


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
        #: the frames the warm start may still collect (a run's budget left, when they count towards it); None: all
        self.frames_left: Callable[[], int] | None = None

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
        record = None
        if self.warm_start is not None:
            limited = {} if self.frames_left is None else {"limit": self.frames_left()}
            record = self.warm_start(event, **limited)
        for hook in self.after_warm_start:
            hook(record)
        if self._reset is not None:  # the warm start stepped the env under it
            self._reset()

    __call__ = on_truncate

    def on_event(self, event) -> None:
        for hook in self.after_event:
            hook(event)

    def record_run(self, trainer) -> RunRecords:
        """Add a trainer's records of every event (:class:`RunRecords`) to the effects; returns them."""
        records = RunRecords(trainer)
        if trainer.recipe.replay.warm_start.count_frames:  # counted: it never collects past the frame budget
            self.frames_left = records.frames_left
        self.after_warm_start.append(records.count_warm_start)
        self.after_event.append(records.record_event)
        return records


class RunRecords:
    """What a trainer keeps of rank events: the warm start's frames (counted towards the budget unless
    ``replay.warm_start.count_frames`` is false, and logged), and after every event the ranks and acceptance errors
    logged and the rank history written. ``trainer``: a :class:`~adarl.runtime.trainers.base.BaseTrainer` (its
    counters, logger, run folder and components)."""

    def __init__(self, trainer) -> None:
        self.trainer = trainer

    def count_warm_start(self, record: WarmStartRecord | None) -> None:
        """After a rank event's warm start: its frames count towards the budget unless
        ``replay.warm_start.count_frames`` is false; ``warm_start/frames`` is logged (0 without a warm start)."""
        t = self.trainer
        added = int(record.frames_added) if record is not None else 0
        t.warm_start_frames += added
        if t.recipe.replay.warm_start.count_frames:
            t.frames += added
        t.logger.log_scalar(metrics.WARM_START_FRAMES, added, step=t.frames)

    def frames_left(self) -> int:
        """The frames the budget has left (``collector.total_frames`` less the frames counted so far): what a warm
        start whose frames count may collect. Before, one in the run's last batch collected past the budget
        (``total_frames=1500`` ended at 1750)."""
        t = self.trainer
        return max(0, int(t.recipe.collector.total_frames) - int(t.frames))

    def record_event(self, event) -> None:
        """After every rank event, changed or not (a refused candidate is a result too): ranks and history."""
        t = self.trainer
        adapter = t.c.adapter
        event.frames = t.frames  # the frames axis of the run's plots (ranks.json, ranks.csv)
        for name, rank in adapter.named_ranks.items():
            t.logger.log_scalar(metrics.rank(name), rank, step=t.frames)
        for record in event.layers:
            if record.error is not None:
                t.logger.log_scalar(metrics.rank_error(record.name or record.layer), float(record.error), step=t.frames)
        t.run_dir.write_rank_history(adapter.history, frames=t.frames)
