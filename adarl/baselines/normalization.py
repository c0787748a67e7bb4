"""Running statistics the PPO baselines' original trainer uses: observation normalisation and reward scaling.

:class:`RunningObsNorm` is a module placed at the input of the actor and of the critic (so evaluation, RNAC-DS's
candidate ranking and checkpoints carry the statistics with the networks); the trainer updates it from each
collected batch *after* the PPO epochs on that batch, so the log-probabilities stored at collection time stay
those of the networks being optimised. :class:`RewardScaler` divides rewards by the running standard deviation
of the discounted return (the "reward scaling" of PPO implementations).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RunningMeanStd", "RunningObsNorm", "RewardScaler"]


class RunningMeanStd(nn.Module):
    """Mean and variance of a stream of samples (Chan et al.'s parallel update), as float64 buffers."""

    def __init__(self, shape: tuple[int, ...] = ()) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(shape, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Fold in a batch ``[N, *shape]``."""
        x = x.detach().to(torch.float64).reshape(-1, *self.mean.shape)
        n = x.shape[0]
        if n == 0:
            return
        b_mean = x.mean(0)
        b_var = x.var(0, unbiased=False)
        total = self.count + n
        delta = b_mean - self.mean
        m2 = self.var * self.count + b_var * n + delta.pow(2) * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.fill_(float(total))

    @property
    def std(self) -> torch.Tensor:
        return self.var.sqrt()


class RunningObsNorm(RunningMeanStd):
    """``(x - mean) / (std + eps)`` with running statistics; identity until the first :meth:`update`."""

    def __init__(self, dim: int, eps: float = 1e-8) -> None:
        super().__init__((int(dim),))
        self.eps = float(eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if float(self.count) == 0:
            return x
        return (x - self.mean.to(x.dtype)) / (self.std.to(x.dtype) + self.eps)


class RewardScaler:
    """Divides each reward by the running std of the discounted return ``R_t = gamma R_{t-1} + r_t`` (reset at
    episode ends). Works on ``[n_envs, T]`` reward/done tensors, in time order.

    While the statistics have no spread yet (the run's very first reward of one env: a single sample) their std is 0;
    the divisor is then ``|R|``, so that reward scales to +-1: RNAC's trainer (``normalization.py``) sets its std to
    the first sample itself, where ``std + eps`` alone would multiply the first reward by 1e8."""

    def __init__(self, gamma: float, eps: float = 1e-8) -> None:
        self.gamma = float(gamma)
        self.eps = float(eps)
        self.stats = RunningMeanStd(())
        self.returns: torch.Tensor | None = None

    @torch.no_grad()
    def __call__(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        r = reward.reshape(reward.shape[0], reward.shape[1]).to(torch.float64)
        d = done.reshape(done.shape[0], done.shape[1])
        if self.returns is None or self.returns.shape[0] != r.shape[0]:
            self.returns = torch.zeros(r.shape[0], dtype=torch.float64)
        out = torch.empty_like(r)
        for t in range(r.shape[1]):
            self.returns = self.gamma * self.returns + r[:, t]
            self.stats.update(self.returns)
            std = self.stats.std
            std = torch.where(std > 0, std, self.returns.abs())  # no spread yet: +-1, not r / eps
            out[:, t] = r[:, t] / (std + self.eps)
            self.returns = torch.where(d[:, t], torch.zeros_like(self.returns), self.returns)
        return out.to(reward.dtype).reshape(reward.shape)

    def state_dict(self) -> dict:
        return {"stats": self.stats.state_dict(), "returns": self.returns}

    def load_state_dict(self, state: dict) -> None:
        self.stats.load_state_dict(state["stats"])
        self.returns = state["returns"]
