"""Robustness sweeps: evaluate a trained policy on a grid of fixed dynamics (paper Fig. 8, RRLS-style).

One or two perturbation parameters vary over a grid; every other parameter stays at the nominal dynamics (the
centre of the run's training schedule). Each grid point gets ``episodes`` deterministic episodes; we report their
mean, std, 95% interval and worst case, and over the whole grid the worst case and the average (as RRLS does).

``adarl eval RUN_DIR --sweep torso_length=0.25:0.55:7`` writes ``RUN_DIR/sweeps/<name>.csv`` (one row per grid
point), ``<name>.json`` (summary) and ``<name>.png`` (mean with std band and worst-case stars; a heat map in 2-D).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from adarl.envs.registry import parameters_for
from adarl.errors import AdaRLValueError, did_you_mean
from adarl.runtime.report import pyplot
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = ["parse_sweep", "SweepPoint", "SweepResult", "sweep_policy", "sweep_run", "read_sweep", "plot_sweep"]


def parse_sweep(text: str) -> tuple[str, list[float]]:
    """``"param=lo:hi:n"`` (n evenly spaced values, ends included) or ``"param=v1,v2,..."`` -> (param, values)."""
    if not isinstance(text, str) or "=" not in text:
        raise AdaRLValueError(
            f"sweep {text!r} must look like PARAM=LO:HI:N (e.g. torso_length=0.25:0.55:7) or PARAM=V1,V2,..."
        )
    name, spec = (s.strip() for s in text.split("=", 1))
    if not name:
        raise AdaRLValueError(f"sweep {text!r} has no parameter name before '='")
    try:
        if ":" in spec:
            parts = spec.split(":")
            if len(parts) != 3:
                raise ValueError
            lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
            if n < 1 or not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError
            values = [lo] if n == 1 else [lo + (hi - lo) * i / (n - 1) for i in range(n)]
        else:
            values = [float(v) for v in spec.split(",") if v.strip()]
            if not values or not all(math.isfinite(v) for v in values):
                raise ValueError
    except ValueError:
        raise AdaRLValueError(
            f"sweep {text!r}: expected {name}=LO:HI:N with numbers LO, HI and an integer N >= 1, "
            f"or {name}=V1,V2,... with finite numbers"
        ) from None
    return name, [round(v, 12) for v in values]


@dataclass
class SweepPoint:
    """One grid point: the swept values and the episode returns there."""

    values: dict[str, float]
    returns: list[float]
    mean: float = field(init=False)
    std: float = field(init=False)
    ci95: float = field(init=False)
    worst: float = field(init=False)

    def __post_init__(self) -> None:
        from adarl.runtime.evaluation import EvalResult  # torch: imported once a sweep is read, not before

        r = EvalResult(returns=list(self.returns), lengths=[0] * len(self.returns))
        self.mean, self.std, self.ci95 = r.mean, r.std, r.ci95
        self.worst = min(self.returns) if self.returns else float("nan")


@dataclass
class SweepResult:
    """A whole sweep: its grid, the fixed nominal values of the other parameters, and the per-point results."""

    params: list[str]
    nominal: dict[str, float]
    points: list[SweepPoint]
    episodes: int
    frames: int | None = None
    name: str = ""

    @property
    def worst_case(self) -> float:
        """Lowest single-episode return anywhere on the grid."""
        return min(p.worst for p in self.points)

    @property
    def worst_mean(self) -> float:
        """Lowest per-point mean return (the worst dynamics on average)."""
        return min(p.mean for p in self.points)

    @property
    def average(self) -> float:
        """Mean over grid points of the per-point mean return."""
        return sum(p.mean for p in self.points) / len(self.points)

    def summary(self) -> dict:
        worst = min(self.points, key=lambda p: p.mean)
        return {
            "name": self.name,
            "params": self.params,
            "nominal": self.nominal,
            "episodes": self.episodes,
            "frames": self.frames,
            "points": len(self.points),
            "average": self.average,
            "worst_mean": self.worst_mean,
            "worst_mean_at": worst.values,
            "worst_case": self.worst_case,
        }

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow([*self.params, "mean", "std", "ci95", "worst", "episodes", "returns"])
        for p in self.points:
            w.writerow(
                [
                    *(p.values[k] for k in self.params),
                    p.mean,
                    p.std,
                    p.ci95,
                    p.worst,
                    len(p.returns),
                    json.dumps(p.returns),
                ]
            )
        return buf.getvalue()

    def describe(self) -> str:
        s = self.summary()
        return (
            f"sweep {self.name} over {', '.join(self.params)} ({len(self.points)} points x {self.episodes} "
            f"episodes, others at nominal {self.nominal}): average {s['average']:.1f}, worst mean "
            f"{s['worst_mean']:.1f} at {s['worst_mean_at']}, worst episode {s['worst_case']:.1f}"
        )


def _grid(axes: list[tuple[str, list[float]]]) -> list[dict[str, float]]:
    names = [n for n, _ in axes]
    return [dict(zip(names, combo)) for combo in itertools.product(*(v for _, v in axes))]


def sweep_policy(
    policy,
    env_id: str,
    axes: list[tuple[str, list[float]]],
    *,
    nominal: dict[str, float],
    episodes: int = 5,
    max_steps: int = 1000,
    seed: int = 0,
    **env_kwargs,
) -> SweepResult:
    """Evaluate ``policy`` deterministically at each grid point of ``axes`` (others held at ``nominal``)."""
    if not 1 <= len(axes) <= 2:
        raise AdaRLValueError(f"a sweep varies one or two parameters, got {len(axes)}: {[n for n, _ in axes]}")
    names = [n for n, _ in axes]
    if len(set(names)) != len(names):
        raise AdaRLValueError(f"sweep parameters must differ, got {names}")
    # a plugin's parameter: its package is loaded first; a recipe's own (env.parameters) come in env_kwargs
    allowed = parameters_for(env_id, env_kwargs.get("parameters"), require=names)
    for n in names:
        if n not in allowed:
            raise AdaRLValueError(
                f"unknown sweep parameter {n!r} for {env_id}; allowed: {list(allowed)}{did_you_mean(n, allowed)}"
                + ("" if allowed else " (it has none: a MuJoCo env can declare some in env.parameters)")
            )
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise AdaRLValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    from adarl.envs.factory import make_eval_env
    from adarl.runtime.evaluation import evaluate_policy

    points = []
    for values in _grid(axes):
        env = make_eval_env(env_id, values={**nominal, **values}, seed=seed, **env_kwargs)
        try:
            result = evaluate_policy(policy, env, episodes=episodes, max_steps=max_steps)
        finally:
            env.close()
        points.append(SweepPoint(values, result.returns))
    return SweepResult(names, {k: v for k, v in nominal.items() if k not in names}, points, episodes)


def _nominal_values(recipe) -> dict[str, float]:
    from adarl.envs.factory import resolve_schedule

    p = recipe.env.perturbation
    schedule = p.schedule.model_dump() if hasattr(p.schedule, "model_dump") else p.schedule
    sched = resolve_schedule(recipe.env.id, p.preset, schedule)
    return dict(sched.nominal()) if sched is not None else {}


def sweep_run(
    run_dir: str | os.PathLike,
    axes: list[tuple[str, list[float]]],
    *,
    episodes: int | None = None,
    name: str | None = None,
    checkpoint: str | os.PathLike | None = None,
) -> SweepResult:
    """Sweep the latest checkpoint of a run folder (or ``checkpoint``: ``"latest"``, ``"best"``, a file, as
    :meth:`~adarl.runtime.trainers.base.BaseTrainer.resume` takes it); writes ``sweeps/<name>.{csv,json,png}`` there
    and nothing else (the run is loaded read-only)."""
    # Check the grid against the run's env before loading anything heavy.
    env = RunDir.open(run_dir).load_recipe().env
    env_id = env.id
    allowed = parameters_for(env_id, env.declared(), require=[n for n, _ in axes])
    for n, _ in axes:
        if n not in allowed:
            raise AdaRLValueError(
                f"unknown sweep parameter {n!r} for {env_id}; allowed: {list(allowed)}{did_you_mean(n, allowed)}"
                + ("" if allowed else " (it has none: a MuJoCo env can declare some in env.parameters)")
            )
    from adarl.runtime.trainers import BaseTrainer  # torch and TorchRL: once the grid is known to be valid

    trainer = BaseTrainer.resume(run_dir, quiet=True, read_only=True, checkpoint=checkpoint)
    try:
        recipe = trainer.recipe
        e = recipe.env
        result = sweep_policy(
            trainer.c.raw_observation_actor(),  # the sweep's envs are built without the run's normaliser
            e.id,
            axes,
            nominal=_nominal_values(recipe),
            episodes=episodes or recipe.eval.episodes,
            max_steps=recipe.eval.max_steps,
            seed=recipe.seed + 20_000,
            mode=e.perturbation.mode,
            device=recipe.device,
            max_episode_steps=e.max_episode_steps,
            parameters=e.declared(),
        )
    finally:
        trainer.close()
    result.frames = trainer.frames
    result.name = name or "__".join(n for n, _ in axes)
    out = Path(run_dir) / "sweeps"
    out.mkdir(exist_ok=True)
    (out / f"{result.name}.csv").write_text(result.to_csv())
    (out / f"{result.name}.json").write_text(json.dumps(result.summary(), indent=2) + "\n")
    plot_sweep(result, out / f"{result.name}.png")
    return result


def read_sweep(csv_path: str | os.PathLike) -> SweepResult:
    """Load a sweep back from its CSV (and JSON summary beside it, when present)."""
    path = Path(csv_path)
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise AdaRLValueError(f"sweep file {str(path)!r} has no rows")
    fixed = {"mean", "std", "ci95", "worst", "episodes", "returns"}
    params = [k for k in rows[0] if k not in fixed]
    points = [SweepPoint({k: float(r[k]) for k in params}, [float(x) for x in json.loads(r["returns"])]) for r in rows]
    meta = path.with_suffix(".json")
    info = json.loads(meta.read_text()) if meta.is_file() else {}
    return SweepResult(params, info.get("nominal", {}), points, int(rows[0]["episodes"]), info.get("frames"), path.stem)


def plot_sweep(result: SweepResult, out: str | os.PathLike) -> Path:
    """Fig. 8 style: mean with a std band and red worst-case stars (1-D), or a heat map of the mean (2-D)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    if len(result.params) == 1:
        k = result.params[0]
        x = [p.values[k] for p in result.points]
        m = [p.mean for p in result.points]
        s = [p.std for p in result.points]
        ax.plot(x, m, "o-", label=f"mean over {result.episodes} episodes")
        ax.fill_between(x, [a - b for a, b in zip(m, s)], [a + b for a, b in zip(m, s)], alpha=0.25, label="± std")
        worst = [p.worst for p in result.points]
        ax.plot(x, worst, ":", color="red", lw=1, label="worst episode at each point")
        k = worst.index(min(worst))
        ax.plot([x[k]], [worst[k]], "*", color="red", ms=13, label="worst case")
        ax.set_xlabel(k)
        ax.set_ylabel("episode return")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    else:
        kx, ky = result.params
        xs = sorted({p.values[kx] for p in result.points})
        ys = sorted({p.values[ky] for p in result.points})
        grid = [[math.nan] * len(xs) for _ in ys]
        for p in result.points:
            grid[ys.index(p.values[ky])][xs.index(p.values[kx])] = p.mean
        im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
        ax.set_xticks(range(len(xs)), [f"{v:.3g}" for v in xs])
        ax.set_yticks(range(len(ys)), [f"{v:.3g}" for v in ys])
        for i, row in enumerate(grid):
            for j, v in enumerate(row):
                # dark text on the light (high) end of viridis, white on the dark end: readable everywhere
                light = not math.isnan(v) and im.norm(v) > 0.6
                ax.text(j, i, f"{v:.0f}", ha="center", va="center", fontsize=7, color="black" if light else "white")
        fig.colorbar(im, ax=ax, label="mean return")
        ax.set_xlabel(kx)
        ax.set_ylabel(ky)
    ax.set_title(f"worst case {result.worst_case:.1f}, average {result.average:.1f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return Path(out)
