"""How far one Adam step on the balanced factors moves W = W1 W2, against one Adam step on a dense W (issue 45 (c)).

Adam's first step (and the first after a rank event, whose optimiser state is reset) is lr * g / (|g| + eps), a
sign step. On a dense layer it moves W by lr * sign(G_W); on the factors by (W1 - lr sign(G_W1)) (W2 - lr
sign(G_W2)) - W1 W2, with G_W1 = G_W W2^T and G_W2 = W1^T G_W. This prints the ratio of the two moves' Frobenius
norms per factorised layer (each critic of the ensemble on its own), on the SAC losses' real gradients at
initialisation: Hopper-v5 (recipes/hopper_adarl.yaml, the pilot's overrides), a batch of 256 from 5000 frames of
random actions, per seed. At initialisation every layer is full rank, so one factor is square and G_W follows from
it exactly. ``algorithm.factor_lr_scale`` = 1 / (the geometric mean ratio) makes one factor step move W as far as a
dense step does, on average over these layers.

    python docs/reports/issue45/factor_step.py [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import math

import torch

from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe

PILOT = [
    "collector.total_frames=300000",
    "replay.size=300000",
    "rank.interval=60000",
    "replay.warm_start.frames=5000",
    "replay.warm_start.count_frames=false",
    "algorithm.fused=false",  # the autograd path: the factors' gradients straight from SACLoss
]


def dense_grad(w1, w2, g1, g2):
    """G_W from the factors' gradients, where one factor is square (full rank): G_W1 = G_W W2^T, G_W2 = W1^T G_W."""
    if w1.shape[-1] == w1.shape[-2]:
        return torch.linalg.solve(w1.mT, g2)
    return torch.linalg.solve(w2, g1.mT).mT


def ratio(w1, w2, g1, g2, lr):
    gw = dense_grad(w1.double(), w2.double(), g1.double(), g2.double())
    w1, w2 = w1.double(), w2.double()
    moved = (w1 - lr * g1.double().sign()) @ (w2 - lr * g2.double().sign()) - w1 @ w2
    dense = lr * gw.sign()
    cos = (moved * -dense).sum((-2, -1)) / (moved.norm(dim=(-2, -1)) * dense.norm(dim=(-2, -1)))
    return moved.norm(dim=(-2, -1)) / dense.norm(dim=(-2, -1)), cos


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    logs = []
    for seed in args.seeds:
        c = build_sac_components(load_recipe("hopper_adarl", PILOT + [f"seed={seed}"]))
        torch.manual_seed(seed)
        c.replay_buffer.extend(c.env.rollout(5000, break_when_any_done=False).reshape(-1))
        loss, lr = c.modules.loss, c.recipe.algorithm.lr
        out = loss(c.replay_buffer.sample())
        (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
        for net, params in (("actor", loss.actor_network_params), ("critic", loss.qvalue_network_params)):
            flat = dict(params.flatten_keys(".").items())
            for key in sorted(k for k in flat if k.endswith("w1")):
                w1, w2 = flat[key], flat[key[:-2] + "w2"]
                r, cos = ratio(w1.detach(), w2.detach(), w1.grad, w2.grad, lr)
                for member, (x, cs) in enumerate(zip(r.reshape(-1).tolist(), cos.reshape(-1).tolist())):
                    name = f"{net} {key[:-3]} ({w1.shape[-2]}x{w2.shape[-1]})" + (f" #{member}" if r.dim() else "")
                    print(f"seed {seed}  {name:<40} ratio {x:.3f}  cos(factor step, dense step) {cs:.3f}")
                    logs.append(math.log(x))
    gm = math.exp(sum(logs) / len(logs))
    print(
        f"geometric mean ratio over {len(logs)} layer-members: {gm:.3f}; min {math.exp(min(logs)):.3f}, "
        f"max {math.exp(max(logs)):.3f}; factor_lr_scale = 1 / {gm:.3f} = {1 / gm:.3f}"
    )


if __name__ == "__main__":
    main()
