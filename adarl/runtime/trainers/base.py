"""What every trainer does the same way, whatever the algorithm: :class:`BaseTrainer`.

It owns the run folder (its lock, resolved recipe, logger, checkpoints, records and report), the progress bar, the
logging of episodes, losses and throughput, the evaluation and checkpoint cadence, the divergence guards (stop, or roll
back to the last checkpoint with a lower learning rate), the first SIGINT/SIGTERM/SIGHUP (a checkpoint, then
:class:`~adarl.runtime.signals.RunInterrupted`), and exact resume (counters, RNGs, the live episode and the
collector's state in every checkpoint: what a checkpoint holds, and its writing and loading, are its mixin
:class:`~adarl.runtime.trainers._checkpointing.Checkpointing`'s). A subclass builds its components and consumes one
collected batch:

* :meth:`_build_components` - the components (``self.c``, a
  :class:`~adarl.runtime.builders.common.RunComponents`: they save and load their own checkpoint state, say which
  parameters the divergence guard checks, and hold the replay buffer, rank adapter and rank events if any); by
  default the recipe's family's builder makes them (``family(recipe).build(recipe)``);
* :meth:`_consume` - one batch: count its frames, log its episodes, run the updates; return the losses;
* :attr:`counters` - its own counters, checkpointed with the common ones.

What a rank event sets off, the trainer's records included, is wired in :mod:`adarl.runtime.rank_events`. Which
trainer runs a recipe is the one dispatcher's answer (:func:`trainer_class`, :mod:`adarl.runtime.families`). The
loop (:meth:`train` and :meth:`_train_batches`) reads top to bottom: collect, consume, log, evaluate, checkpoint,
stop on a signal or at the frame budget.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import time
import warnings
from collections.abc import Sequence
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tqdm import auto as tqdm_auto

from adarl.errors import FusedFallbackWarning, command
from adarl.runtime import metrics
from adarl.runtime.builders.common import RunComponents
from adarl.runtime.callbacks import TrainerHooks, build_callbacks, stop_holds
from adarl.runtime.continuing import open_continued, retarget_schedules, schedule_totals
from adarl.runtime.evaluation import EvalResult, evaluate_policy
from adarl.runtime.families import check_trainer, family
from adarl.runtime.guards import NonFiniteError, NonFiniteGuard
from adarl.runtime.report import write_report
from adarl.runtime.run_folder.run_dir import RunDir, null_logger, recipe_fingerprint
from adarl.runtime.run_folder.verdicts import await_verdict
from adarl.runtime.signals import FINISHING, GracefulInterrupt, RunInterrupted, stopped_after_the_end
from adarl.runtime.trainers._checkpointing import Checkpointing

__all__ = ["BaseTrainer", "trainer_class"]


class BaseTrainer(Checkpointing):
    """Runs one recipe in one run folder: train, evaluate on nominal dynamics, checkpoint, report.

    ``OffPolicyTrainer(recipe, run_dir).train()`` for a new run; ``BaseTrainer.resume(run_dir).train()`` to continue
    one (the recipe's ``algorithm.base`` picks the subclass: :func:`trainer_class`). Which loop a trainer runs is
    said once, by the family that names it (:mod:`adarl.runtime.families`); a recipe of another loop is refused there
    (:func:`~adarl.runtime.families.check_trainer`).
    """

    #: the subclass's own counters, checkpointed with the common ones: ``{attribute: (type, value a checkpoint
    #: without it resumes from)}``, ``None`` for a counter every checkpoint has; each starts at 0
    counters: ClassVar[dict[str, tuple[type, int | float | None]]] = {}

    def __init__(
        self,
        recipe,
        run_dir: RunDir,
        *,
        quiet: bool = False,
        _resume_state: dict | None = None,
        _log_from: int | None = None,
        _read_only: bool = False,
    ) -> None:
        check_trainer(recipe, type(self))
        self.recipe = recipe
        self.run_dir = run_dir
        self.quiet = quiet
        self.read_only = _read_only  # loaded for evaluation: nothing is written into the run folder
        self.fingerprint = recipe_fingerprint(recipe)
        self.frames = 0
        self.updates = 0
        self.episodes = 0
        self.last_eval_frames = 0
        self._watched = True  # until its evaluations find no watcher's file (run_folder.verdicts)
        self.last_ckpt_frames = 0
        self.best_eval = -math.inf
        self.last_return = float("nan")
        self.rollbacks = 0
        self.warm_start_frames = (
            0  # env frames collected by rank events' warm starts (off-policy; counted in `frames` by default)
        )
        # training losses are averaged over logging.log_interval frames (sums kept in checkpoints: exact resume)
        self._loss_sums: dict[str, float] = {}
        self._loss_count = 0
        self._last_log_frames = 0
        self._bar = None
        self._clock: tuple[float, int, int] | None = None
        self._wall_before = 0.0  # training wall time of the earlier processes of this run (from the checkpoint)
        self._fps_frames: int | None = None
        for name, (kind, _) in self.counters.items():
            setattr(self, name, kind(0))
        if not _read_only:
            run_dir.lock()  # one process trains in a run folder at a time (released by close())
            if _resume_state is None and not run_dir.recipe_path.exists():
                run_dir.save_recipe(recipe)  # a run started from Python resumes and loads like any
        # _log_from: the frames a resumed run's logs continue from (None: a new run, or evaluation only)
        self.logger = null_logger() if _read_only else run_dir.make_logger(recipe, step=_log_from)
        self.hooks = TrainerHooks()  # the recipe's callbacks (adarl.runtime.callbacks), before a checkpoint loads
        for name, callback in build_callbacks(recipe):
            callback.register(self, name)
        with warnings.catch_warnings():
            if _read_only:  # loaded to evaluate: no update runs, so the update path's cost is no news (issue 48.6)
                warnings.simplefilter("ignore", FusedFallbackWarning)
            self._build(_resume_state)

    # ------------------------------------------------------------------ what a subclass provides
    def _build_components(self, state: dict | None) -> RunComponents:
        """Build the run's components (to continue from checkpoint ``state`` when given): the family's builder's."""
        return family(self.recipe).build(self.recipe)

    def _consume(self, batch: TensorDictBase) -> list[dict[str, torch.Tensor]] | None:
        """One collected batch: count its frames, log its episodes, run the updates it allows. Returns the
        updates' losses (None when it ran none, as before the first update: nothing is logged then)."""
        raise NotImplementedError

    def _postfix(self) -> dict:
        """The progress bar's postfix."""
        return {"ret": f"{self.last_return:.1f}", "upd": str(self.updates)}  # tqdm shows an int as 1e+4

    @property
    def adapter(self):
        """The rank adapter of the run (None: no rank adaptation)."""
        return self.c.adapter

    # ------------------------------------------------------------------ callbacks (TorchRL Trainer's names)
    def register_op(self, dest: str, op) -> None:
        """Call ``op`` at the hook point ``dest`` (:data:`adarl.runtime.callbacks.HOOK_POINTS`)."""
        self.hooks.register_op(dest, op)

    def register_module(self, name: str, module) -> None:
        """Checkpoint ``module``'s ``state_dict`` (a TorchRL ``TrainerHookBase``) as ``name``."""
        self.hooks.register_module(name, module)

    def request_stop(self, reason: str, *, by: str | None = None) -> None:
        """Stop this run at the end of the current batch, as a finished one ends; the first request is kept and
        recorded (summary.json's ``stopped_early``, and every checkpoint from here on)."""
        self.hooks.request_stop(reason, by=by, frames=self.frames, updates=self.updates, recipe=self.recipe)

    @property
    def stopped_early(self) -> dict | None:
        """The stop a callback asked for, while it still ends this run (None: none, or a resume trains past it)."""
        return self.hooks.stop if stop_holds(self.hooks.stop, self.recipe) else None

    # ------------------------------------------------------------------ construction
    def _build(self, state: dict | None) -> None:
        """Build the components (fresh, or to continue from checkpoint ``state``), this run's records of their rank
        events, and the divergence guard."""
        self.c = self._build_components(state)
        if self.c.rank_events is not None:
            self.c.rank_events.record_run(self)
            if self.hooks.wants("post_rank_event"):
                self.c.rank_events.after_event.append(lambda event: self.hooks.call("post_rank_event", event))
        self.guard = NonFiniteGuard(self.c.guarded_parameters())
        if state is not None:
            totals = schedule_totals(self.c.schedulers)  # as this recipe's total plans them
            self._load_checked(state)
            retarget_schedules(self.c.schedulers, totals)  # a run continued to more frames: re-planned from here

    @classmethod
    def resume(
        cls,
        path: str | os.PathLike,
        *,
        quiet: bool = False,
        truncate_metrics: bool = True,
        checkpoint: str | os.PathLike | None = None,
        read_only: bool | None = None,
        overrides: Sequence[str] = (),
    ) -> BaseTrainer:
        """Continue the run in ``path`` from its latest loadable checkpoint (metrics after it are dropped first).

        The trainer is the recipe's (:func:`trainer_class`: ``OffPolicyTrainer.resume`` of a PPO run gives a
        :class:`~adarl.runtime.trainers.ppo.PPOTrainer`) unless ``cls`` is a subclass of it.
        ``checkpoint``: None, the newest checkpoint that loads (a damaged or foreign newer one is skipped with a
        :class:`~adarl.errors.CheckpointFallbackWarning` naming it and why); ``"latest"``, the newest or a
        :class:`~adarl.errors.CheckpointError` (no fallback); ``"best"`` (the best nominal evaluation); or a
        checkpoint file (its replay buffer is looked for beside it). Every checkpoint is checked against the run's
        recipe (:func:`~adarl.runtime.run_folder.run_dir.recipe_fingerprint`) before any tensor is used.
        ``read_only`` (default: ``not truncate_metrics``, i.e. loading to evaluate): nothing in the run folder is
        written, renamed or locked, and the replay buffer is not read; such a trainer evaluates, it does not train.
        ``overrides``: ``collector.total_frames=M`` continues the run (a finished one too) to ``M`` frames, and
        recipe.yaml records it; any other key is refused by name (:mod:`adarl.runtime.continuing`).
        """
        run_dir, recorded, recipe = open_continued(path, overrides)
        target = trainer_class(recipe)
        cls = cls if issubclass(cls, target) else target
        read_only = not truncate_metrics if read_only is None else read_only
        if not read_only:
            run_dir.lock()  # one process trains in a run folder at a time
        fingerprint = recipe_fingerprint(recipe)
        continuing = recipe is not recorded and not read_only
        if not read_only and checkpoint in (None, "latest") and run_dir.starts_over():
            if continuing:
                run_dir.save_recipe(recipe)
            return cls(recipe, run_dir, quiet=quiet)  # stopped before its frame-0 checkpoint: start it again
        if checkpoint is None or checkpoint == "latest":
            state = run_dir.load_latest_checkpoint(
                quarantine=not read_only,
                fingerprint=fingerprint,
                strict=checkpoint == "latest",
                replay_buffer=not read_only,
            )
        else:
            state = run_dir.load_checkpoint(
                run_dir.best_checkpoint_path if checkpoint == "best" else checkpoint,
                fingerprint=fingerprint,
                replay_buffer=not read_only,
            )
        if truncate_metrics and not read_only:
            run_dir.truncate_metrics(int(state["counters"]["frames"]))
        log_from = int(state["counters"]["frames"]) if truncate_metrics and not read_only else None
        trainer = cls(recipe, run_dir, quiet=quiet, _resume_state=state, _log_from=log_from, _read_only=read_only)
        if continuing:
            run_dir.save_recipe(recipe)  # the new total, once the checkpoint has loaded into it
        return trainer

    # ------------------------------------------------------------------ the loop
    def train(self) -> dict:
        """Collect, update, evaluate and checkpoint until the frame budget is spent; write the summary and report.

        The first SIGINT/SIGTERM/SIGHUP checkpoints after the current batch and raises :class:`RunInterrupted`;
        NaN/inf in training raises :class:`~adarl.runtime.guards.NonFiniteError` (or rolls back, per
        ``recipe.guards``).
        """
        rc = self.recipe
        total = rc.collector.total_frames
        bar = tqdm_auto.tqdm(
            total=total, initial=self.frames, unit="frame", disable=self.quiet, dynamic_ncols=True, desc=rc.name
        )
        self._bar = bar
        self._clock = (time.perf_counter(), self.frames, self.updates)  # time/fps counts this process's work only
        self.hooks.on_resume(self.recipe, quiet=self.quiet)  # a stopped run: complete, or trains on (said)
        try:
            with self._interrupt() as interrupt:
                if not self.run_dir.checkpoints():
                    self.save_checkpoint()  # frame 0: a run killed at any later moment can be resumed
                while self.hooks.stop is None:  # a run a callback stopped is complete
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
                if self.frames >= total:
                    self.hooks.stop = None  # the budget was spent: no early stop
                last = self.save_checkpoint()
                interrupt.notice = FINISHING  # a signal from here on stops once the summary and report are written
                summary = self._write_summary(self._wall_time())
                # the plots a user opens at once; `adarl report RUN` adds their PDF and SVG (about 1.5 s more)
                write_report(self.run_dir.path, formats=("png",))
        finally:
            self._sync_bar()
            bar.close()
            self._bar = None
        self.close()
        if interrupt.requested is not None:
            raise stopped_after_the_end(interrupt.requested, self.frames, last, self.run_dir.path)
        return summary

    def _interrupt(self) -> GracefulInterrupt:
        """What turns a signal into a stop after the current batch: this run's own handler (the seeds of a pack share
        their pack's, :mod:`adarl.runtime.trainers.packed`)."""
        return GracefulInterrupt(quiet=self.quiet)

    def _train_batches(self, bar, interrupt: GracefulInterrupt) -> None:
        rc = self.recipe
        total = rc.collector.total_frames
        for batch in self.c.collector if self.frames < total else ():
            losses = self._consume(batch)
            if losses is not None:
                self._log_losses(losses)
            self._sync_bar()  # the batch and any warm-start frames that count towards the budget
            if self.hooks.wants("post_steps"):
                self.hooks.call("post_steps", batch)
            evaluated = self.frames - self.last_eval_frames >= rc.eval.interval
            if evaluated:
                self._evaluate()
            saved = None
            if self.frames - self.last_ckpt_frames >= rc.checkpoint.interval:
                saved = self.save_checkpoint()
            bar.set_postfix(refresh=False, **self._postfix())
            if evaluated and self.frames < total and self._watched:
                # `adarl tune`'s pruner decides on this evaluation before the run trains on (run_folder.verdicts)
                held = await_verdict(
                    self.run_dir.path, self.frames, lambda: interrupt.requested is not None, quiet=self.quiet
                )
                self._watched = held not in ("unwatched", "stale")
            if interrupt.requested is not None and self.frames < total:
                # from here on a second signal is ignored: the stop is moments away and must not be cut short
                interrupt.stopping(f"saving the checkpoint at {self.frames} frames, then exiting")
                # this batch's checkpoint when one was just written (the same state: writing it again would only
                # open a window in which a kill leaves it half-replaced)
                path = saved or self.save_checkpoint(scheduled=False)
                self.close()
                name = signal.Signals(interrupt.requested).name
                raise RunInterrupted(
                    f"stopped on {name} at {self.frames} frames; checkpoint {path.name} saved, continue with "
                    f"`{command('adarl', 'resume', self.run_dir.path)}`",
                    signum=interrupt.requested,
                    checkpoint=path,
                )
            if self.frames >= total or self.hooks.stop is not None:
                break

    def _sync_bar(self) -> None:
        """Move the progress bar to ``self.frames``: every frame the budget counts (warm starts included when
        ``replay.warm_start.count_frames``), so that its percentage and ETA are right."""
        bar = self._bar
        if bar is not None and self.frames != bar.n:
            bar.update(self.frames - bar.n)

    # ------------------------------------------------------------------ divergence
    def _on_nonfinite(self, err: NonFiniteError) -> None:
        """Stop with a clear message, or roll back to the last checkpoint with a lower learning rate."""
        g = self.recipe.guards
        ckpts = self.run_dir.checkpoints()
        last = ckpts[-1].name if ckpts else "none"
        if g.on_nonfinite == "rollback" and self.rollbacks < g.max_rollbacks and ckpts:
            self._rollback(err)
            return
        self.close()
        why = (
            f"after {self.rollbacks} rollback(s) (guards.max_rollbacks={g.max_rollbacks})"
            if g.on_nonfinite == "rollback"
            else "(guards.on_nonfinite=stop)"
        )
        raise NonFiniteError(
            f"training diverged: {err} at {self.frames} frames; stopped {why} without writing a checkpoint. The last "
            f"good checkpoint is {last}; continue it with `{command('adarl', 'resume', self.run_dir.path)}`, or lower "
            f"algorithm.lr, or set guards.on_nonfinite=rollback",
            stage=err.stage,
            what=err.what,
            update=err.update,
        ) from None

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
            print(
                f"adarl: {err}; rolled back to {self.frames} frames with the learning rate x{g.lr_factor} "
                f"(rollback {self.rollbacks}/{g.max_rollbacks})",
                file=sys.stderr,
                flush=True,
            )

    def _clip_and_step(self) -> None:
        """Per-optimiser gradient clipping (``algorithm.max_grad_norm``), then every optimiser's step."""
        max_norm = self.recipe.algorithm.max_grad_norm
        if max_norm is not None:
            for opt in self.c.optimizers.values():
                for group in opt.param_groups:
                    torch.nn.utils.clip_grad_norm_(group["params"], max_norm)
        for opt in self.c.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)

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
                    self.logger.log_scalar(
                        metrics.dynamics(name), float(value.reshape(-1)[done].float().mean()), step=self.frames
                    )

    def _log_losses(self, losses: list[dict[str, torch.Tensor]], *, flush: bool = False) -> None:
        """Accumulate a batch's losses; every ``logging.log_interval`` frames log their means (and at the end)."""
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
            self.logger.log_scalar(metrics.TRAIN_LR, self.c.optimizers["actor"].param_groups[0]["lr"], step=self.frames)
        self._log_throughput()
        self._loss_sums, self._loss_count = {}, 0

    def _log_throughput(self) -> None:
        """``time/fps`` and ``time/updates_per_s`` since this process started training (wall clock)."""
        if self._clock is None or self._fps_frames == self.frames:  # once per step
            return
        self._fps_frames = self.frames
        t0, frames0, updates0 = self._clock
        elapsed = time.perf_counter() - t0
        if elapsed > 0 and self.frames > frames0:
            self.logger.log_scalar(metrics.FPS, (self.frames - frames0) / elapsed, step=self.frames)
            self.logger.log_scalar(metrics.UPDATES_PER_S, (self.updates - updates0) / elapsed, step=self.frames)
        self.logger.log_scalar(metrics.TIME_ELAPSED, self._wall_time(), step=self.frames)

    def _evaluate(self) -> EvalResult:
        e = self.recipe.eval
        result = evaluate_policy(self.c.modules.actor, self.c.eval_env, episodes=e.episodes, max_steps=e.max_steps)
        self.last_eval_frames = self.frames
        self.logger.log_scalar(metrics.EVAL_RETURN, result.mean, step=self.frames)
        self.logger.log_scalar(metrics.EVAL_RETURN_STD, result.std, step=self.frames)
        self.logger.log_scalar(metrics.EVAL_LENGTH, sum(result.lengths) / len(result.lengths), step=self.frames)
        self.run_dir.append_eval(self.frames, self.updates, result, ranks=self.adapter.ranks if self.adapter else {})
        if result.mean > self.best_eval:
            self.best_eval = result.mean
            if self.recipe.checkpoint.keep_best:
                self.run_dir.save_best(
                    self.state_dict(), frames=self.frames, score=result.mean, fingerprint=self.fingerprint
                )
        if self.hooks.wants("post_eval"):
            what = {metrics.EVAL_RETURN: result.mean, metrics.EVAL_RETURN_STD: result.std}
            self.hooks.call("post_eval", {"frames": self.frames, "updates": self.updates, **what})
        return result

    def _wall_time(self) -> float:
        """Seconds of training in this run, every process of it (each resume adds its own to the checkpoint's)."""
        now = time.perf_counter() - self._clock[0] if self._clock is not None else 0.0
        return self._wall_before + now

    def _summary(self, elapsed: float) -> dict:
        adapter, warm_start_frames = self.adapter, self.warm_start_frames
        return {
            "name": self.recipe.name,
            "frames": self.frames,
            "warm_start_frames": warm_start_frames,
            "env_frames": self.frames + (0 if self.recipe.replay.warm_start.count_frames else warm_start_frames),
            "updates": self.updates,
            "episodes": self.episodes,
            "wall_time_s": elapsed,
            "updates_per_s": self.updates / elapsed if elapsed > 0 else float("nan"),
            "ranks": adapter.ranks if adapter is not None else {},
            "layer_names": adapter.names if adapter is not None else {},  # module path -> name
            "rank_events": len(adapter.history) if adapter is not None else 0,
            "final_eval": self.run_dir.last_eval(),
            "best_eval_mean": self.best_eval,
            "stopped_early": self.hooks.stop,  # a callback's stop: frames, updates, callback, reason (None: none)
            "earlier_stops": self.hooks.earlier,
        }

    def _write_summary(self, elapsed: float) -> dict:
        summary = self._summary(elapsed)
        self.run_dir.write_json("summary.json", summary)
        return summary

    def close(self) -> None:
        """Close the collector, envs and logger, and release the run folder."""
        self.c.close()
        self.run_dir.close_logger(self.logger)
        if not getattr(self, "read_only", True):  # an evaluator never held the lock (a trainer beside it may)
            self.run_dir.unlock()


def trainer_class(recipe) -> type[BaseTrainer]:
    """The trainer that runs ``recipe``: its loop's (``algorithm.base``: a plugin's algorithm runs on its base's
    trainer, :mod:`adarl.plugins`), as the one dispatcher says (:func:`adarl.runtime.families.family`)."""
    return family(recipe).trainer_class()
