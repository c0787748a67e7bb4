"""How much may a truncation change a network before it costs return? Measured, to choose rank.accept's tolerances.

    PYTHONPATH=. python benchmarks/acceptance_calibration.py RUN_DIR [RUN_DIR ...] --out DIR [--episodes 5]

Each RUN_DIR is a finished run whose low-rank layers are still at full rank (``rank.enabled=false``, e.g. the
``off`` arm of recipes/experiments/rank_settling.yaml). From its last checkpoint, for every low-rank layer and a
grid of ranks, with that one layer projected to the rank (the SVD projection a rank event applies):

* actor layers: the relative output error the acceptance step measures
(:func:`adarl.core.acceptance.relative_output_error`
  of the distribution parameters on the 2048 most recent transitions) and the return of the truncated
  deterministic policy on the nominal dynamics (``--episodes`` episodes, the same start states for every rank);
* critic layers: the relative output error (worst of the two critics) and the critic loss (clipped double-Q TD
  error, the run's SAC loss on the same transitions, one fixed seed) relative to the untruncated critic's.

Writes ``calibration.csv`` and ``calibration.png`` (return ratio and TD-loss ratio against the error) in ``--out``.
The run folders are copied to a temporary folder first: nothing in them is modified.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import tempfile
from pathlib import Path

import torch

from adarl.core.acceptance import recent_transitions
from adarl.core.adapter import _NetworkProbe, _padded_factors, find_low_rank_layers
from adarl.core.lowrank import factor_svd
from adarl.runtime.evaluation import evaluate_policy
from adarl.runtime.trainers import OffPolicyTrainer


def _grid(width: int) -> list[int]:
    small = [r for r in (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16) if r < width]
    wide = [r for r in (20, 24, 28, 32, 40, 48, 56) if r < width]
    return small + wide + [width]


@torch.no_grad()
def calibrate(run: Path, episodes: int, rows: list[dict]) -> None:
    with tempfile.TemporaryDirectory(prefix="adarl-calib-") as tmp:
        copy = Path(tmp) / run.name
        shutil.copytree(run, copy, ignore=shutil.ignore_patterns("*.corrupt", "report.md", "plots"))
        trainer = OffPolicyTrainer.resume(copy, quiet=True, truncate_metrics=False)
        c = trainer.c
        loss = c.modules.loss
        batch = recent_transitions(c.replay_buffer, 2048)
        sites, _ = find_low_rank_layers(loss)

        def td_loss() -> float:
            torch.manual_seed(0)
            return float(loss(batch.clone())["loss_qvalue"])

        def nominal_return() -> float:
            # the same evaluation episodes (start states) for every rank
            c.eval_env.set_seed(12345)
            return evaluate_policy(c.modules.actor, c.eval_env, episodes=episodes).mean

        base_return = nominal_return()
        base_td = td_loss()
        print(f"{run.name}: nominal return {base_return:.1f}, critic loss {base_td:.4g}", flush=True)
        for site in sites:
            u, s, vh = factor_svd(site.w1, site.w2)
            width = site.rank
            members = [()] if not site.batch_shape else [(i,) for i in range(site.batch_shape[0])]
            probes = [_NetworkProbe(site.network_name, site.network, site.params, m, batch) for m in members]
            old1, old2 = site.w1.detach().clone(), site.w2.detach().clone()
            for rank in _grid(width):
                w1, w2 = _padded_factors(u, s, vh, rank, width, site.w1.dtype)
                key1, key2 = site.key + ("w1",), site.key + ("w2",)
                err = max(p.relative_error({key1: w1[m], key2: w2[m]}) for p, m in zip(probes, members))
                site.w1.copy_(w1)  # the online factors only: the TD target keeps the trained target critics
                site.w2.copy_(w2)
                row = {
                    "run": run.name,
                    "layer": site.path,
                    "network": site.role,
                    "width": width,
                    "rank": rank,
                    "relative_error": err,
                }
                if site.role == "actor":
                    ret = nominal_return()
                    row |= {"return": ret, "return_ratio": ret / base_return if base_return else float("nan")}
                else:
                    td = td_loss()
                    row |= {"critic_loss": td, "critic_loss_ratio": td / base_td if base_td else float("nan")}
                site.w1.copy_(old1)
                site.w2.copy_(old2)
                rows.append(row)
                print(
                    f"  {site.path} rank {rank:3d}: error {err:.4f} "
                    + (
                        f"return {row['return']:.1f}"
                        if "return" in row
                        else f"critic loss x{row['critic_loss_ratio']:.3f}"
                    ),
                    flush=True,
                )
        trainer.close()


def plot(rows: list[dict], out: Path, tolerances: tuple[float, float] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, (ax, role, key, label) in enumerate(
        (
            (axes[0], "actor", "return_ratio", "nominal return / untruncated"),
            (axes[1], "critic", "critic_loss_ratio", "critic TD loss / untruncated"),
        )
    ):
        for layer in sorted({r["layer"].split(".", 1)[1] for r in rows if r["network"] == role}):
            pts = [
                (float(r["relative_error"]), float(r[key]))
                for r in rows
                if r["network"] == role and r["layer"].endswith(layer) and float(r["relative_error"]) > 1e-4
            ]
            if pts:
                ax.scatter([p[0] for p in pts], [p[1] for p in pts], s=12, label=f"{role} {layer}")
        if tolerances is not None:
            ax.axvline(tolerances[i], color="red", ls="--", lw=1, label=f"default tolerance {tolerances[i]:g}")
        ax.set_xscale("log")
        if role == "critic":
            ax.set_yscale("log")
        ax.set_xlabel("relative output error of the truncation")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="*", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--replot", action="store_true", help="only redraw calibration.png from --out's CSV")
    a = p.parse_args()
    from adarl.runtime.config import load_recipe

    accept = load_recipe("base").rank.accept
    tolerances = (accept.actor_tol, accept.critic_tol)
    if a.replot:
        with open(a.out / "calibration.csv") as fh:
            plot(list(csv.DictReader(fh)), a.out / "calibration.png", tolerances)
        return
    torch.set_num_threads(1)
    rows: list[dict] = []
    for run in a.runs:
        calibrate(run, a.episodes, rows)
    a.out.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(a.out / "calibration.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    plot(rows, a.out / "calibration.png", tolerances)
    print(f"wrote {a.out / 'calibration.csv'} and calibration.png")


if __name__ == "__main__":
    main()
