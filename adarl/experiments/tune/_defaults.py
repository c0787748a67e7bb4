"""Default search spaces (``space: default``, or ``adarl tune RECIPE``): per algorithm, as rl-baselines3-zoo's
``hyperparams_opt.py`` samples SB3's hyperparameters, written as recipe keys; plus AdaRL's rank rule (beta, the rank
interval, the acceptance tolerances) when the recipe adapts ranks.

What was taken from rl-zoo and what was changed is in docs/evaluation-and-experiments.md ("Default search spaces").
The tables below are data: a space is built from them for one resolved recipe by :func:`default_space`, which also
drops the keys the spec's own ``overrides`` set (they stay as given) and derives the budget-relative ranges (the rank
interval) and the ones bounded by another key (a PPO minibatch <= the collector's batch) from that recipe.
"""

from __future__ import annotations

from typing import Any

from adarl.errors import RecipeError
from adarl.plugins import algorithm
from adarl.runtime.families import family

__all__ = ["ALGORITHM_SPACES", "RANK_KEYS", "default_space", "pinned_keys"]

_GAMMAS = [0.9, 0.95, 0.98, 0.99, 0.995, 0.999, 0.9999]  # rl-zoo's SAC/TD3/DDPG choices, as they are
_TAUS = [0.001, 0.005, 0.01, 0.02, 0.05, 0.08]  # rl-zoo's Polyak choices, as they are
_BATCHES = [32, 64, 100, 128, 256, 512]  # rl-zoo's without 16, 1024, 2048 (a CPU update at UTD 1)
_BUFFERS = [10_000, 100_000, 1_000_000]  # rl-zoo's buffer_size, as it is

_OFF_POLICY: dict[str, dict[str, Any]] = {
    "algorithm.gamma": {"type": "categorical", "choices": _GAMMAS},
    "algorithm.lr": {"type": "float", "low": 1.0e-5, "high": 1.0e-2, "log": True},  # rl-zoo: up to 1
    "algorithm.batch_size": {"type": "categorical", "choices": _BATCHES},
    "algorithm.tau": {"type": "categorical", "choices": _TAUS},
    "replay.size": {"type": "categorical", "choices": _BUFFERS},
}
_DETERMINISTIC = {  # TD3, DDPG: rl-zoo's noise_std (Gaussian only here: algorithm.td3.exploration_noise)
    **_OFF_POLICY,
    "algorithm.td3.exploration_noise": {"type": "float", "low": 0.05, "high": 0.5},
}

#: algorithm (or training loop) -> recipe key -> a :class:`~adarl.experiments.tune._spec.Param`'s fields
ALGORITHM_SPACES: dict[str, dict[str, dict[str, Any]]] = {
    "sac": dict(_OFF_POLICY),
    "td3": dict(_DETERMINISTIC),
    "ddpg": dict(_DETERMINISTIC),
    "ppo": {
        "algorithm.gamma": {"type": "categorical", "choices": [0.97, 0.98, 0.99, 0.995, 0.999, 0.9999]},
        "algorithm.ppo.gae_lambda": {"type": "categorical", "choices": [0.9, 0.95, 0.98, 0.99, 0.995, 0.999, 0.9999]},
        "algorithm.lr": {"type": "float", "low": 1.0e-5, "high": 2.0e-3, "log": True},
        "algorithm.ppo.entropy_coeff": {"type": "float", "low": 1.0e-8, "high": 0.1, "log": True},
        "algorithm.ppo.clip_epsilon": {"type": "categorical", "choices": [0.1, 0.2, 0.3, 0.4]},
        "algorithm.ppo.epochs": {"type": "categorical", "choices": [1, 5, 10, 20]},
        "algorithm.ppo.minibatch_size": {"type": "categorical", "choices": [32, 64, 128, 256, 512]},
        "algorithm.max_grad_norm": {"type": "float", "low": 0.3, "high": 2.0},
    },
}

#: the rank rule's keys a default space may hold (which ones it does depends on the recipe's rank section)
RANK_KEYS = ("rank.beta", "rank.interval", "rank.accept.actor_tol", "rank.accept.critic_tol")
_BETA_RULES = ("energy", "energy_inclusive", "ratio")  # the rules that read rank.beta


def pinned_keys(overrides: list[str]) -> set[str]:
    """The recipe keys a list of ``key=value`` overrides sets (and the sections it sets whole)."""
    return {o.split("=", 1)[0].strip() for o in overrides if "=" in o}


def _pinned(key: str, pinned: set[str]) -> bool:
    return any(key == p or key.startswith(p + ".") for p in pinned)


