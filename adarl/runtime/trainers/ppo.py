"""The PPO loop of the RNAC baselines (Zhou et al., 2023): :class:`PPOTrainer` runs a recipe with
a PPO-based ``algorithm.name`` (``ppo``, ``rnac_ipm``, ``rnac_ds`` or a plugin's, :mod:`adarl.plugins`) on the same
perturbed envs, with the same run folder, logging, evaluation, checkpoints,
divergence guards, Ctrl-C checkpoint and exact resume as AdaRL-SAC (all of :class:`BaseTrainer`).

Each collected batch: reward scaling, advantages (GAE, or RNAC-IPM's shifted GAE), the advantage standardised over
the whole batch (RNAC's trainer), ``epochs`` passes of minibatch ``ClipPPOLoss`` updates (each guarded: losses,
gradients, parameters), then the observation statistics absorb the batch and the learning rate decays.
The algorithm's hooks make it RNAC-IPM (its ``advantage``: :class:`~adarl.baselines.rnac.IPMAdvantage`) or RNAC-DS
(its ``env_transform``: :class:`~adarl.baselines.rnac.DoubleSamplingTransform`). The networks:
:mod:`adarl.runtime.builders.ppo`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from adarl.baselines.rnac import IPMAdvantage
from adarl.runtime.builders.ppo import simulator_steps_per_frame
from adarl.runtime.trainers.base import BaseTrainer
from adarl.runtime.update import loss_output, require_losses, scalar_entries

__all__ = ["PPOTrainer", "normalize_advantage_"]

#: the PPO losses a minibatch update checks and returns (``loss_entropy`` when the entropy bonus is on)
PPO_LOSSES = ("loss_objective", "loss_critic", "loss_entropy")


@torch.no_grad()
def normalize_advantage_(batch: TensorDictBase, key: str = "advantage", eps: float = 1e-5) -> TensorDictBase:
    """Standardise ``batch[key]`` in place over the whole batch, ``(A - mean) / (std + eps)`` with the unbiased
    std, as RNAC's trainer does once per 2048-frame batch before its epochs (TorchRL's ``ClipPPOLoss`` would do it
    per minibatch). The value target, computed from the raw advantage, is left alone. A one-frame batch has no
    spread: its advantage becomes 0.

    >>> from tensordict import TensorDict
    >>> normalize_advantage_(TensorDict({"advantage": torch.tensor([1.0, 3.0])}, [2]))["advantage"]
    tensor([-0.7071,  0.7071])
    """
    adv = batch.get(key)
    std = adv.std() if adv.numel() > 1 else torch.zeros((), dtype=adv.dtype, device=adv.device)
    batch.set(key, (adv - adv.mean()) / (std + eps))
    return batch


class PPOTrainer(BaseTrainer):
    """Runs a PPO/RNAC recipe in a run folder; same outputs as
    :class:`~adarl.runtime.trainers.off_policy.OffPolicyTrainer` (and ``simulator_steps_per_frame``/``simulator_steps``
    in the summary). Its components
    (:class:`~adarl.runtime.builders.ppo.PPOComponents`) save and load their own state."""

    #: PPO iterations done (one per collected batch)
    counters = {"iterations": (int, 0)}

    # ------------------------------------------------------------------ one batch
    def _consume(self, batch: TensorDictBase) -> list[dict[str, torch.Tensor]]:
        if batch.ndim == 1:
            batch = batch.unsqueeze(0)  # [n_envs, T]: GAE runs along the last dimension
        flat = batch.reshape(-1)
        self.frames += flat.numel()
        self._log_episodes(flat)
        return self._iteration(batch)

    def _iteration(self, batch) -> list[dict[str, torch.Tensor]]:
        """Reward scaling, advantages, then ``epochs`` passes of minibatch PPO updates; then the observation
        statistics absorb the batch and the LR decays."""
        c, ppo = self.c, self.recipe.algorithm.ppo
        m = c.modules
        if c.reward_scaler is not None:
            batch.set(("next", "reward"), c.reward_scaler(batch.get(("next", "reward")), batch.get(("next", "done"))))
        with torch.no_grad():
            m.advantage(batch)
        if ppo.normalize_advantage == "batch":
            normalize_advantage_(batch)
        flat = batch.reshape(-1)
        n, mb = flat.numel(), ppo.minibatch_size
        losses = []
        for _ in range(ppo.epochs):
            perm = torch.randperm(n, generator=c.sampling_generator)
            for i in range(0, n, mb):
                losses.append(self._update(flat[perm[i : i + mb]]))
        for norm in m.obs_norms:
            norm.update(flat.get("observation"))
        for s in c.schedulers.values():
            s.step()
        self.iterations += 1
        extra = {}
        if isinstance(m.advantage, IPMAdvantage):
            extra["ipm_reward_shift"] = torch.tensor(m.advantage.last_shift)
        if c.double_sampling is not None:
            ds = c.double_sampling
            extra["ds_worst_fraction"] = torch.tensor(ds.worst_picks / max(1, ds.steps))
        if extra:
            losses[-1] = {**losses[-1], **extra}
            for d in losses[:-1]:
                d.update(extra)
        return losses

    def _update(self, minibatch) -> dict[str, torch.Tensor]:
        """One guarded minibatch update: the loss (plus its terms), backward, clipping, the optimisers."""
        c = self.c
        td, losses = loss_output(c.modules.loss, minibatch, c.terms)
        require_losses(losses, PPO_LOSSES[:2], c.modules.loss, "PPO")
        self.guard.check_losses(losses, self.updates)
        sum(losses.values()).backward()
        self.guard.check_grads(self.updates)
        self._clip_and_step()
        self.guard.check_params(self.updates)
        self.updates += 1
        out = {k: v.detach() for k, v in losses.items()}
        if c.plugin_metrics:  # a registered algorithm's loss: its own scalar entries are logged as train/<key>
            out.update((k, v) for k, v in scalar_entries(td).items() if k not in out)
        self.hooks.post_optim(out)  # the callbacks' post_optim hook point (adarl.runtime.callbacks)
        return out

    # ------------------------------------------------------------------ summary
    def _summary(self, elapsed: float) -> dict:
        """The common summary plus the simulator's cost: RNAC-DS takes ``m + 1`` env steps per frame, so a comparison
        at equal frames gives it ``m + 1`` times the simulator steps of the other methods."""
        summary = super()._summary(elapsed)
        per_frame = simulator_steps_per_frame(self.recipe)
        summary["simulator_steps_per_frame"] = per_frame
        summary["simulator_steps"] = self.frames * per_frame
        return summary
