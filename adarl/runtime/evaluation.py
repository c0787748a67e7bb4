"""Deterministic evaluation of a policy: N episodes on fixed dynamics, with mean, std and a 95% interval.

The paper evaluates every method on the *nominal* dynamics (the centre of the uncertainty set); sweeps over
other fixed dynamics reuse the same function with another environment.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adarl.fast.evaluation import episode_runner

__all__ = ["EvalResult", "evaluate_policy", "describe_returns"]

# Two-sided 95% Student-t quantiles for small samples (df = n - 1); normal beyond the table.
_T95 = {
    1: 12.706,
    2: 4.303,
    3: 3.182,
    4: 2.776,
    5: 2.571,
    6: 2.447,
    7: 2.365,
    8: 2.306,
    9: 2.262,
    10: 2.228,
    15: 2.131,
    20: 2.086,
    30: 2.042,
}


def _t95(df: int) -> float:
    if df <= 0:
        return float("nan")
    for k in sorted(_T95):
        if df <= k:
            return _T95[k]
    return 1.96


def describe_returns(mean: float, std: float, ci95: float, episodes: int) -> str:
    """``"3012.4 ± 41.2 (95% CI ± 29.5) over 10 episodes"``; one episode has no spread to show (it printed
    ``95% CI ± nan`` and ``1 episodes``).

    >>> describe_returns(3012.4, 0.0, float("nan"), 1)
    '3012.4 over 1 episode (no spread from one episode)'
    """
    if episodes == 1 or not math.isfinite(ci95):
        return f"{mean:.1f} over {episodes} episode{'' if episodes == 1 else 's'} (no spread from one episode)"
    return f"{mean:.1f} ± {std:.1f} (95% CI ± {ci95:.1f}) over {episodes} episodes"


@dataclass
class EvalResult:
    """Returns and lengths of each episode, and their summary."""

    returns: list[float]
    lengths: list[int]
    mean: float = field(init=False)
    std: float = field(init=False)
    ci95: float = field(init=False)  # half-width of the 95% Student-t interval of the mean

    def __post_init__(self) -> None:
        n = len(self.returns)
        t = torch.tensor(self.returns, dtype=torch.float64)
        self.mean = float(t.mean()) if n else float("nan")
        self.std = float(t.std(unbiased=True)) if n > 1 else 0.0
        self.ci95 = _t95(n - 1) * self.std / math.sqrt(n) if n > 1 else float("nan")

    def as_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def evaluate_policy(
    policy: TensorDictModuleBase, env: EnvBase, episodes: int = 5, max_steps: int = 1000, deterministic: bool = True
) -> EvalResult:
    """Run ``episodes`` episodes of at most ``max_steps`` steps; the policy acts by its mode when deterministic.

    A deterministic SAC actor on a :func:`adarl.envs.make_env` env runs its episodes through
    :func:`adarl.fast.evaluation.episode_runner` (the same returns as ``env.rollout``, bit for bit, ~3x faster)."""
    returns, lengths = [], []
    fast = episode_runner(policy, env) if deterministic else None
    if fast is not None:
        for _ in range(episodes):
            total, length = fast(max_steps)
            returns.append(total)
            lengths.append(length)
        return EvalResult(returns=returns, lengths=lengths)
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with set_exploration_type(mode):
        for _ in range(episodes):
            rollout = env.rollout(max_steps, policy, break_when_any_done=True, auto_cast_to_device=True)
            reward = rollout["next", "reward"]
            returns.append(float(reward.sum()))
            lengths.append(int(rollout.shape[-1]))
    return EvalResult(returns=returns, lengths=lengths)
