"""AdaRL-SAC end to end: :class:`Trainer` runs a SAC recipe (AdaRL and the SAC baselines) in a run folder.

What it adds to :class:`~adarl.runtime.trainers.base.BaseTrainer`: the replay buffer (filled from each batch,
saved beside checkpoints), the update-to-data cadence (``algorithm.utd_ratio`` from ``algorithm.update_after``
on), the update step (:class:`~adarl.runtime.update.UpdateStep`: TorchRL's ``SACLoss`` step or the fused one, both
checked by the divergence guard), and the records of rank events: the warm start's frames counted towards the
budget (unless ``replay.warm_start.count_frames`` is false), the ranks and acceptance errors logged, the rank
history written after every event. What a rank event sets off is assembled in one place,
:class:`~adarl.runtime.rank_events.RankEventEffects`.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from adarl.core.adapter import RankAdapter, resize_to_ranks
from adarl.core.warmstart import WarmStartRecord
from adarl.errors import CheckpointError
from adarl.runtime import metrics
from adarl.runtime.builders.sac import build_components, sac_parameters, update_after
from adarl.runtime.trainers.base import BaseTrainer

__all__ = ["Trainer"]


def _rank_summary(adapter: RankAdapter | None) -> str:
    """The progress bar's ranks: ``actor.layer0=11 actor.layer1=64 ...``."""
    if adapter is None:
        return "-"
    return " ".join(f"{name}={rank}" for name, rank in adapter.named_ranks.items())


