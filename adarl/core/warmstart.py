"""Warm-start replay buffer after a rank event (paper App. D.5.3).

After each rank adaptation the paper pre-collects trajectories with the *updated* policy before optimisation
resumes, so that SAC does not over-fit the first few samples of the newly perturbed dynamics.
:class:`ReplayWarmStart` is that step as an ``on_truncate`` callback of :class:`adarl.core.adapter.RankAdapter`:

* ``mode="refill"``: empty the buffer, reset the environment (so a dynamics-perturbation transform draws new
  dynamics) and fill it with ``frames`` frames collected by the current policy;
* ``mode="prefill"``: the same without emptying (new frames are added to the old ones);
* ``mode="reset"``: empty the buffer and add nothing: optimisation resumes on the few transitions collected after
  the event, what the paper's first experiments did (App. D.5.3: "the replay buffer is effectively reset after each
  rank update"; the control of Fig. 9);
* ``mode="keep"``: do nothing (the old data stays; no warm start).

``source`` is a :class:`torchrl.collectors.Collector` (its :meth:`~torchrl.collectors.Collector.reset` and
:meth:`~torchrl.collectors.Collector.rollout` are used: one ``rollout()`` is one batch of ``frames_per_batch`` env
steps; it does not advance the collector's frame counter, so warm-start frames do not count against
``total_frames``) or an ``(env, policy)`` pair rolled out with ``env.rollout(..., auto_reset=True,
break_when_any_done=False)``. Either way the policy must be the loss's actor itself (the same ``Parameter``
objects), which a same-device collector is: a rank event changes those parameters in place. At an event this is
checked: a policy holding LowRankLinear layers that are not the loss's (a copy) is refused, since it would refill
the buffer with the pre-truncation policy. Multi-process collectors cannot be the source (they cannot collect one
batch on demand): give those set-ups an ``(env, actor)`` pair.

Emptying keeps the buffer's ``write_count`` (``rb.empty(empty_write_count=False)``): TorchRL gates a collector's
random-action phase on it (``Collector(..., replay_buffer=rb, init_random_frames=N)`` acts randomly while
``rb.write_count < N``), so resetting it would send the training loop back to random actions after every event.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adarl.core.adapter import find_low_rank_layers
from adarl.core.lowrank import iter_low_rank
from adarl.errors import AdaRLValueError

__all__ = ["ReplayWarmStart", "WarmStartRecord", "WARM_START_MODES"]

WARM_START_MODES = ("refill", "prefill", "reset", "keep")


@dataclass
class WarmStartRecord:
    """What one warm start did: the event step (if any), mode, frames added and buffer sizes around it."""

    step: int | None
    mode: str
    frames_added: int
    size_before: int
    size_after: int
    emptied: bool

    def as_dict(self) -> dict:
        return asdict(self)


class ReplayWarmStart:
    """Refill (or top up) a replay buffer with the current policy after a rank event.

    Args:
        replay_buffer: the TorchRL replay buffer the loss samples from.
        source: a ``torchrl.collectors.Collector`` (or :class:`~adarl.fast.collector.LeanCollector`, which has the
            same ``reset`` / ``rollout`` contract) or an ``(env, policy)`` pair.
        frames: frames to add (exactly this many: a collector's last batch is trimmed when the buffer is extended
            here; a collector that writes into the buffer itself adds whole batches of ``frames_per_batch``).
        mode: ``"refill"`` (default, paper D.5.3), ``"prefill"``, ``"reset"`` (empty only) or ``"keep"``.
        exploration_type: exploration used by the ``(env, policy)`` rollout (default: random sampling, as a
            collector does). Ignored for collectors (they use their own).

    Call it as ``warm_start(event)`` (the signature of ``on_truncate`` callbacks) or ``warm_start()``. Each call
    appends a :class:`WarmStartRecord` to :attr:`records` and returns it.

    >>> from torchrl.data import ListStorage, ReplayBuffer
    >>> from torchrl.envs import GymEnv
    >>> from torchrl.envs.utils import RandomPolicy
    >>> env = GymEnv("Pendulum-v1")
    >>> buffer = ReplayBuffer(storage=ListStorage(1000))
    >>> _ = buffer.extend(env.rollout(50))
    >>> warm_start = ReplayWarmStart(buffer, (env, RandomPolicy(env.action_spec)), frames=20)
    >>> warm_start()  # RankAdapter(..., on_truncate=[warm_start]) calls it after each rank event
    WarmStartRecord(step=None, mode='refill', frames_added=20, size_before=50, size_after=20, emptied=True)
    """

    def __init__(self, replay_buffer, source, frames: int, mode: str = "refill", *, exploration_type=None) -> None:
        if mode not in WARM_START_MODES:
            raise AdaRLValueError(f"ReplayWarmStart: mode must be one of {list(WARM_START_MODES)}, got {mode!r}")
        minimum = 0 if mode in ("keep", "reset") else 1
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < minimum:
            raise AdaRLValueError(
                f"ReplayWarmStart: frames must be an integer >= {minimum} for mode {mode!r}, got {frames!r}"
            )
        for attr in ("extend", "empty", "__len__"):
            if not hasattr(replay_buffer, attr):
                raise AdaRLValueError(
                    f"ReplayWarmStart: replay_buffer must be a TorchRL replay buffer (extend/empty/len), got "
                    f"{type(replay_buffer).__name__}"
                )
        if isinstance(source, tuple) and len(source) == 2:
            env, policy = source
            if not callable(getattr(env, "rollout", None)) or not callable(policy):
                raise AdaRLValueError(
                    "ReplayWarmStart: an (env, policy) source needs a TorchRL env and a callable policy"
                )
        elif getattr(source, "rebuilds_collector", False) or (
            callable(getattr(source, "reset", None)) and not callable(getattr(source, "rollout", None))
        ):
            raise AdaRLValueError(
                f"ReplayWarmStart: a {type(source).__name__} cannot be the warm start's source (a multi-process or "
                f"rebuilt collector cannot collect one batch on demand with the loss's own actor); give the warm start "
                f"an (env, actor) pair: an env in this process and the loss's actor itself"
            )
        elif not (callable(getattr(source, "rollout", None)) and callable(getattr(source, "reset", None))):
            raise AdaRLValueError(
                f"ReplayWarmStart: source must be a torchrl.collectors.Collector or an (env, policy) pair, got "
                f"{type(source).__name__}"
            )
        self.replay_buffer = replay_buffer
        self.source = source
        self.frames = frames
        self.mode = mode
        self.exploration_type = exploration_type
        self.records: list[WarmStartRecord] = []

    def __call__(self, event: Any = None, *, limit: int | None = None) -> WarmStartRecord:
        """Warm-start the buffer after ``event``. ``limit``: at most this many frames (a run's frame budget left,
        when its warm-start frames count towards the budget): 0 collects nothing and leaves the buffer as it is."""
        rb = self.replay_buffer
        before = len(rb)
        step = getattr(event, "step", None)
        if self.mode in ("keep", "reset"):
            if self.mode == "reset":
                self._empty()
            record = WarmStartRecord(step, self.mode, 0, before, len(rb), self.mode == "reset")
            self.records.append(record)
            return record
        self.check_event(event)
        frames = self.frames if limit is None else max(0, min(self.frames, int(limit)))
        if frames == 0:  # no budget left: the run ends with this batch, nothing is collected past its budget
            record = WarmStartRecord(step, self.mode, 0, before, before, False)
            self.records.append(record)
            return record
        emptied = self.mode == "refill"
        if emptied:
            self._empty()
        start = self._writes()
        if isinstance(self.source, tuple):
            self._from_env(*self.source, frames)
        else:
            self._from_collector(self.source, frames)
        record = WarmStartRecord(step, self.mode, self._frames(self._writes() - start), before, len(rb), emptied)
        self.records.append(record)
        return record

    def _empty(self) -> None:
        """Empty the buffer but keep its write count (a collector's random phase is gated on it)."""
        try:
            self.replay_buffer.empty(empty_write_count=False)
        except TypeError:  # a buffer of another kind, without TorchRL's keyword
            self.replay_buffer.empty()

    def check_event(self, event) -> None:
        """Refuse a policy that does not run the loss's own factors: it would refill with the pre-event policy.

        :class:`~adarl.core.adapter.RankAdapter` calls this before it changes anything (the event's decisions made), so
        a refused warm start leaves the model as it was; the call itself checks again.
        """
        if self.mode in ("keep", "reset"):  # nothing is collected
            return
        policy = self.source[1] if isinstance(self.source, tuple) else getattr(self.source, "policy", None)
        adapter = getattr(event, "adapter", None)
        if adapter is None or not getattr(event, "changed", False):
            return
        sites, _ = find_low_rank_layers(adapter.loss_module, "both")
        known = {id(t) for s in sites for t in (s.w1, s.template.w1)}
        layers = list(iter_low_rank(policy)) if isinstance(policy, torch.nn.Module) else []
        foreign = [name or "<policy>" for name, layer in layers if id(layer.w1) not in known]
        changed_actor = [r.layer for r in event.layers if r.changed and r.network == "actor"]
        if foreign or (changed_actor and not layers):
            what = (
                f"holds LowRankLinear layers that are not the loss's ({foreign[:3]}): a copy of the actor (a "
                f"deepcopy, a policy moved to another device) keeps the ranks and weights it had before the "
                f"event"
                if foreign
                else f"({type(policy).__name__}) holds no LowRankLinear layer, while the event changed {changed_actor}"
            )
            raise AdaRLValueError(
                f"ReplayWarmStart: the warm start's policy {what}, so the buffer would be refilled with the old "
                f"policy. "
                f"Give the collector the loss's actor itself (Collector(env, actor) on the actor's device: "
                f"collector.policy is actor), or give the warm start an (env, actor) pair; a collector that must copy "
                f"the policy is rebuilt after each event with adarl.CollectorRebuild"
            )

    def _writes(self) -> int:
        """Entries written so far: ``write_count`` (which also counts overwrites in a full buffer), else ``len``."""
        count = getattr(self.replay_buffer, "write_count", None)
        return int(count) if count is not None else len(self.replay_buffer)

    def _frames(self, entries: int) -> int:
        """Frames in ``entries`` buffer entries written just now (read from the last entry's batch size).

        An entry is one frame, except for a collector over several envs that holds the buffer: it stores one entry
        per env and batch, a segment of ``frames_per_batch / n_envs`` frames.
        """
        rb = self.replay_buffer
        if entries <= 0 or len(rb) == 0:
            return entries
        last = rb[len(rb) - 1 : len(rb)]
        per_entry = last.batch_size.numel() if isinstance(last, TensorDictBase) else 1
        return entries * int(per_entry)

    # -- sources ------------------------------------------------------------------------------------------------

    def _extend(self, data: TensorDictBase, limit: int) -> int:
        data = data.reshape(-1)
        if data.numel() > limit:
            data = data[:limit]
        self.replay_buffer.extend(data)
        return data.numel()

    def _from_env(self, env, policy, frames: int) -> None:
        n_envs = max(1, int(torch.Size(env.batch_size).numel()))
        steps = math.ceil(frames / n_envs)
        exploration = self.exploration_type if self.exploration_type is not None else ExplorationType.RANDOM
        with torch.no_grad(), set_exploration_type(exploration):
            data = env.rollout(steps, policy=policy, auto_reset=True, break_when_any_done=False)
        self._extend(data, frames)

    def _from_collector(self, collector, frames: int) -> None:
        collector.reset()  # new episodes: a perturbation transform draws fresh dynamics at reset
        # The collector's random-action phase (gated on its frame count, or on the buffer's write_count when it holds
        # the buffer): switched off while it collects here, so the frames come from the current policy.
        saved_random = getattr(collector, "init_random_frames", None)
        if saved_random:
            collector.init_random_frames = 0
        own = getattr(collector, "replay_buffer", None)
        own = None if getattr(collector, "_ignore_rb", False) else own
        # extend_buffer=False: the collector writes each step into its buffer itself and rollout() returns None.
        writes_itself = own is not None and not getattr(collector, "extend_buffer", True)
        if writes_itself and own is not self.replay_buffer:
            raise AdaRLValueError(
                "ReplayWarmStart: the collector writes into its own replay buffer, which is not the one given"
            )
        holds_buffer = own is self.replay_buffer  # then its iterator fixes the buffer's layout
        added = 0
        try:
            while added < frames:
                before = self._writes()
                out = collector.rollout()
                if out is not None and not writes_itself:
                    if holds_buffer and out.ndim > 1:
                        # extended as the collector's own iterator does (over several envs a buffer entry is one
                        # env's segment of the batch), so the buffer keeps one layout: whole batches
                        post = getattr(collector, "postproc", None)
                        self.replay_buffer.extend(post(out) if callable(post) else out)
                    else:
                        self._extend(out, frames - added)
                grew = self._frames(self._writes() - before)
                if grew <= 0:
                    raise AdaRLValueError("ReplayWarmStart: a collector rollout added no frame to the replay buffer")
                added += grew
        finally:
            if saved_random:
                collector.init_random_frames = saved_random

    def state_dict(self) -> dict:
        return {"records": [r.as_dict() for r in self.records]}

    def load_state_dict(self, state_dict: dict) -> None:
        self.records = [WarmStartRecord(**r) for r in state_dict.get("records", [])]

    def __repr__(self) -> str:
        return f"ReplayWarmStart(mode={self.mode!r}, frames={self.frames}, source={type(self.source).__name__})"
