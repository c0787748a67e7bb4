"""AdaRL-SAC end to end: compose TorchRL's SACLoss, replay buffer and Collector with adarl's components.

:func:`build_components` returns every piece a recipe describes, wired together, for users who want to write
their own loop; :class:`Trainer` runs the recipe's loop in a run folder (metrics, rank history, evaluation,
checkpoints, report). The loop is CleanRL-style: readable top to bottom in :meth:`Trainer.train`.
"""

from __future__ import annotations

import functools
import json
import math
import os
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs import TransformedEnv

from adarl.acceptance import ProjectionAcceptance, RecentTransitions
from adarl.adapter import RankAdapter
from adarl.builders import SACModules, check_device, make_sac_modules
from adarl.env_state import (
    collector_state_dict,
    env_state_dict,
    gym_rng_state_dict,
    load_collector_state_dict,
    load_env_state_dict,
    load_gym_rng_state_dict,
)
from adarl.envs import dynamics_state_dict, load_dynamics_state_dict, make_env, make_eval_env
from adarl.errors import AdaRLError, AdaRLValueError, CheckpointError
from adarl.fast_sac import FusedSACUpdate, make_adam, wants_fused
from adarl.fast_replay import UniformTensorSampler
from adarl.lean_collector import LeanCollector, wants_lean
from adarl.evaluation import EvalResult, evaluate_policy
from adarl.guards import NonFiniteError, NonFiniteGuard, check_live_layers
from adarl import metrics
from adarl.lr_schedule import make_lr_scheduler
from adarl.policy import policy_specs
from adarl.rank import make_rule
from adarl.run_dir import RunDir, null_logger, recipe_fingerprint
from adarl.signals import GracefulInterrupt, RunInterrupted
from adarl.warmstart import ReplayWarmStart

__all__ = ["Components", "build_components", "Trainer"]


@dataclass
class Components:
    """Everything a recipe builds, wired together (no training has happened yet)."""

    recipe: object
    env: object
    eval_env: object
    modules: SACModules
    optimizers: dict[str, torch.optim.Optimizer]
    schedulers: dict[str, torch.optim.lr_scheduler.LRScheduler]
    replay_buffer: TensorDictReplayBuffer
    collector: Collector | LeanCollector
    adapter: RankAdapter | None
    warm_start: ReplayWarmStart | None
    total_updates: int
    extras: dict = field(default_factory=dict)

    @property
    def policy(self):
        """The stochastic policy the collector runs (the same parameter objects as the loss's actor)."""
        return self.modules.actor


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU determinism is what the exact-resume guarantee relies on)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def update_after(recipe) -> int:
    """Frames collected before the first optimisation step (``algorithm.update_after``, else the random phase)."""
    a = recipe.algorithm.update_after
    return recipe.collector.init_random_frames if a is None else a


def planned_updates(recipe) -> int:
    """Optimisation steps the recipe's budget allows (frames after the first update times the UTD ratio)."""
    c = recipe.collector
    return max(1, int((c.total_frames - min(update_after(recipe), c.total_frames)) * recipe.algorithm.utd_ratio))


def _env_kwargs(recipe) -> dict:
    e = recipe.env
    p = e.perturbation
    return dict(mode=p.mode, dynamics_key=p.key, device=recipe.device, max_episode_steps=e.max_episode_steps)


def train_env_factory(recipe) -> Callable[[], TransformedEnv]:
    """A picklable callable that builds the training env (a collector worker process builds its own copy)."""
    e, p = recipe.env, recipe.env.perturbation
    return functools.partial(make_env, e.id, preset=p.preset, schedule=p.schedule, num_envs=e.num_envs,
                             parallel=e.parallel, seed=recipe.seed, **_env_kwargs(recipe))


def make_envs(recipe) -> tuple:
    """The training env (perturbed per episode) and the evaluation env (fixed at the nominal dynamics)."""
    e, p = recipe.env, recipe.env.perturbation
    env = train_env_factory(recipe)()
    # Evaluation runs on the nominal dynamics: the centre of the training schedule (or the plain env).
    nominal = (p.schedule if p.schedule is not None else p.preset) if recipe.eval.nominal else "none"
    eval_env = make_eval_env(e.id, nominal, seed=recipe.seed + 10_000, **_env_kwargs(recipe))
    return env, eval_env


