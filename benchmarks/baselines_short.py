"""Short benchmark of every algorithm of docs/baselines.md on one env, against a random policy.

Each algorithm runs its shipped Hopper recipe with the env switched (default InvertedPendulum-v5 with its paper
perturbation schedule) and a small budget, through the same Trainer/PPOTrainer as `adarl run`; every run is
evaluated the same way (deterministic policy, nominal dynamics, `--episodes` episodes). The random policy is
evaluated on the same evaluation env. Writes a Markdown table and a JSON file.

    OMP_NUM_THREADS=1 python benchmarks/baselines_short.py --out runs/bench   # ~20-40 min on 2 loaded cores
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

SAC_BUDGET = [
    "collector.total_frames={sac_frames}",
    "collector.init_random_frames=1000",
    "collector.frames_per_batch=250",
    "algorithm.utd_ratio=0.5",
    "replay.size=20000",
    "eval.interval={sac_frames}",
    "checkpoint.interval={sac_frames}",
    "lr_schedule.warmup_steps=200",
    "replay.warm_start.frames=500",
    "rank.interval=1000",
]
PPO_BUDGET = ["collector.total_frames={ppo_frames}", "eval.interval={ppo_frames}", "checkpoint.interval={ppo_frames}"]

ALGORITHMS = {  # name: (recipe, extra overrides)
    "AdaRL-SAC": ("quickstart", []),
    "SAC full rank": ("baselines/hopper_sac_full", []),
    "SAC fixed rank 3": ("baselines/hopper_sac_fixed", ["network.actor.rank=3", "network.critic.rank=3"]),
    "SAC + Parseval (1e-4)": ("baselines/hopper_parseval", []),
    "SAC + sparsification (1024, k=3)": ("baselines/hopper_sparse", []),
    "RNAC-IPM (PPO)": ("baselines/hopper_rnac_ipm", []),
    "RNAC-DS (PPO)": ("baselines/hopper_rnac_ds", []),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--env", default="InvertedPendulum-v5")
    ap.add_argument("--sac-frames", type=int, default=5000)
    ap.add_argument("--ppo-frames", type=int, default=30720)
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", help="run only these algorithm names")
    ap.add_argument("--out", default="runs/bench")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from adarl.runtime.config import load_recipe
    from adarl.runtime.evaluation import evaluate_policy
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import trainer_class

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    common = [f"env.id={args.env}", f"seed={args.seed}", f"eval.episodes={args.episodes}", "eval.max_steps=1000"]
    results = {}
    results_path = out / "results.json"
    if results_path.exists():
        results = json.loads(results_path.read_text())
    for name, (recipe_name, extra) in ALGORITHMS.items():
        if args.only and name not in args.only:
            continue
        is_ppo = "rnac" in recipe_name
        budget = [
            b.format(sac_frames=args.sac_frames, ppo_frames=args.ppo_frames)
            for b in (PPO_BUDGET if is_ppo else SAC_BUDGET)
        ]
        recipe = load_recipe(recipe_name, [*common, *budget, *extra])
        run_dir = RunDir.create(out / recipe.name, overwrite=True)
        t0 = time.perf_counter()
        summary = trainer_class(recipe)(recipe, run_dir, quiet=True).train()
        ev = summary["final_eval"]
        results[name] = {
            "recipe": recipe_name,
            "frames": summary["frames"],
            "updates": summary["updates"],
            "mean": ev["mean"],
            "std": ev["std"],
            "wall_s": time.perf_counter() - t0,
        }
        print(name, results[name], flush=True)
        results_path.write_text(json.dumps(results, indent=2))

    if not args.only or "random" in args.only:
        from torchrl.envs.utils import RandomPolicy

        recipe = load_recipe("quickstart", common)
        from adarl.runtime.builders.common import make_envs

        _, env = make_envs(recipe)  # the evaluation env: nominal dynamics, seed + 10000
        ev = evaluate_policy(
            RandomPolicy(env.action_spec), env, episodes=args.episodes, max_steps=1000, deterministic=False
        )
        results["random policy"] = {
            "recipe": "-",
            "frames": 0,
            "updates": 0,
            "mean": ev.mean,
            "std": ev.std,
            "wall_s": 0.0,
        }
        results_path.write_text(json.dumps(results, indent=2))

    print(f"\n| algorithm | frames | updates | nominal return (mean ± std, {args.episodes} episodes) | wall time |")
    print("|---|---|---|---|---|")
    for name, r in results.items():
        print(
            f"| {name} | {r['frames']} | {r['updates']} | {r['mean']:.1f} ± {r['std']:.1f} "
            f"| {r['wall_s'] / 60:.1f} min |"
        )


if __name__ == "__main__":
    main()
