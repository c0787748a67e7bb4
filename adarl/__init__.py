"""adarl: TensorDict-native TorchRL components for robust RL by adaptive rank control (AdaRL).

The public components, importable from here:

- :class:`LowRankLinear` / :func:`low_rank_mlp`: ``W = W1 @ W2`` layers with a bias-free bottleneck.
- Rank rules (:mod:`adarl.rank`): :class:`EnergyRule` (paper Eq. 10), :class:`InclusiveEnergyRule`,
  :class:`RatioRule` (Eq. 33), :class:`FixedRank`, :class:`PolicyFitRule` (upper level of Eq. 8).
- :class:`RankAdapter`: Algorithm 1's rank-adaptation step on any TorchRL loss module (a ``TrainerHookBase``).
- :class:`ProjectionAcceptance` / :class:`RecentTransitions`: Algorithm 1's acceptance step (a lower rank only if
  the truncated network still fits recent data, else ``r_new = r_old``).
- :class:`WarmupCosine` / :func:`make_lr_scheduler`: the restartable warm-up + cosine LR schedule.
- :class:`ReplayWarmStart`: the warm-start replay buffer, an ``on_truncate`` callback.
- :class:`CollectorRebuild`: a collector rebuilt after each rank event (process collectors, policy copies).
- :class:`PerturbedDynamicsEnvTransform` / :func:`make_env`: per-episode MuJoCo dynamics, a TorchRL ``Transform``.
- :func:`load_recipe`, :func:`build_components`, :class:`Trainer`: recipes and the AdaRL-SAC loop.
"""

from adarl.errors import AdaRLError, AdaRLValueError, CheckpointError, RecipeError
from adarl.lowrank import LowRankLinear, factor_svd, iter_low_rank, low_rank_mlp, refactorize, truncation_error
from adarl.builders import reinit_low_rank_ensemble
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
from adarl.acceptance import ProjectionAcceptance, RecentTransitions, recent_transitions
from adarl.lr_schedule import WarmupCosine, make_lr_scheduler, restart_lr_scheduler
from adarl.adapter import LayerRecord, RankAdapter, RankEvent, find_low_rank_layers, resize_to_ranks
from adarl.warmstart import ReplayWarmStart, WarmStartRecord
from adarl.collector_rebuild import CollectorRebuild
from adarl.envs import (
    FixedSchedule,
    ListSchedule,
    PerturbedDynamicsEnvTransform,
    SinusoidSchedule,
    UniformSchedule,
    env_parameters,
    make_env,
    make_eval_env,
    make_schedule,
)

__version__ = "0.1.0"


def __getattr__(name):
    # The recipe layer pulls in pydantic/OmegaConf and the training loop; load them on first use only.
    if name in ("load_recipe", "list_recipes"):
        from adarl import config

        return getattr(config, name)
    if name in ("build_components", "Trainer", "Components"):
        from adarl import training

        return getattr(training, name)
    raise AttributeError(f"module 'adarl' has no attribute {name!r}")


__all__ = [
    "AdaRLError", "AdaRLValueError", "CheckpointError", "RecipeError",
    "LowRankLinear", "low_rank_mlp", "factor_svd", "refactorize", "truncation_error", "iter_low_rank",
    "reinit_low_rank_ensemble",
    "RankRule", "RankDecision", "EnergyRule", "InclusiveEnergyRule", "RatioRule", "FixedRank", "PolicyFitRule",
    "make_rule",
    "WarmupCosine", "make_lr_scheduler", "restart_lr_scheduler",
    "ProjectionAcceptance", "RecentTransitions", "recent_transitions",
    "RankAdapter", "RankEvent", "LayerRecord", "find_low_rank_layers", "resize_to_ranks",
    "ReplayWarmStart", "WarmStartRecord", "CollectorRebuild",
    "PerturbedDynamicsEnvTransform", "make_env", "make_eval_env", "make_schedule", "env_parameters",
    "SinusoidSchedule", "UniformSchedule", "FixedSchedule", "ListSchedule",
    "load_recipe", "list_recipes", "build_components", "Trainer", "Components",
]