def build_components(recipe, *, init_random_frames: int | None = None,
                     scratch_dir: str | os.PathLike | None = None) -> Components:
    """Build env, networks, SAC loss, optimisers, LR schedules, buffer, collector, rank adapter and warm start.

    With ``algorithm.fused`` the SAC step is a :class:`~adarl.fast_sac.FusedSACUpdate` in ``extras["fused_update"]``
    (same parameters, losses and optimisers as the plain path). ``scratch_dir`` holds a memmap replay storage."""
    check_device(recipe.device)
    if recipe.algorithm.num_threads is not None:
        torch.set_num_threads(recipe.algorithm.num_threads)
    seed_everything(recipe.seed)
    env, eval_env = make_envs(recipe)
    modules = make_sac_modules(recipe, env)
    loss = modules.loss
    alg = recipe.algorithm

    actor_params = list(loss.actor_network_params.flatten_keys().values())
    critic_params = list(loss.qvalue_network_params.flatten_keys().values())
    fused = wants_fused(alg.fused, loss)
    if alg.parseval.enabled and fused:
        # The fused step computes SACLoss's terms only; the Parseval term needs the TorchRL path.
        if alg.fused is True:
            raise AdaRLValueError("algorithm.fused: true cannot add the Parseval term; allowed with "
                                  "algorithm.parseval.enabled: 'auto' or false")
        fused = False
    optimizers = {
        "actor": make_adam(actor_params, alg.lr, fused=fused),
        "critic": make_adam(critic_params, alg.lr, fused=fused),
    }
    if not alg.fixed_alpha:
        optimizers["alpha"] = make_adam([loss.log_alpha], alg.alpha_lr, fused=fused)
    total_updates = planned_updates(recipe)
    s = recipe.lr_schedule
    schedulers = {
        name: make_lr_scheduler(
            optimizers[name],
            warmup_steps=s.warmup_steps,
            total_steps=total_updates if s.cosine else None,
            min_factor=s.min_factor,
        )
        for name in ("actor", "critic")
    }

    generator = torch.Generator().manual_seed(recipe.seed + 1)
    replay_buffer = TensorDictReplayBuffer(
        storage=(LazyMemmapStorage(recipe.replay.size, scratch_dir=scratch_dir, device=recipe.device)
                 if recipe.replay.storage == "memmap" else LazyTensorStorage(recipe.replay.size, device=recipe.device)),
        sampler=RandomSampler(),
        batch_size=alg.batch_size,
        generator=generator,
    )
    c = recipe.collector
    init_random = c.init_random_frames if init_random_frames is None else init_random_frames
    lean = wants_lean(c.lean, env, modules.actor)
    if c.overlap and not lean:
        raise AdaRLValueError(f"collector.overlap: {c.overlap!r} needs the lean collector (one env, a TanhNormal "
                              "actor, collector.lean: 'auto' or true); allowed otherwise: collector.overlap: false")
    if lean:
        collector = LeanCollector(env, modules.actor, frames_per_batch=c.frames_per_batch,
                                  init_random_frames=init_random, overlap=c.overlap, noise_seed=recipe.seed + 2,
                                  env_factory=train_env_factory(recipe) if c.overlap == "process" else None)
    else:
        collector = Collector(env, modules.actor, frames_per_batch=c.frames_per_batch, total_frames=-1,
                              init_random_frames=init_random, device=recipe.device)

    adapter = warm_start = None
    r = recipe.rank
    if r.enabled:
        if r.rule == "fixed":
            rule = make_rule("fixed", rank=r.target_rank)
        elif r.rule == "policy_fit":
            rule = make_rule("policy_fit", lam=r.lam)
        else:
            rule = make_rule(r.rule, beta=r.beta)
        w = recipe.replay.warm_start
        if w.mode == "reset" or (w.mode != "keep" and w.frames > 0):
            # the lean collector is no torchrl Collector: the warm start rolls the same env and policy out itself
            source = (env, modules.actor) if lean else collector
            warm_start = ReplayWarmStart(replay_buffer, source, frames=w.frames, mode=w.mode)
        a = r.accept
        # 'fixed' is an instruction (the fixed-rank projection), not a candidate: nothing to accept or refuse
        acceptance = (ProjectionAcceptance(a.actor_tol, a.critic_tol, search=a.search)
                      if a.mode == "projection" and r.rule != "fixed" else None)
        adapter = RankAdapter(
            loss,
            list(optimizers.values()),
            rule,
            interval=r.interval,
            scope=r.scope,
            min_rank=r.min_rank,
            target_mode=r.target_mode,
            lr_schedulers=list(schedulers.values()),
            # the acceptance step (and, with 'always', the recorded error) compares outputs on recent transitions
            fit_data=RecentTransitions(replay_buffer, a.samples),
            num_threads=r.num_threads,
            acceptance=acceptance,
        )
    extras = {"sampling_generator": generator}
    update = None
    if fused:
        try:
            update = FusedSACUpdate(loss, list(optimizers.values()), tau=alg.tau,
                                    schedulers=list(schedulers.values()), max_grad_norm=alg.max_grad_norm,
                                    compile=alg.compile, backward=alg.backward)
        except AdaRLValueError:
            if alg.fused is True or alg.backward == "manual":  # asked for explicitly: say why not
                raise
            # 'auto' with layers the fused step does not know (e.g. the sparsification layer): TorchRL's path.
    if update is not None:
        extras["fused_update"] = update
        # the same indices rb.sample() would draw, gathered straight into the update's five tensors
        extras["fused_sampler"] = UniformTensorSampler(replay_buffer, FusedSACUpdate.KEYS, generator=generator)
        if adapter is not None:
            adapter.on_truncate.insert(0, update.on_rank_event)
    if alg.parseval.enabled:  # Parseval baseline: a term added to the SAC loss (adarl.baselines.parseval)
        from adarl.baselines.parseval import ParsevalRegularizer

        pv = alg.parseval
        extras["regularizer"] = ParsevalRegularizer(loss, lam=pv.lam, s=pv.s, base_width=pv.base_width)
    return Components(recipe, env, eval_env, modules, optimizers, schedulers, replay_buffer, collector, adapter,
                      warm_start, total_updates, extras=extras)


