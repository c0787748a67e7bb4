"""The Gaussian policy of RNAC's original PPO trainer (tliu1997/RNAC, ``ppo_continuous.py``), in TorchRL's terms.

The original's continuous actor computes the mean as ``max_action * tanh(head(s))``, keeps a state-independent
``log_std`` (a parameter initialised to 0), samples ``Normal(mean, exp(log_std))``, clips the sample to the action
box, and stores the log-probability of the *clipped* action under the *unclipped* Gaussian; PPO's ratio uses the
same density and its entropy bonus is the Gaussian's analytic entropy. Evaluation acts with the mean.

* :class:`BoxTanh` maps the head's output into the box (``center + half_width * tanh(x)``, which is
  ``max_action * tanh(x)`` for the symmetric boxes of MuJoCo);
* :class:`ClippedNormal` is the distribution: a diagonal Gaussian (``torch.distributions.Independent`` of
  ``Normal``) whose ``sample``/``rsample`` clip to ``[low, high]`` while ``log_prob`` and ``entropy`` stay the
  Gaussian's. Give it to :class:`torchrl.modules.ProbabilisticActor` as ``distribution_class`` with
  ``distribution_kwargs={"low": ..., "high": ...}``, as for TorchRL's ``TanhNormal``.

Why not TorchRL's ``TanhNormal``: its samples are squashed, not clipped (a different action distribution near the
bounds), and it has no closed-form entropy, so ``ClipPPOLoss`` estimates the entropy bonus from one sample.
"""

from __future__ import annotations

import torch
from torch import distributions as D
from torch import nn

__all__ = ["BoxTanh", "ClippedNormal"]


def _as_tensor(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


class BoxTanh(nn.Module):
    """``center + half_width * tanh(x)`` for the box ``[low, high]``: the original's
    ``max_action * tanh(mean_layer(s))``."""

    def __init__(self, low, high) -> None:
        super().__init__()
        low, high = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
        # not persistent: the box comes from the env's spec, the state dict holds only what training changes
        self.register_buffer("center", (high + low) / 2, persistent=False)
        self.register_buffer("half_width", (high - low) / 2, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.center.to(x.dtype) + self.half_width.to(x.dtype) * torch.tanh(x)


class ClippedNormal(D.Independent):
    """A diagonal Gaussian whose samples are clipped to ``[low, high]``; ``log_prob``, ``entropy`` and ``mean`` are
    those of the unclipped Gaussian (as in RNAC's trainer), the deterministic action is the clipped mean.

    Args:
        loc, scale: the Gaussian's mean and standard deviation (``[..., d]``).
        low, high: the action box (tensors or numbers broadcastable to ``loc``).
        event_dim: trailing dimensions summed by ``log_prob``/``entropy`` (1: the action dimension).
    """

    num_params: int = 2

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, low=-1.0, high=1.0, event_dim: int = 1) -> None:
        self.low, self.high = _as_tensor(low, loc), _as_tensor(high, loc)
        if not bool((self.low <= self.high).all()):
            raise ValueError(f"ClippedNormal needs low <= high, got low={low!r}, high={high!r}")
        super().__init__(D.Normal(loc, scale), event_dim)

    def _clip(self, x: torch.Tensor) -> torch.Tensor:
        return torch.clamp(x, self.low, self.high)

    def sample(self, sample_shape=torch.Size()) -> torch.Tensor:
        return self._clip(super().sample(sample_shape))

    def rsample(self, sample_shape=torch.Size()) -> torch.Tensor:
        return self._clip(super().rsample(sample_shape))

    @property
    def mode(self) -> torch.Tensor:
        return self._clip(self.base_dist.mean)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mode
