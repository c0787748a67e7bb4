"""Warm-start replay buffer after a rank event (paper App. D.5.3).

After each rank adaptation the paper pre-collects trajectories with the *updated* policy before optimisation
resumes, so that SAC does not over-fit the first few samples of the newly perturbed dynamics.
:class:`ReplayWarmStart` is that step as an ``on_truncate`` callback of :class:`adarl.adapter.RankAdapter`:

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
objects), which a same-device collector is: a rank event changes those parameters in place.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

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
        source: a ``torchrl.collectors.Collector`` or an ``(env, policy)`` pair.
        frames: frames to add (exactly this many: a collector's last batch is trimmed when the buffer is extended
            here; a collector that writes into the buffer itself adds whole batches of ``frames_per_batch``).
        mode: ``"refill"`` (default, paper D.5.3), ``"prefill"``, ``"reset"`` (empty only) or ``"keep"``.
        exploration_type: exploration used by the ``(env, policy)`` rollout (default: random sampling, as a
            collector does). Ignored for collectors (they use their own).

    Call it as ``warm_start(event)`` (the signature of ``on_truncate`` callbacks) or ``warm_start()``. Each call
    appends a :class:`WarmStartRecord` to :attr:`records` and returns it.
    """

    def __init__(self, replay_buffer, source, frames: int, mode: str = "refill", *, exploration_type=None) -> None:
        if mode not in WARM_START_MODES:
            raise AdaRLValueError(f"ReplayWarmStart: mode must be one of {list(WARM_START_MODES)}, got {mode!r}")
        minimum = 0 if mode in ("keep", "reset") else 1
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < minimum:
            raise AdaRLValueError(f"ReplayWarmStart: frames must be an integer >= {minimum} for mode {mode!r}, got {frames!r}")
        for attr in ("extend", "empty", "__len__"):
            if not hasattr(replay_buffer, attr):
                raise AdaRLValueError(
                    f"ReplayWarmStart: replay_buffer must be a TorchRL replay buffer (extend/empty/len), got "
                    f"{type(replay_buffer).__name__}"
                )
        if isinstance(source, tuple) and len(source) == 2:
            env, policy = source
            if not callable(getattr(env, "rollout", None)) or not callable(policy):
                raise AdaRLValueError("ReplayWarmStart: an (env, policy) source needs a TorchRL env and a callable policy")
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

    def __call__(self, event: Any = None) -> WarmStartRecord:
        rb = self.replay_buffer
        before = len(rb)
        step = getattr(event, "step", None)
        if self.mode in ("keep", "reset"):
            if self.mode == "reset":
                rb.empty()
            record = WarmStartRecord(step, self.mode, 0, before, len(rb), self.mode == "reset")
            self.records.append(record)
            return record
        emptied = self.mode == "refill"
        if emptied:
            rb.empty()
        start = self._writes()
        if isinstance(self.source, tuple):
            self._from_env(*self.source)
        else:
            self._from_collector(self.source)
        record = WarmStartRecord(step, self.mode, self._writes() - start, before, len(rb), emptied)
        self.records.append(record)
        return record

    def _writes(self) -> int:
        """Frames written so far (``write_count``, which also counts overwrites in a full buffer), else ``len``."""
        count = getattr(self.replay_buffer, "write_count", None)
        return int(count) if count is not None else len(self.replay_buffer)

    # -- sources ------------------------------------------------------------------------------------------------

    def _extend(self, data: TensorDictBase, limit: int) -> int:
        data = data.reshape(-1)
        if data.numel() > limit:
            data = data[:limit]
        self.replay_buffer.extend(data)
        return data.numel()

    def _from_env(self, env, policy) -> None:
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        n_envs = max(1, int(torch.Size(env.batch_size).numel()))
        steps = math.ceil(self.frames / n_envs)
        exploration = self.exploration_type if self.exploration_type is not None else ExplorationType.RANDOM
        with torch.no_grad(), set_exploration_type(exploration):
            data = env.rollout(steps, policy=policy, auto_reset=True, break_when_any_done=False)
        self._extend(data, self.frames)

    def _from_collector(self, collector) -> None:
        collector.reset()  # new episodes: a perturbation transform draws fresh dynamics at reset
        # The collector's random-action phase is gated on the buffer's write_count, which empty() resets: switch
        # it off so the frames come from the current policy.
        saved_random = getattr(collector, "init_random_frames", None)
        if saved_random:
            collector.init_random_frames = 0
        # A collector built with a replay buffer (and extend_buffer=False) writes each batch into it and returns None.
        writes_itself = (
            getattr(collector, "replay_buffer", None) is not None
            and not getattr(collector, "_ignore_rb", False)
            and not getattr(collector, "extend_buffer", True)
        )
        if writes_itself and collector.replay_buffer is not self.replay_buffer:
            raise AdaRLValueError(
                "ReplayWarmStart: the collector writes into its own replay buffer, which is not the one given"
            )
        added = 0
        try:
            while added < self.frames:
                before = self._writes()
                out = collector.rollout()
                if out is not None and not writes_itself:
                    self._extend(out, self.frames - added)
                grew = self._writes() - before
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