def _rank_summary(adapter: RankAdapter | None) -> str:
    """The progress bar's ranks: ``actor.layer0=11 actor.layer1=64 ...``."""
    if adapter is None:
        return "-"
    return " ".join(f"{name}={rank}" for name, rank in adapter.named_ranks.items())


class Trainer:
    """Runs one recipe in one run folder: train, evaluate on nominal dynamics, checkpoint, report.

    ``Trainer(recipe, run_dir).train()`` for a new run; ``Trainer.resume(run_dir).train()`` to continue one.
    """

    def __init__(self, recipe, run_dir: RunDir, *, quiet: bool = False, _resume_state: dict | None = None,
                 _log_from: int | None = None, _read_only: bool = False) -> None:
        self.recipe = recipe
        self.run_dir = run_dir
        self.quiet = quiet
        self.read_only = _read_only  # loaded for evaluation: nothing is written into the run folder
        self.fingerprint = recipe_fingerprint(recipe)
        self.frames = 0
        self.updates = 0
        self.episodes = 0
        self.last_eval_frames = 0
        self.last_ckpt_frames = 0
        self.best_eval = -math.inf
        self.last_return = float("nan")
        self.rollbacks = 0
        self.warm_start_frames = 0  # env frames collected by warm starts (also counted in `frames` by default)
        # training losses are averaged over logging.log_interval frames (sums kept in checkpoints: exact resume)
        self._loss_sums: dict[str, float] = {}
        self._loss_count = 0
        self._last_log_frames = 0
        self._pending_updates = 0.0
        self._bar = None
        if not _read_only:
            run_dir.lock()  # one process trains in a run folder at a time (released by close())
        # _log_from: the frames a resumed run's logs continue from (None: a new run, or evaluation only)
        self.logger = null_logger() if _read_only else run_dir.make_logger(recipe, step=_log_from)
        self._build(_resume_state)

    def _build(self, state: dict | None) -> None:
        """Build the components (fresh, or to continue from checkpoint ``state``)."""
        init_random = None
        if state is not None and state.get("collector") is None:
            # Checkpoints without the collector's state (older format): skip the random frames already done.
            init_random = max(0, self.recipe.collector.init_random_frames - int(state["counters"]["frames"]))
        self.c = build_components(self.recipe, init_random_frames=init_random,
                                  scratch_dir=None if self.read_only else self.run_dir.path / "replay_storage")
        if self.c.adapter is not None:
            lean = isinstance(self.c.collector, LeanCollector)
            if lean:  # nothing may step the env under the warm start (a batch being prefetched is dropped)
                self.c.adapter.on_truncate.append(lambda event: self.c.collector.reset())
            self.c.adapter.on_truncate.append(self._on_truncate)
            if lean:  # the warm start stepped the env under it
                self.c.adapter.on_truncate.append(lambda event: self.c.collector.reset())
            self.c.adapter.on_event.append(self._on_rank_event)
        loss = self.c.modules.loss
        named = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items()}
        named.update({f"critic.{k}": v for k, v in loss.qvalue_network_params.flatten_keys(".").items()})
        if not self.recipe.algorithm.fixed_alpha:
            named["log_alpha"] = loss.log_alpha
        self.guard = NonFiniteGuard(named)
        self._factors = {k: v for k, v in named.items() if k.endswith((".w1", ".w2"))}
        if state is not None:
            self._load_checked(state)

    def _load_checked(self, state: dict) -> None:
        """:meth:`_load_state`, with a checkpoint that does not fit (one written before checkpoints named their
        recipe, for other networks) refused in one line instead of a traceback from deep inside torch."""
        try:
            self._load_state(state)
        except AdaRLError:
            raise
        except (RuntimeError, KeyError, ValueError, IndexError, TypeError) as err:
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            where = state.get("checkpoint_file", "the checkpoint")
            raise CheckpointError(f"checkpoint {where!r} does not fit this run's recipe ({type(err).__name__}: "
                                  f"{first[:200]}); it was written for other networks or is damaged") from None

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def resume(cls, path: str | os.PathLike, *, quiet: bool = False, truncate_metrics: bool = True,
               checkpoint: str | os.PathLike | None = None, read_only: bool | None = None) -> Trainer:
        """Continue the run in ``path`` from its latest loadable checkpoint (metrics after it are dropped first).

        ``checkpoint``: None, the newest checkpoint that loads (a damaged or foreign newer one is skipped with a
        :class:`~adarl.errors.CheckpointFallbackWarning` naming it and why); ``"latest"``, the newest or a
        :class:`~adarl.errors.CheckpointError` (no fallback); ``"best"`` (the best nominal evaluation); or a
        checkpoint file (its replay buffer is looked for beside it). Every checkpoint is checked against the run's
        recipe (:func:`~adarl.run_dir.recipe_fingerprint`) before any tensor is used.
        ``read_only`` (default: ``not truncate_metrics``, i.e. loading to evaluate): nothing in the run folder is
        written, renamed or locked, and the replay buffer is not read; such a trainer evaluates, it does not train.
        """
        from adarl.config import load_recipe

        run_dir = RunDir.open(path)
        recipe = load_recipe(str(run_dir.recipe_path))
        if recipe.algorithm.name == "ppo" and cls is Trainer:  # the baselines' PPO loop has its own trainer
            from adarl.training_ppo import PPOTrainer

            cls = PPOTrainer
        read_only = not truncate_metrics if read_only is None else read_only
        if not read_only:
            run_dir.lock()  # one process trains in a run folder at a time
        fingerprint = recipe_fingerprint(recipe)
        if checkpoint is None or checkpoint == "latest":
            state = run_dir.load_latest_checkpoint(quarantine=not read_only, fingerprint=fingerprint,
                                                   strict=checkpoint == "latest", replay_buffer=not read_only)
        else:
            state = run_dir.load_checkpoint(run_dir.best_checkpoint_path if checkpoint == "best" else checkpoint,
                                            fingerprint=fingerprint, replay_buffer=not read_only)
        if truncate_metrics and not read_only:
            run_dir.truncate_metrics(int(state["counters"]["frames"]))
        log_from = int(state["counters"]["frames"]) if truncate_metrics and not read_only else None
        return cls(recipe, run_dir, quiet=quiet, _resume_state=state, _log_from=log_from, _read_only=read_only)

    # ------------------------------------------------------------------ the loop
    def train(self) -> dict:
        """Collect, update, adapt ranks, evaluate and checkpoint until the frame budget is spent.

        The first SIGINT/SIGTERM checkpoints after the current batch and raises :class:`RunInterrupted`; NaN/inf
        in training raises :class:`~adarl.guards.NonFiniteError` (or rolls back, per ``recipe.guards``).
        """
        from tqdm.auto import tqdm

        rc = self.recipe
        total = rc.collector.total_frames
        bar = tqdm(total=total, initial=self.frames, unit="frame", disable=self.quiet, dynamic_ncols=True,
                   desc=rc.name)
        self._bar = bar
        start = time.perf_counter()
        self._clock = (start, self.frames, self.updates)  # time/fps counts this process's work only
        try:
            with GracefulInterrupt(quiet=self.quiet) as interrupt:
                if not self.run_dir.checkpoints():
                    self.save_checkpoint()  # frame 0: a run killed at any later moment can be resumed
                while True:
                    try:
                        self._train_batches(bar, interrupt)
                        break
                    except NonFiniteError as err:
                        self._on_nonfinite(err)
                        bar.reset(total=total)
                        bar.update(self.frames)
                self._log_losses([], flush=True)  # the last partial logging interval
                if self.last_eval_frames != self.frames:
                    self._evaluate()
                self.save_checkpoint()
        finally:
            self._sync_bar()
            bar.close()
            self._bar = None
        elapsed = time.perf_counter() - start
        summary = self._write_summary(elapsed)
        from adarl.report import write_report

        write_report(self.run_dir.path)
        self.close()
        return summary

    def _train_batches(self, bar, interrupt: GracefulInterrupt) -> None:
        rc, c = self.recipe, self.c
        total = rc.collector.total_frames
        for batch in c.collector if self.frames < total else ():
            batch = batch.reshape(-1)
            if self.frames + batch.numel() > total:
                batch = batch[: total - self.frames]
            c.replay_buffer.extend(batch)
            self.frames += batch.numel()
            self._log_episodes(batch)

            if self.frames >= update_after(rc) and len(c.replay_buffer) >= rc.algorithm.batch_size:
                self._pending_updates += batch.numel() * rc.algorithm.utd_ratio
                n_updates = int(self._pending_updates)
                self._pending_updates -= n_updates
                losses = []
                for _ in range(n_updates):
                    if len(c.replay_buffer) < rc.algorithm.batch_size:
                        break  # a rank event emptied the buffer ('reset'): resume once a batch of new data is in
                    losses.append(self._update())
                self._log_losses(losses)

            self._sync_bar()  # the batch and any warm-start frames that count towards the budget
            if self.frames - self.last_eval_frames >= rc.eval.interval:
                self._evaluate()
            if self.frames - self.last_ckpt_frames >= rc.checkpoint.interval:
                self.save_checkpoint()
            bar.set_postfix(ret=f"{self.last_return:.1f}", ranks=_rank_summary(c.adapter), upd=self.updates,
                            refresh=False)
            if interrupt.requested is not None and self.frames < total:
                path = self.save_checkpoint(scheduled=False)
                self.close()
                import signal

                name = signal.Signals(interrupt.requested).name
                raise RunInterrupted(
                    f"stopped on {name} at {self.frames} frames; checkpoint {path.name} saved, continue with "
                    f"`adarl resume {self.run_dir.path}`", signum=interrupt.requested, checkpoint=path)
            if self.frames >= total:
                break

    def _sync_bar(self) -> None:
        """Move the progress bar to ``self.frames``: every frame the budget counts (warm starts included when
        ``replay.warm_start.count_frames``), so that its percentage and ETA are right."""
        bar = self._bar
        if bar is not None and self.frames != bar.n:
            bar.update(self.frames - bar.n)

    def _on_nonfinite(self, err: NonFiniteError) -> None:
        """Stop with a clear message, or roll back to the last checkpoint with a lower learning rate."""
        g = self.recipe.guards
        ckpts = self.run_dir.checkpoints()
        last = ckpts[-1].name if ckpts else "none"
        if g.on_nonfinite == "rollback" and self.rollbacks < g.max_rollbacks and ckpts:
            self._rollback(err)
            return
        self.close()
        why = (f"after {self.rollbacks} rollback(s) (guards.max_rollbacks={g.max_rollbacks})"
               if g.on_nonfinite == "rollback" else "(guards.on_nonfinite=stop)")
        raise NonFiniteError(
            f"training diverged: {err} at {self.frames} frames; stopped {why} without writing a checkpoint. The last "
            f"good checkpoint is {last}; continue it with `adarl resume {self.run_dir.path}`, or lower algorithm.lr, "
            f"or set guards.on_nonfinite=rollback", stage=err.stage, what=err.what, update=err.update) from None

    def _rollback(self, err: NonFiniteError) -> None:
        g = self.recipe.guards
        rollbacks = self.rollbacks + 1
        state = self.run_dir.load_latest_checkpoint(fingerprint=self.fingerprint)
        self.close()
        self.run_dir.lock()  # close() released it; training goes on here
        self.run_dir.truncate_metrics(int(state["counters"]["frames"]))
        self.logger = self.run_dir.make_logger(self.recipe, step=int(state["counters"]["frames"]))
        self._build(state)
        self.rollbacks = rollbacks
        for sched in self.c.schedulers.values():
            sched.base_lrs = [lr * g.lr_factor for lr in sched.base_lrs]
        for opt in self.c.optimizers.values():
            for group in opt.param_groups:
                group["lr"] *= g.lr_factor
                if "initial_lr" in group:
                    group["initial_lr"] *= g.lr_factor
        self.logger.log_scalar(metrics.ROLLBACKS, self.rollbacks, step=self.frames)
        if not self.quiet:
            import sys

            print(f"adarl: {err}; rolled back to {self.frames} frames with the learning rate x{g.lr_factor} "
                  f"(rollback {self.rollbacks}/{g.max_rollbacks})", file=sys.stderr, flush=True)

    def _update(self) -> dict[str, float]:
        """One SAC optimisation step, then the target update and (maybe) a rank event."""
        c, alg = self.c, self.recipe.algorithm
        fused = c.extras.get("fused_update")
        if fused is not None:  # adarl.fast_sac: the same step without SACLoss's TensorDict overhead
            out = fused.step(*c.extras["fused_sampler"]())
            self.guard.check_losses({k: out[k] for k in ("loss_actor", "loss_qvalue", "loss_alpha")}, self.updates)
            self.guard.check_params(self.updates)
            self.updates += 1
            if c.adapter is not None:
                c.adapter.step()
            return out
        td = c.modules.loss(c.replay_buffer.sample())
        self.guard.check_losses({k: td[k] for k in ("loss_actor", "loss_qvalue", "loss_alpha")}, self.updates)
        loss = td["loss_actor"] + td["loss_qvalue"] + td["loss_alpha"]
        regularizer = c.extras.get("regularizer")
        if regularizer is not None:
            td = regularizer.wrap_output(td)
            loss = loss + td["loss_parseval"]
        loss.backward()
        self.guard.check_grads(self.updates)
        if alg.max_grad_norm is not None:
            for opt in c.optimizers.values():
                for group in opt.param_groups:
                    torch.nn.utils.clip_grad_norm_(group["params"], alg.max_grad_norm)
        for opt in c.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        for sched in c.schedulers.values():
            sched.step()
        c.modules.target_updater.step()
        self.guard.check_params(self.updates)
        self.updates += 1
        out = {"loss_actor": td["loss_actor"].detach(), "loss_qvalue": td["loss_qvalue"].detach(),
               "loss_alpha": td["loss_alpha"].detach(), "alpha": td["alpha"].detach()}
        if "loss_parseval" in td.keys():
            out["loss_parseval"] = td["loss_parseval"].detach()
        if c.adapter is not None:
            c.adapter.step()
        return out

    def _on_truncate(self, event) -> None:
        """After a rank event: warm-start the buffer (its frames count towards the budget unless
        ``replay.warm_start.count_frames`` is false)."""
        c = self.c
        check_live_layers(self._factors, event_step=getattr(event, "step", None))
        added = 0
        if c.warm_start is not None:
            added = int(c.warm_start(event).frames_added)
            self.warm_start_frames += added
            if self.recipe.replay.warm_start.count_frames:
                self.frames += added
        self.logger.log_scalar(metrics.WARM_START_FRAMES, added, step=self.frames)

    def _on_rank_event(self, event) -> None:
        """After every rank event, changed or not (a refused candidate is a result too): ranks and history."""
        c = self.c
        for name, rank in c.adapter.named_ranks.items():
            self.logger.log_scalar(metrics.rank(name), rank, step=self.frames)
        for record in event.layers:
            if record.error is not None:
                self.logger.log_scalar(metrics.rank_error(record.name or record.layer), float(record.error),
                                       step=self.frames)
        self.run_dir.write_rank_history(c.adapter.history, frames=self.frames)

    # ------------------------------------------------------------------ logging and evaluation
    def _log_episodes(self, batch: TensorDictBase) -> None:
        done = batch["next", "done"].reshape(-1)
        if not bool(done.any()):
            return
        returns = batch["next", "episode_reward"].reshape(-1)[done]
        self.episodes += int(done.sum())
        self.last_return = float(returns.mean())
        self.logger.log_scalar(metrics.TRAIN_RETURN, self.last_return, step=self.frames)
        if ("next", "step_count") in batch.keys(True):
            lengths = batch["next", "step_count"].reshape(-1)[done]
            self.logger.log_scalar(metrics.TRAIN_LENGTH, float(lengths.float().mean()), step=self.frames)
        self.logger.log_scalar(metrics.TRAIN_EPISODES, self.episodes, step=self.frames)
        key = self.recipe.env.perturbation.key
        if key in batch.keys():
            for name, value in batch[key].items():
                if name != "episode":
                    self.logger.log_scalar(metrics.dynamics(name), float(value.reshape(-1)[done].float().mean()),
                                           step=self.frames)

    def _log_losses(self, losses: list[dict[str, torch.Tensor]], *, flush: bool = False) -> None:
        """Accumulate the batch's losses; every ``logging.log_interval`` frames log their means (and at the end)."""
        if losses:
            for k in losses[0]:
                self._loss_sums[k] = self._loss_sums.get(k, 0.0) + float(torch.stack([d[k] for d in losses]).sum())
            self._loss_count += len(losses)
        if not flush and self.frames - self._last_log_frames < self.recipe.logging.log_interval:
            return
        self._last_log_frames = self.frames
        if self._loss_count:
            for k, total in self._loss_sums.items():
                self.logger.log_scalar(metrics.train(k), total / self._loss_count, step=self.frames)
            self.logger.log_scalar(metrics.TRAIN_UPDATES, self.updates, step=self.frames)
            self.logger.log_scalar(metrics.TRAIN_LR, self.c.optimizers["actor"].param_groups[0]["lr"],
                                   step=self.frames)
        self._log_throughput()
        self._loss_sums, self._loss_count = {}, 0

    def _log_throughput(self) -> None:
        """``time/fps`` and ``time/updates_per_s`` since this process started training (wall clock)."""
        clock = getattr(self, "_clock", None)
        if clock is None or getattr(self, "_fps_frames", None) == self.frames:  # once per step
            return
        self._fps_frames = self.frames
        t0, frames0, updates0 = clock
        elapsed = time.perf_counter() - t0
        if elapsed > 0 and self.frames > frames0:
            self.logger.log_scalar(metrics.FPS, (self.frames - frames0) / elapsed, step=self.frames)
            self.logger.log_scalar(metrics.UPDATES_PER_S, (self.updates - updates0) / elapsed, step=self.frames)

    def _evaluate(self) -> EvalResult:
        e = self.recipe.eval
        result = evaluate_policy(self.c.modules.actor, self.c.eval_env, episodes=e.episodes, max_steps=e.max_steps)
        self.last_eval_frames = self.frames
        self.logger.log_scalar(metrics.EVAL_RETURN, result.mean, step=self.frames)
        self.logger.log_scalar(metrics.EVAL_RETURN_STD, result.std, step=self.frames)
        self.run_dir.append_eval(self.frames, self.updates, result, ranks=self.c.adapter.ranks if self.c.adapter else {})
        if result.mean > self.best_eval:
            self.best_eval = result.mean
            if self.recipe.checkpoint.keep_best:
                self.run_dir.save_best(self.state_dict(), frames=self.frames, score=result.mean,
                                       fingerprint=self.fingerprint)
        return result

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything needed to continue this run (the replay buffer is dumped beside it when configured)."""
        c = self.c
        if isinstance(c.collector, LeanCollector):  # a batch being prefetched moves the env: snapshot after it
            c.collector.drain(keep=True)
        return {
            "counters": {"frames": self.frames, "updates": self.updates, "episodes": self.episodes,
                         "last_eval_frames": self.last_eval_frames, "pending_updates": self._pending_updates,
                         "best_eval": self.best_eval, "last_ckpt_frames": self.last_ckpt_frames,
                         "rollbacks": self.rollbacks, "warm_start_frames": self.warm_start_frames,
                         "loss_sums": dict(self._loss_sums), "loss_count": self._loss_count,
                         "last_log_frames": self._last_log_frames},
            "loss": c.modules.loss.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in c.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in c.schedulers.items()},
            "adapter": c.adapter.state_dict() if c.adapter is not None else None,
            "rng": _rng_state(),
            "dynamics": dynamics_state_dict(c.env),
            "sampling_rng": c.extras["sampling_generator"].get_state(),
            "warm_start": c.warm_start.state_dict() if c.warm_start is not None else None,
            # The live episode (exact resume): simulator + gymnasium state, the collector's carrier and counters.
            "env_state": env_state_dict(c.env),
            "collector": collector_state_dict(c.collector),
            "eval_rng": gym_rng_state_dict(c.eval_env),
            "policy_specs": policy_specs(c.env),  # adarl.load_policy builds the actor from these, without an env
        }

    def save_checkpoint(self, *, scheduled: bool = True) -> Path:
        """Write a checkpoint (atomically; metric files are fsync'ed first so they are as durable as it).

        ``scheduled=False`` (an interrupt) does not move the checkpoint schedule, so resumed runs keep it.
        """
        if scheduled:
            self.last_ckpt_frames = self.frames
        self.run_dir.sync_metrics(self.logger)
        rb = self.c.replay_buffer if self.recipe.checkpoint.replay_buffer and len(self.c.replay_buffer) else None
        state = self.state_dict()
        state["replay_buffer_saved"] = rb is not None
        return self.run_dir.save_checkpoint(
            state, frames=self.frames, keep_last=self.recipe.checkpoint.keep_last, replay_buffer=rb,
            fingerprint=self.fingerprint,
        )

    def _load_state(self, state: dict) -> None:
        from adarl.adapter import resize_to_ranks

        c = self.c
        if state.get("adapter") is not None and c.adapter is not None:
            resize_to_ranks(c.modules.loss, state["adapter"], optimizers=list(c.optimizers.values()))
        c.modules.loss.load_state_dict(state["loss"])
        for k, o in c.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        for k, s in c.schedulers.items():
            s.load_state_dict(state["schedulers"][k])
        if c.adapter is not None and state.get("adapter") is not None:
            c.adapter.load_state_dict(state["adapter"])
        cnt = state["counters"]
        self.frames, self.updates, self.episodes = int(cnt["frames"]), int(cnt["updates"]), int(cnt["episodes"])
        self.last_eval_frames = int(cnt["last_eval_frames"])
        self.last_ckpt_frames = int(cnt.get("last_ckpt_frames", self.frames))
        self._pending_updates = float(cnt["pending_updates"])
        self.best_eval = float(cnt["best_eval"])
        self.rollbacks = int(cnt.get("rollbacks", 0))
        self.warm_start_frames = int(cnt.get("warm_start_frames", 0))
        self._loss_sums = {k: float(v) for k, v in cnt.get("loss_sums", {}).items()}
        self._loss_count = int(cnt.get("loss_count", 0))
        self._last_log_frames = int(cnt.get("last_log_frames", self.frames))
        if c.warm_start is not None and state.get("warm_start") is not None:
            c.warm_start.load_state_dict(state["warm_start"])
        load_dynamics_state_dict(c.env, state["dynamics"])
        live_episode = load_env_state_dict(c.env, state.get("env_state"))
        if state.get("collector") is not None:
            load_collector_state_dict(c.collector, state["collector"], carrier=live_episode)
        load_gym_rng_state_dict(c.eval_env, state.get("eval_rng"))
        c.extras["sampling_generator"].set_state(state["sampling_rng"])
        saved = state.get("replay_buffer_saved")
        if not self.read_only and (saved or (saved is None and self.recipe.checkpoint.replay_buffer)):
            source = state.get("checkpoint_file")  # the buffer lies beside the checkpoint file, wherever it is
            loaded = self.run_dir.load_replay_buffer(self.c.replay_buffer, frames=self.frames, checkpoint=source)
            if not loaded and saved:
                raise CheckpointError(f"the replay buffer saved with the checkpoint at {self.frames} frames is missing "
                                      f"from {Path(source).parent if source else self.run_dir.checkpoint_dir}")
        if c.adapter is not None and not self.read_only:  # the rank history as of the checkpoint resumed
            self.run_dir.write_rank_history(c.adapter.history, frames=self.frames)
        _set_rng_state(state["rng"])  # last: nothing after it may draw random numbers

    def _write_summary(self, elapsed: float) -> dict:
        summary = {
            "name": self.recipe.name,
            "frames": self.frames,
            "warm_start_frames": self.warm_start_frames,
            "env_frames": self.frames + (0 if self.recipe.replay.warm_start.count_frames else self.warm_start_frames),
            "updates": self.updates,
            "episodes": self.episodes,
            "wall_time_s": elapsed,
            "updates_per_s": self.updates / elapsed if elapsed > 0 else float("nan"),
            "ranks": self.c.adapter.ranks if self.c.adapter is not None else {},
            "layer_names": self.c.adapter.names if self.c.adapter is not None else {},  # module path -> name
            "rank_events": len(self.c.adapter.history) if self.c.adapter is not None else 0,
            "final_eval": self.run_dir.last_eval(),
            "best_eval_mean": self.best_eval,
        }
        self.run_dir.write_json("summary.json", summary)
        return summary

    def close(self) -> None:
        for closable in (self.c.collector, self.c.env, self.c.eval_env):
            try:
                closable.shutdown() if hasattr(closable, "shutdown") else closable.close()
            except Exception:  # already closed
                pass
        self.run_dir.close_logger(self.logger)
        if not getattr(self, "read_only", True):  # an evaluator never held the lock (a trainer beside it may)
            self.run_dir.unlock()


def _rng_state() -> dict:
    np_state = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"key": np_state[0], "state": torch.from_numpy(np_state[1].astype(np.int64)), "pos": int(np_state[2]),
                  "has_gauss": int(np_state[3]), "cached_gaussian": float(np_state[4])},
        "python": json.dumps(random.getstate()),
    }


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["key"], n["state"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached_gaussian"]))
    py = json.loads(state["python"])
    random.setstate((py[0], tuple(py[1]), py[2]))
