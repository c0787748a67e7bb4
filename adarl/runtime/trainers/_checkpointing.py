"""What a trainer's checkpoint holds, how it is written and how it loads back: :class:`Checkpointing`.

A mixin of :class:`~adarl.runtime.trainers.base.BaseTrainer`, apart because exact resume is one idea with its own
contract: every checkpoint holds the counters (the subclass's :attr:`~adarl.runtime.trainers.base.BaseTrainer.counters`
too), the components' own state, the callbacks' and the global RNGs, the replay buffer beside it when configured; it is
checked against the run's recipe before any tensor is used, and a checkpoint that does not fit is refused in one line.
"""

from __future__ import annotations

from pathlib import Path

from adarl.errors import AdaRLError, CheckpointError
from adarl.runtime.state import rng_state, set_rng_state

__all__ = ["Checkpointing"]


class Checkpointing:
    """Checkpoint state for exact resume, for :class:`~adarl.runtime.trainers.base.BaseTrainer` (which provides the
    counters, components, callbacks, run folder and logger these methods read, and
    :meth:`~adarl.runtime.trainers.base.BaseTrainer.resume`, which picks the checkpoint and builds the trainer)."""

    def _load_checked(self, state: dict) -> None:
        """:meth:`_load_state`, with a checkpoint that does not fit (one written before checkpoints named their
        recipe, for other networks) refused in one line instead of a traceback from deep inside torch."""
        try:
            self._load_state(state)
        except AdaRLError:
            raise
        except (RuntimeError, KeyError, ValueError, IndexError, TypeError) as err:
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            where = state.get("checkpoint_file", "the checkpoint")
            raise CheckpointError(
                f"checkpoint {where!r} does not fit this run's recipe ({type(err).__name__}: "
                f"{first[:200]}); it was written for other networks or is damaged"
            ) from None

    def _counters(self) -> dict:
        return {
            "frames": self.frames,
            "updates": self.updates,
            "episodes": self.episodes,
            "last_eval_frames": self.last_eval_frames,
            "best_eval": self.best_eval,
            "last_ckpt_frames": self.last_ckpt_frames,
            "rollbacks": self.rollbacks,
            "wall_time_s": self._wall_time(),  # summed over the run's processes (not part of exact resume)
            **{name: getattr(self, name) for name in self.counters},
            "loss_sums": dict(self._loss_sums),
            "loss_count": self._loss_count,
            "last_log_frames": self._last_log_frames,
        }

    def state_dict(self) -> dict:
        """Everything needed to continue this run: the counters, the components' own state (networks, optimisers,
        the live episode, ...; :meth:`~adarl.runtime.builders.common.RunComponents.state_dict`) and the global RNGs
        (the replay buffer is dumped beside it when configured)."""
        counters = self._counters()
        components = self.c.state_dict()  # first: a lean collector's prefetched batch is finished before the RNGs
        return {"counters": counters, **components, "callbacks": self.hooks.state_dict(), "rng": rng_state()}

    def _replay_buffer_to_save(self):
        """The replay buffer saved beside a checkpoint (None: none, or ``checkpoint.replay_buffer`` is false)."""
        rb = self.c.replay_buffer
        return rb if rb is not None and self.recipe.checkpoint.replay_buffer and len(rb) else None

    def save_checkpoint(self, *, scheduled: bool = True) -> Path:
        """Write a checkpoint (atomically; metric files are fsync'ed first so they are as durable as it).

        ``scheduled=False`` (an interrupt) does not move the checkpoint schedule, so resumed runs keep it.
        """
        if scheduled:
            self.last_ckpt_frames = self.frames
        self.run_dir.sync_metrics(self.logger)
        rb = self._replay_buffer_to_save()
        state = self.state_dict()
        state["replay_buffer_saved"] = rb is not None
        return self.run_dir.save_checkpoint(
            state,
            frames=self.frames,
            keep_last=self.recipe.checkpoint.keep_last,
            replay_buffer=rb,
            fingerprint=self.fingerprint,
        )

    def _load_state(self, state: dict) -> None:
        cnt = state["counters"]
        self.frames, self.updates, self.episodes = int(cnt["frames"]), int(cnt["updates"]), int(cnt["episodes"])
        self.last_eval_frames = int(cnt["last_eval_frames"])
        self.last_ckpt_frames = int(cnt.get("last_ckpt_frames", self.frames))
        self.best_eval = float(cnt["best_eval"])
        self.rollbacks = int(cnt.get("rollbacks", 0))
        if self._clock is None:  # resuming (a rollback, in training, keeps counting this process's time)
            self._wall_before = float(cnt.get("wall_time_s", 0.0))
        self._loss_sums = {k: float(v) for k, v in cnt.get("loss_sums", {}).items()}
        self._loss_count = int(cnt.get("loss_count", 0))
        self._last_log_frames = int(cnt.get("last_log_frames", self.frames))
        for name, (kind, default) in self.counters.items():
            setattr(self, name, kind(cnt[name] if default is None else cnt.get(name, default)))
        self.c.load_state_dict(state, fill_replay_buffer=lambda rb: self._load_replay_buffer(rb, state))
        self.hooks.load_state_dict(state.get("callbacks"))
        if self.adapter is not None and not self.read_only:  # the rank history as of the checkpoint resumed
            self.run_dir.write_rank_history(self.adapter.history, frames=self.frames)
        set_rng_state(state["rng"])  # last: nothing after it may draw random numbers

    def _load_replay_buffer(self, replay_buffer, state: dict) -> None:
        """Fill the replay buffer from the one saved beside the checkpoint (a buffer saved but missing is an error);
        an evaluator (read-only) leaves it empty."""
        saved = state.get("replay_buffer_saved")
        if self.read_only or not (saved or (saved is None and self.recipe.checkpoint.replay_buffer)):
            return
        source = state.get("checkpoint_file")  # the buffer lies beside the checkpoint file, wherever it is
        loaded = self.run_dir.load_replay_buffer(replay_buffer, frames=self.frames, checkpoint=source)
        if not loaded and saved:
            raise CheckpointError(
                f"the replay buffer saved with the checkpoint at {self.frames} frames is missing "
                f"from {Path(source).parent if source else self.run_dir.checkpoint_dir}"
            )
