"""The baselines of the AdaRL paper's Table 1 as composable TorchRL pieces (docs/baselines.md).

* :mod:`adarl.baselines.parseval` - Parseval regularisation as a term added to any TorchRL loss;
* :mod:`adarl.baselines.sparse` - the sparsification layer of Tiwari et al. (2025), as we interpret it;
* :mod:`adarl.baselines.rnac` - RNAC-IPM (a GAE with a shifted reward) and RNAC-DS (a collection-time transform);
* :mod:`adarl.baselines.normalization` - the PPO trainer's running observation normalisation and reward scaling;
* :mod:`adarl.baselines.policy` - the PPO trainer's Gaussian policy with actions clipped to the box;
* :mod:`adarl.baselines.init` - orthogonal initialisation as RNAC's and Parseval's original code does it, and the
  factors drawn apart as Fig. 5's bias-free bottleneck (``independent_factors``);
* :mod:`adarl.baselines.mlp` - one MLP builder for the network variants;
* :mod:`adarl.baselines.registry` - how they plug into the recipe builders (network variants, init schemes, loss
  terms), each module registering itself on import.

Fixed- and full-rank SAC need no new code (``rank.enabled: false``); the PPO loop of the RNAC baselines is
:mod:`adarl.runtime.trainers.ppo`, its networks :mod:`adarl.runtime.builders.ppo`.
"""

from adarl.baselines import registry
from adarl.baselines.init import (
    independent_factors_init_,
    independent_factors_init_loss_,
    orthogonal_init_,
    orthogonal_init_loss_,
)
from adarl.baselines.mlp import BaselineMLP, make_baseline_mlp
from adarl.baselines.normalization import RewardScaler, RunningMeanStd, RunningObsNorm
from adarl.baselines.parseval import DiagonalScale, InputScale, ParsevalRegularizer, parseval_penalty, parseval_weights
from adarl.baselines.policy import BoxTanh, ClippedNormal
from adarl.baselines.rnac import DoubleSamplingTransform, IPMAdvantage, critic_parameter_norm
from adarl.baselines.sparse import KWinnersTakeAll, SparsificationLayer, intrinsic_rank

__all__ = [
    "registry",
    "BaselineMLP",
    "make_baseline_mlp",
    "RewardScaler",
    "RunningMeanStd",
    "RunningObsNorm",
    "DiagonalScale",
    "InputScale",
    "ParsevalRegularizer",
    "parseval_penalty",
    "parseval_weights",
    "DoubleSamplingTransform",
    "IPMAdvantage",
    "critic_parameter_norm",
    "KWinnersTakeAll",
    "SparsificationLayer",
    "intrinsic_rank",
    "BoxTanh",
    "ClippedNormal",
    "orthogonal_init_",
    "orthogonal_init_loss_",
    "independent_factors_init_",
    "independent_factors_init_loss_",
]
