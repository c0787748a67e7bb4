"""The off-policy loop end to end: :class:`OffPolicyTrainer` runs a recipe on any off-policy family (``sac``: AdaRL
and the SAC baselines; ``td3``: TD3 and DDPG; a family of your own) in a run folder.

One trainer for every off-policy loss, as TorchRL's ``Trainer`` is one loop whatever the loss: what differs between
SAC and TD3 (networks, loss, update step) is the family's builder's (:func:`~adarl.runtime.families.family`,
``family(recipe).build(...)``), so a new family needs no trainer. What it adds to
:class:`~adarl.runtime.trainers.base.BaseTrainer`: its step. Each batch goes into the replay buffer, then the
update-to-data cadence (``algorithm.utd_ratio`` from ``algorithm.update_after`` on) runs the family's update step
(:class:`~adarl.runtime.update.UpdateStep`: TorchRL's ``SACLoss`` step or the fused one, TD3's delayed-actor step;
each checked by the divergence guard) and the rank adapter. Its components
(:class:`~adarl.runtime.builders.off_policy.OffPolicyComponents`) save and load their own state, replay buffer
included; what a rank event sets off, the warm start's frames and the rank records included, is wired in
:mod:`adarl.runtime.rank_events`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from adarl.core.adapter import RankAdapter
from adarl.runtime.builders.off_policy import OffPolicyComponents, update_after
from adarl.runtime.families import family
from adarl.runtime.trainers.base import BaseTrainer

__all__ = ["OffPolicyTrainer"]


def _rank_summary(adapter: RankAdapter | None) -> str:
    """The progress bar's ranks: ``actor.layer0=11 actor.layer1=64 ...``."""
    if adapter is None:
        return "-"
    return " ".join(f"{name}={rank}" for name, rank in adapter.named_ranks.items())


class OffPolicyTrainer(BaseTrainer):
    """Runs a recipe on an off-policy loop in one run folder: train, adapt ranks, evaluate on nominal dynamics,
    checkpoint, report.

    ``OffPolicyTrainer(recipe, run_dir).train()`` for a new run; ``BaseTrainer.resume(run_dir).train()`` to continue
    one.

    >>> from tensordict import TensorDict
    >>> from adarl import load_policy, load_recipe
    >>> from adarl.runtime.run_folder.run_dir import RunDir
    >>> recipe = load_recipe("quickstart", ["collector.total_frames=400", "collector.init_random_frames=200",
    ...                                     "collector.frames_per_batch=100", "replay.size=400",
    ...                                     "replay.warm_start.frames=100", "eval.episodes=1", "eval.max_steps=50"])
    >>> summary = OffPolicyTrainer(recipe, RunDir.create("runs/tiny"), quiet=True).train()
    >>> summary["frames"], summary["updates"]
    (400, 200)
    >>> policy = load_policy("runs/tiny")  # the trained actor, a TorchRL ProbabilisticActor
    >>> policy(TensorDict(observation=torch.zeros(11)))["action"].shape
    torch.Size([3])
    """

    #: the fraction of an update carried to the next batch (``utd_ratio`` times frames need not be whole), and the
    #: env frames rank events' warm starts collected
    counters = {"pending_updates": (float, None), "warm_start_frames": (int, 0)}

    def _build_components(self, state: dict | None) -> OffPolicyComponents:
        init_random = None
        if state is not None and state.get("collector") is None:
            # Checkpoints without the collector's state (older format): skip the random frames already done.
            init_random = max(0, self.recipe.collector.init_random_frames - int(state["counters"]["frames"]))
        return family(self.recipe).build(
            self.recipe,
            init_random_frames=init_random,
            scratch_dir=None if self.read_only else self.run_dir.path / "replay_storage",
        )

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
        self.pending_updates += batch.numel() * rc.algorithm.utd_ratio
        n_updates = int(self.pending_updates)
        self.pending_updates -= n_updates
        losses = []
        for _ in range(n_updates):
            if len(c.replay_buffer) < rc.algorithm.batch_size:
                break  # a rank event emptied the buffer ('reset'): resume once a batch of new data is in
            losses.append(self._update())
        return losses

    def _update(self) -> dict[str, torch.Tensor]:
        """One optimisation step of the family's update step (guarded), then (maybe) a rank event."""
        out = self.c.update(self.guard, update=self.updates)
        self.updates += 1
        self.hooks.post_optim(out)  # the callbacks' post_optim hook point (adarl.runtime.callbacks)
        if self.c.adapter is not None:
            self.c.adapter.step()
        return out

    def _postfix(self) -> dict:
        return {"ret": f"{self.last_return:.1f}", "ranks": _rank_summary(self.c.adapter), "upd": str(self.updates)}
