"""adarl: TensorDict-native TorchRL components for robust RL by adaptive rank control (AdaRL).

The public components, importable from here:

- :class:`LowRankLinear` / :func:`low_rank_mlp`: ``W = W1 @ W2`` layers with a bias-free bottleneck.
- Rank rules (:mod:`adarl.core.rank`): :class:`EnergyRule` (paper Eq. 10), :class:`InclusiveEnergyRule`,
  :class:`RatioRule` (Eq. 33), :class:`FixedRank`, :class:`PolicyFitRule` (upper level of Eq. 8).
- :class:`RankAdapter`: Algorithm 1's rank-adaptation step on any TorchRL loss module (a ``TrainerHookBase``).
- :class:`ProjectionAcceptance` / :class:`RecentTransitions`: Algorithm 1's acceptance step (a lower rank only if
  the truncated network still fits recent data, else ``r_new = r_old``).
- :class:`WarmupCosine` / :func:`make_lr_scheduler`: the restartable warm-up + cosine LR schedule.
- :class:`ReplayWarmStart`: the warm-start replay buffer, an ``on_truncate`` callback.
- :class:`CollectorRebuild`: a collector rebuilt after each rank event (process collectors, policy copies).
- :class:`PerturbedDynamicsEnvTransform` / :func:`make_env`: per-episode MuJoCo dynamics, a TorchRL ``Transform``.
- :func:`register_env` / :func:`register_parameter`: env ids and perturbation parameters from your own package.
- :func:`load_recipe`, :func:`build_sac_components` / :class:`SACComponents`, :class:`OffPolicyTrainer`: recipes,
  AdaRL-SAC's components, and the loop every off-policy family (SAC, TD3, DDPG) runs on.
- :func:`load_policy`: a trained run's policy as a TorchRL actor, without its env, buffer or collector.
- :func:`export_policy` / :class:`ExportedPolicy`: a run's policy as one file torch alone loads (``adarl export``),
  and SB3's ``predict(obs)`` on numpy for it.

Every name is imported on first use (PEP 562): ``import adarl`` itself loads neither torch nor TorchRL (~4.5 s
here), so ``adarl --help`` and ``from adarl import load_recipe`` stay quick. The public namespace
(``dir(adarl)``) is ``__all__`` and the subpackages already imported, nothing else (no ``annotations`` or
``importlib`` of this module's own making).
"""

import importlib as _importlib
from types import ModuleType as _ModuleType

__version__ = "0.1.0"

# public name -> the module that defines it (imported when the name is first read)
_EXPORTS: dict[str, str] = {
    **dict.fromkeys(["AdaRLError", "AdaRLValueError", "CheckpointError", "RecipeError"], "adarl.errors"),
    **dict.fromkeys(
        ["LowRankLinear", "low_rank_mlp", "factor_svd", "refactorize", "truncation_error", "iter_low_rank"],
        "adarl.core.lowrank",
    ),
    "reinit_low_rank_ensemble": "adarl.core.ensemble",
    **dict.fromkeys(
        [
            "RankRule",
            "RankDecision",
            "EnergyRule",
            "InclusiveEnergyRule",
            "RatioRule",
            "FixedRank",
            "PolicyFitRule",
            "make_rule",
        ],
        "adarl.core.rank",
    ),
    **dict.fromkeys(["WarmupCosine", "make_lr_scheduler", "restart_lr_scheduler"], "adarl.core.lr_schedule"),
    **dict.fromkeys(["ProjectionAcceptance", "RecentTransitions", "recent_transitions"], "adarl.core.acceptance"),
    **dict.fromkeys(
        ["RankAdapter", "RankEvent", "LayerRecord", "find_low_rank_layers", "resize_to_ranks"], "adarl.core.adapter"
    ),
    **dict.fromkeys(["ReplayWarmStart", "WarmStartRecord"], "adarl.core.warmstart"),
    "CollectorRebuild": "adarl.core.collector_rebuild",
    "TargetShiftSACLoss": "adarl.core.target_shift",
    **dict.fromkeys(
        ["register_algorithm", "algorithm_names", "register_rank_rule", "rank_rule_names"], "adarl.plugins"
    ),
    **dict.fromkeys(["register_callback", "callback_names"], "adarl.plugins"),
    "Callback": "adarl.runtime.callbacks",
    **dict.fromkeys(["register_env", "register_parameter"], "adarl.envs.registration"),
    "ParameterInfo": "adarl.envs.registry",
    **dict.fromkeys(
        [
            "PerturbedDynamicsEnvTransform",
            "make_env",
            "make_eval_env",
            "make_schedule",
            "env_parameters",
            "SinusoidSchedule",
            "UniformSchedule",
            "FixedSchedule",
            "ListSchedule",
        ],
        "adarl.envs",
    ),
    **dict.fromkeys(["load_recipe", "list_recipes"], "adarl.runtime.config"),
    **dict.fromkeys(["build_sac_components", "SACComponents"], "adarl.runtime.builders.sac"),
    "OffPolicyTrainer": "adarl.runtime.trainers.off_policy",
    "load_policy": "adarl.runtime.policy",
    "export_policy": "adarl.runtime.export",
    **dict.fromkeys(["ExportedPolicy", "read_export_metadata"], "adarl.runtime.exported"),
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'adarl' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module), name)
    globals()[name] = value  # later reads skip this function
    return value


def __dir__() -> list[str]:
    """``__all__``, the subpackages imported so far (``adarl.core``, ...) and the module's dunders."""
    here = globals()
    submodules = {n for n, v in here.items() if isinstance(v, _ModuleType) and v.__name__ == f"{__name__}.{n}"}
    return sorted({*(n for n in here if n.startswith("__")), *__all__, *submodules})
