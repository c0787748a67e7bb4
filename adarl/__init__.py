"""adarl: TensorDict-native TorchRL components for robust RL by adaptive rank control."""

from adarl.errors import AdaRLError, AdaRLValueError, CheckpointError, RecipeError
from adarl.lowrank import LowRankLinear, factor_svd, iter_low_rank, low_rank_mlp, refactorize
from adarl.rank import (
    EnergyRule,
    FixedRank,
    InclusiveEnergyRule,
    PolicyFitRule,
    RankDecision,
    RankRule,
    RatioRule,
    make_rule,
)

__version__ = "0.1.0"