class Trainer(BaseTrainer, algorithm="sac"):
    """Runs a SAC recipe in one run folder: train, adapt ranks, evaluate on nominal dynamics, checkpoint, report.

    ``Trainer(recipe, run_dir).train()`` for a new run; ``Trainer.resume(run_dir).train()`` to continue one.

    >>> from tensordict import TensorDict
    >>> from adarl import load_policy, load_recipe
    >>> from adarl.runtime.run_dir import RunDir
    >>> recipe = load_recipe("quickstart", ["collector.total_frames=400", "collector.init_random_frames=200",
    ...                                     "collector.frames_per_batch=100", "replay.size=400",
    ...                                     "replay.warm_start.frames=100", "eval.episodes=1", "eval.max_steps=50"])
    >>> summary = Trainer(recipe, RunDir.create("runs/tiny"), quiet=True).train()
    >>> summary["frames"], summary["updates"]
    (400, 200)
    >>> policy = load_policy("runs/tiny")  # the trained actor, a TorchRL ProbabilisticActor
    >>> policy(TensorDict(observation=torch.zeros(11)))["action"].shape
    torch.Size([3])
    """

    def __init__(
        self,
        recipe,
        run_dir,
        *,
        quiet: bool = False,
        _resume_state: dict | None = None,
        _log_from: int | None = None,
        _read_only: bool = False,
    ) -> None:
        self._pending_updates = 0.0
        super().__init__(
            recipe, run_dir, quiet=quiet, _resume_state=_resume_state, _log_from=_log_from, _read_only=_read_only
        )

    @property
    def adapter(self) -> RankAdapter | None:
        return self.c.adapter

    def _build_components(self, state: dict | None) -> dict[str, torch.Tensor]:
        init_random = None
        if state is not None and state.get("collector") is None:
            # Checkpoints without the collector's state (older format): skip the random frames already done.
            init_random = max(0, self.recipe.collector.init_random_frames - int(state["counters"]["frames"]))
        self.c = build_components(
            self.recipe,
            init_random_frames=init_random,
            scratch_dir=None if self.read_only else self.run_dir.path / "replay_storage",
        )
        if self.c.rank_events is not None:
            self.c.rank_events.after_warm_start.append(self._count_warm_start)
            self.c.rank_events.after_event.append(self._record_rank_event)
        return sac_parameters(self.c.modules.loss, self.recipe.algorithm.fixed_alpha)

    # ------------------------------------------------------------------ one batch
    def _consume(self, batch: TensorDictBase) -> list[dict[str, torch.Tensor]] | None:
        """Into the replay buffer (cut at the frame budget), then ``utd_ratio`` updates per frame once
        ``update_after`` frames are in."""
        rc, c = self.recipe, self.c
        total = rc.collector.total_frames
        batch = batch.reshape(-1)
        if self.frames + batch.numel() > total:
            batch = batch[: total - self.frames]
        c.replay_buffer.extend(batch)
        self.frames += batch.numel()
        self._log_episodes(batch)
        if self.frames < update_after(rc) or len(c.replay_buffer) < rc.algorithm.batch_size:
            return None
        self._pending_updates += batch.numel() * rc.algorithm.utd_ratio
        n_updates = int(self._pending_updates)
        self._pending_updates -= n_updates
        losses = []
        for _ in range(n_updates):
            if len(c.replay_buffer) < rc.algorithm.batch_size:
                break  # a rank event emptied the buffer ('reset'): resume once a batch of new data is in
            losses.append(self._update())
        return losses

    def _update(self) -> dict[str, torch.Tensor]:
        """One SAC optimisation step (guarded), then (maybe) a rank event."""
        out = self.c.update(self.guard, update=self.updates)
        self.updates += 1
        if self.c.adapter is not None:
            self.c.adapter.step()
        return out

    def _postfix(self) -> dict:
        return {"ret": f"{self.last_return:.1f}", "ranks": _rank_summary(self.c.adapter), "upd": self.updates}

    # ------------------------------------------------------------------ rank events (RankEventEffects hooks)
    def _count_warm_start(self, record: WarmStartRecord | None) -> None:
        """After a rank event's warm start: its frames count towards the budget unless
        ``replay.warm_start.count_frames`` is false; ``warm_start/frames`` is logged (0 without a warm start)."""
        added = int(record.frames_added) if record is not None else 0
        self.warm_start_frames += added
        if self.recipe.replay.warm_start.count_frames:
            self.frames += added
        self.logger.log_scalar(metrics.WARM_START_FRAMES, added, step=self.frames)

    def _record_rank_event(self, event) -> None:
        """After every rank event, changed or not (a refused candidate is a result too): ranks and history."""
        adapter = self.c.adapter
        for name, rank in adapter.named_ranks.items():
            self.logger.log_scalar(metrics.rank(name), rank, step=self.frames)
        for record in event.layers:
            if record.error is not None:
                self.logger.log_scalar(
                    metrics.rank_error(record.name or record.layer), float(record.error), step=self.frames
                )
        self.run_dir.write_rank_history(adapter.history, frames=self.frames)

    # ------------------------------------------------------------------ checkpoints
    def _extra_counters(self) -> dict:
        return {"pending_updates": self._pending_updates, "warm_start_frames": self.warm_start_frames}

    def _load_extra_counters(self, counters: dict) -> None:
        self._pending_updates = float(counters["pending_updates"])
        self.warm_start_frames = int(counters.get("warm_start_frames", 0))

    def _module_state(self) -> dict:
        c = self.c
        return {
            "loss": c.modules.loss.state_dict(),
            "adapter": c.adapter.state_dict() if c.adapter is not None else None,
            "warm_start": c.warm_start.state_dict() if c.warm_start is not None else None,
        }

    def _replay_buffer_to_save(self):
        rb = self.c.replay_buffer
        return rb if self.recipe.checkpoint.replay_buffer and len(rb) else None

    def _load_module_state(self, state: dict) -> None:
        c = self.c
        if state.get("adapter") is not None and isinstance(c.adapter, RankAdapter):  # its ranks, before its tensors
            resize_to_ranks(c.modules.loss, state["adapter"], optimizers=list(c.optimizers.values()))
        c.modules.loss.load_state_dict(state["loss"])

    def _load_extra_state(self, state: dict) -> None:
        c = self.c
        if c.adapter is not None and state.get("adapter") is not None:
            c.adapter.load_state_dict(state["adapter"])
        if c.warm_start is not None and state.get("warm_start") is not None:
            c.warm_start.load_state_dict(state["warm_start"])
        saved = state.get("replay_buffer_saved")
        if not self.read_only and (saved or (saved is None and self.recipe.checkpoint.replay_buffer)):
            source = state.get("checkpoint_file")  # the buffer lies beside the checkpoint file, wherever it is
            loaded = self.run_dir.load_replay_buffer(c.replay_buffer, frames=self.frames, checkpoint=source)
            if not loaded and saved:
                raise CheckpointError(
                    f"the replay buffer saved with the checkpoint at {self.frames} frames is missing "
                    f"from {Path(source).parent if source else self.run_dir.checkpoint_dir}"
                )
        if c.adapter is not None and not self.read_only:  # the rank history as of the checkpoint resumed
            self.run_dir.write_rank_history(c.adapter.history, frames=self.frames)