def _rank_space(recipe) -> dict[str, dict[str, Any]]:
    """The rank rule's knobs this recipe reads: beta (energy, energy_inclusive and ratio rules), the interval
    (relative to the budget: an eighth to a half of its optimisation steps, the paper's 1e6 of 3.5e6 inside), and
    the acceptance tolerance of each truncated network (projection acceptance; rule 'fixed' is always applied)."""
    r = recipe.rank
    out: dict[str, dict[str, Any]] = {}
    if r.truncate and r.rule in _BETA_RULES:
        out["rank.beta"] = {"type": "float", "low": 0.9, "high": 0.995}
    steps = max(2, int(recipe.collector.total_frames * recipe.algorithm.utd_ratio))
    low, high = max(1, steps // 8), max(1, steps // 2)
    out["rank.interval"] = {"type": "int", "low": low, "high": max(low, high), "log": True}
    if r.truncate and r.rule != "fixed" and r.accept.mode == "projection":
        if r.scope in ("actor", "both"):
            out["rank.accept.actor_tol"] = {"type": "float", "low": 0.01, "high": 0.2, "log": True}
        if r.scope in ("critic", "both"):
            out["rank.accept.critic_tol"] = {"type": "float", "low": 0.005, "high": 0.1, "log": True}
    return out


def _fit_to_algorithm(recipe, space: dict) -> tuple[dict, list[str]]:
    """The loop's space on another algorithm of that loop (``crossq`` on SAC's): a key one of the algorithm's options
    sets is searched as that option (``algorithm.lr`` -> ``algorithm.options.lr``), and a key the loop's checks refuse
    for it at the space's values (CrossQ's ``tau``: it has no target network) is left out and named."""
    sets = algorithm(recipe.algorithm.name).sets  # {algorithm key: option}
    fitted, refused = {}, []
    for key, param in space.items():
        section, _, name = key.partition(".")
        if section == "algorithm" and name in sets:
            fitted[f"algorithm.options.{sets[name]}"] = param
            continue
        values = param.get("choices") or [param.get("low"), param.get("high")]
        problems = []
        for value in values:
            try:
                problems += family(recipe.algorithm.base).problems(_with(recipe, key, value))
            except (ValueError, TypeError):
                continue
        if any(k == key for k, _, _ in problems):
            refused.append(key)
        else:
            fitted[key] = param
    return fitted, refused


def _with(recipe, key: str, value):
    """A copy of ``recipe`` with the dotted ``key`` set to ``value`` (no validation: the checks are what is asked)."""
    head, *rest = key.split(".")
    if not rest:
        return recipe.model_copy(update={head: value})
    return recipe.model_copy(update={head: _with(getattr(recipe, head), ".".join(rest), value)})


def default_space(recipe, overrides: list[str]) -> tuple[dict[str, dict[str, Any]], str]:
    """The default search space of a resolved ``recipe`` (its algorithm's, else its training loop's; the rank rule's
    when ``rank.enabled``), less the keys ``overrides`` set; and a line saying what it is made of.

    :class:`RecipeError` when neither the algorithm nor its loop has one, or every key is pinned by an override."""
    alg = recipe.algorithm
    if alg.name in ALGORITHM_SPACES:
        table, what = ALGORITHM_SPACES[alg.name], alg.name
    elif alg.base in ALGORITHM_SPACES:
        table, what = ALGORITHM_SPACES[alg.base], f"the {alg.base!r} loop's (algorithm {alg.name!r} has none)"
    else:
        raise RecipeError(
            f"no default search space for algorithm {alg.name!r} (loop {alg.base!r}); default spaces exist for "
            f"{', '.join(repr(n) for n in ALGORITHM_SPACES)}: give the spec a `space:` of recipe keys"
        )
    space = {k: dict(v) for k, v in table.items()}
    refused: list[str] = []
    if table is not ALGORITHM_SPACES.get(alg.name):  # the loop's table on another algorithm of that loop
        space, refused = _fit_to_algorithm(recipe, space)
    mb = space.get("algorithm.ppo.minibatch_size")
    if mb is not None:  # the minibatch must fit the collector's batch (rl-zoo's TODO: account for n_steps)
        mb["choices"] = [c for c in mb["choices"] if c <= recipe.collector.frames_per_batch] or [
            recipe.collector.frames_per_batch
        ]
    if recipe.rank.enabled:
        buffers = space.get("replay.size")
        if buffers is not None:  # a warm start refills from the buffer: it must hold that many frames
            frames = recipe.replay.warm_start.frames
            buffers["choices"] = [c for c in buffers["choices"] if c >= frames] or [frames]
        space.update(_rank_space(recipe))
        what += " + the rank rule's"
    pinned = pinned_keys(overrides)
    kept = {k: v for k, v in space.items() if not _pinned(k, pinned)}
    dropped = sorted(set(space) - set(kept))
    if not kept:
        raise RecipeError(
            f"the default search space ({what}) is empty: the overrides set every key of it ({', '.join(dropped)}); "
            "give the spec a `space:` of recipe keys"
        )
    line = f"the default space of {what} ({len(kept)} keys)"
    if refused:
        line += f"; refused by algorithm {alg.name!r}, so not searched: {', '.join(refused)}"
    if dropped:
        line += f"; set by the overrides, so not searched: {', '.join(dropped)}"
    return kept, line
