"""A ``SACLoss`` whose only change is a shift of its TD target: the documented hook of a robust SAC.

RNAC-IPM's robust TD error is ``r + gamma V(s') - V(s) - kappa ||theta_critic||`` (Zhou et al., 2023): the TD
target minus a number that depends on the parameters, not on the batch. :class:`TargetShiftSACLoss` is TorchRL's
``SACLoss`` with one extra method to override, :meth:`~TargetShiftSACLoss.target_shift`; the shift is subtracted
from the target of the critic loss (``_compute_target_v2``, where TorchRL computes
``r + gamma (1 - d) (min_i Q'_i(s', a') - alpha log pi(a'|s'))``) and reported in the output as ``target_shift``.

Because the shift enters only the target, it equals training on the reward ``r - shift``: adarl's fused SAC
update (:mod:`adarl.fast.sac`) applies it that way and keeps its speed, for a subclass that overrides
``target_shift`` (and ``__init__``) only. Override anything else and the run falls back to TorchRL's path, saying
so in one line (:func:`adarl.fast.sac.fused_fallback_reason`).

>>> import torch
>>> from tensordict import TensorDict
>>> from tensordict.nn import NormalParamExtractor, TensorDictModule
>>> from torch import nn
>>> from torchrl.data import Bounded
>>> from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
>>> from torchrl.objectives import ValueEstimators
>>> class ConstantShift(TargetShiftSACLoss):
...     def target_shift(self):
...         return torch.tensor(0.5)
>>> actor = ProbabilisticActor(TensorDictModule(nn.Sequential(nn.Linear(3, 4), NormalParamExtractor()),
...     ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"], distribution_class=TanhNormal)
>>> loss = ConstantShift(actor, ValueOperator(MLP(5, 1, num_cells=[8]), in_keys=["observation", "action"]),
...                      action_spec=Bounded(-1.0, 1.0, (2,)))
>>> loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
>>> batch = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1,
...     "next": {"observation": torch.randn(8, 3), "reward": torch.randn(8, 1),
...              "done": torch.zeros(8, 1, dtype=torch.bool), "terminated": torch.zeros(8, 1, dtype=torch.bool)}},
...     [8])
>>> float(loss(batch)["target_shift"])
0.5
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import SACLoss

__all__ = ["TargetShiftSACLoss"]


class TargetShiftSACLoss(SACLoss):
    """TorchRL's ``SACLoss`` with its TD target lowered by :meth:`target_shift` (see the module docstring)."""

    def target_shift(self) -> torch.Tensor:
        """A scalar subtracted from every TD target (detached; recomputed at each call). Zero here."""
        return torch.zeros((), device=self.log_alpha.device)

    def _compute_target_v2(self, tensordict) -> torch.Tensor:
        return super()._compute_target_v2(tensordict) - self.target_shift().detach()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = super().forward(tensordict)
        out.set("target_shift", self.target_shift().detach().reshape(()))
        return out
