"""Rebuild a collector after a rank event, for collectors that cannot follow a change of parameter shapes.

A rank event changes the shapes of the factors ``w1``/``w2`` in place (same ``Parameter`` objects, new ``.data``).
A collector that runs the actor itself in the training process sees the new tensors at once. Two kinds cannot:

* process collectors on CPU (``MultiSyncCollector``, ``MultiAsyncCollector``, ``AsyncCollector``,
  ``Collector(num_collectors=...)``) map the policy's parameters into shared memory at construction; the new
  factors are new tensors the workers never see, while in-place updates of the unchanged tensors (biases, head)
  still reach them: they would act with a hybrid of the old and the new policy, and ``update_policy_weights_()``
  fails on the size mismatch;
* collectors that run a copy of the policy (another device, a deep copy) keep the copy's old shapes.

:class:`CollectorRebuild` builds the collector from a factory and builds it again after each event that changed a
rank (it is an ``on_truncate`` callback of :class:`adarl.RankAdapter`), so the new workers map the new tensors.
Iterate it instead of the collector: it yields the current collector's batches and switches to the new collector
after a rebuild. :class:`adarl.RankAdapter` refuses an event that would change factors held in shared memory unless
a ``CollectorRebuild`` is among its ``on_truncate`` callbacks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from adarl.core.lowrank import is_integer
from adarl.errors import AdaRLValueError

__all__ = ["CollectorRebuild"]


class CollectorRebuild:
    """A collector rebuilt by ``make_collector()`` after every rank event that changed a rank.

    Args:
        make_collector: builds the collector from the *live* actor (e.g. ``lambda: MultiSyncCollector([make_env] * 2,
            actor, frames_per_batch=200, total_frames=-1)``); called once here and once per rebuild. Give the
            collectors ``total_frames=-1`` and the budget to ``total_frames`` here: a rebuilt collector counts from 0.
        total_frames: stop iterating after this many frames (the batches' ``numel()``), over all the collectors
            built; ``-1`` never stops (break out of the loop yourself).

    ``rebuild()`` (or calling the object with the event, as ``on_truncate`` does) closes the current iterator, shuts
    the collector down and builds a new one; ``collector`` is the current one, ``rebuilds`` how many times it was
    rebuilt. Other attributes (``update_policy_weights_``, ``reset``, ``policy``...) are the current collector's.

    >>> from torchrl.collectors import Collector
    >>> from torchrl.envs import GymEnv
    >>> from torchrl.envs.utils import RandomPolicy
    >>> env = GymEnv("Pendulum-v1")
    >>> collector = CollectorRebuild(lambda: Collector(env, RandomPolicy(env.action_spec), frames_per_batch=10,
    ...                                                 total_frames=-1), total_frames=30)
    >>> sizes = []
    >>> for batch in collector:
    ...     sizes.append(batch.numel())
    ...     collector.rebuild()  # RankAdapter(..., on_truncate=[collector]) does this after a rank event
    >>> sizes, collector.rebuilds
    ([10, 10, 10], 3)
    >>> collector.shutdown()
    """

    #: RankAdapter lets an event change factors held in shared memory when a callback declares this.
    rebuilds_collector = True

    def __init__(self, make_collector: Callable[[], Any], total_frames: int = -1) -> None:
        if not callable(make_collector):
            raise AdaRLValueError(
                f"CollectorRebuild: make_collector must be a callable returning a collector (e.g. "
                f"lambda: MultiSyncCollector(...)), got {type(make_collector).__name__}"
            )
        if not is_integer(total_frames) or (total_frames < 1 and total_frames != -1):
            raise AdaRLValueError(
                f"CollectorRebuild: total_frames must be an integer >= 1, or -1 (no limit), got {total_frames!r}"
            )
        self.make_collector = make_collector
        self.total_frames = int(total_frames)
        self.frames = 0
        self.rebuilds = 0
        self._iterator: Iterator | None = None
        self.collector = self._build()

    def _build(self):
        collector = self.make_collector()
        if not callable(getattr(collector, "__iter__", None)) or not callable(getattr(collector, "shutdown", None)):
            raise AdaRLValueError(
                f"CollectorRebuild: make_collector() must return a TorchRL collector (iterable, with "
                f"shutdown()), got {type(collector).__name__}"
            )
        return collector

    def __call__(self, event: Any = None) -> None:
        self.rebuild()

    def rebuild(self) -> None:
        """Shut the current collector down and build a new one from the live actor."""
        self._close_iterator()
        self.collector.shutdown()
        self.collector = self._build()
        self.rebuilds += 1

    def _close_iterator(self) -> None:
        if self._iterator is not None:
            close = getattr(self._iterator, "close", None)
            if callable(close):
                close()
            self._iterator = None

    def __iter__(self) -> Iterator:
        while self.total_frames < 0 or self.frames < self.total_frames:
            if self._iterator is None:
                self._iterator = iter(self.collector)
            try:
                batch = next(self._iterator)
            except StopIteration:
                self._iterator = None
                return
            numel = getattr(batch, "numel", None)
            if callable(numel):
                self.frames += int(numel())
            yield batch

    def shutdown(self) -> None:
        self._close_iterator()
        self.collector.shutdown()

    def __getattr__(self, name: str):
        if name.startswith("_") or name == "collector":
            raise AttributeError(name)
        return getattr(self.collector, name)

    def __repr__(self) -> str:
        return f"CollectorRebuild({type(self.collector).__name__}, rebuilds={self.rebuilds}, frames={self.frames})"
