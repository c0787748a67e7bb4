"""Each Table 1 env's stand-still and random-action returns on the nominal dynamics (issue 45's per-env plateau).

A policy that learned nothing useful either stands still (zero torques: the healthy reward for as long as the body
stays up) or flails. Their nominal-dynamics returns, over the same 10 episodes an evaluation uses, set each env's
plateau threshold ("a seed leaves the plateau when its best evaluation exceeds it") and the random score of the
normalised aggregate. Hopper's 1500 (issue 34) sits above its measured stand-still return for the same reason.

    python docs/reports/issue45/standstill.py [--episodes 10]
"""

from __future__ import annotations

import argparse

import torch

from adarl.runtime.builders.common import make_envs
from adarl.runtime.config import load_recipe

ENVS = ("hopper", "walker2d", "ant", "humanoid")


def returns(env, action, episodes: int) -> list[float]:
    out = []
    for _ in range(episodes):
        td = env.rollout(1000, policy=lambda td: td.set("action", action(td)), break_when_any_done=True)
        out.append(float(td["next", "reward"].sum()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=10)
    args = ap.parse_args()
    print("env        stand-still (zero action): mean [min, max]      random actions: mean [min, max]")
    for name in ENVS:
        recipe = load_recipe(f"{name}_adarl", ["seed=0"])
        _, eval_env = make_envs(recipe)  # the nominal dynamics, as every evaluation
        torch.manual_seed(0)
        spec = eval_env.action_spec
        zero = returns(eval_env, lambda td, spec=spec: torch.zeros(spec.shape), args.episodes)
        rand = returns(eval_env, lambda td, spec=spec: spec.rand(), args.episodes)
        fmt = lambda r: f"{sum(r) / len(r):8.1f} [{min(r):.1f}, {max(r):.1f}]"  # noqa: E731
        print(f"{name:<10} {fmt(zero):<42} {fmt(rand)}", flush=True)
        eval_env.close()


if __name__ == "__main__":
    main()
