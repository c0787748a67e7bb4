"""Training callbacks: a recipe's ``callbacks`` list, built and called at the trainer's hook points (docs/callbacks.md).

A callback is a TorchRL :class:`~torchrl.trainers.TrainerHookBase`: ``register(trainer, name)`` puts its methods on
the trainer's hook points with ``trainer.register_op(point, op)`` and itself with ``trainer.register_module(name,
self)``; ``state_dict()`` goes into every checkpoint and ``load_state_dict()`` gets it back on resume (and on a
rollback). The base :class:`Callback` registers whichever of these methods a subclass defines:

=====================  =====================================================================================
hook point             called with
=====================  =====================================================================================
``post_optim``         after each optimisation step: its losses, a :class:`~tensordict.TensorDict` (detached)
``post_steps``         after each collected batch is consumed (its updates done): the batch, a TensorDict
``post_eval``          after each nominal evaluation: ``{"frames", "updates", "eval/mean_reward",
                       "eval/std_reward"}``
``post_rank_event``    after each rank event, changed or not: the :class:`~adarl.core.adapter.RankEvent`
=====================  =====================================================================================

TorchRL's own ``Trainer`` calls ``post_optim`` and ``post_steps`` with no argument; here they receive what a
callback would otherwise have to dig out of the trainer. Any callback may ask the run to stop
(:meth:`Callback.request_stop`): the run stops at the end of that batch and ends as a finished one does (its final
evaluation, checkpoint, summary and report), and ``summary.json``'s ``stopped_early`` says at which frame, by which
callback and why. The stop is kept in the checkpoints: a resumed run that stopped is complete, and trains on only
when ``adarl resume`` raises ``collector.total_frames`` or changes ``callbacks`` (:func:`stop_holds`).

adarl's own: :class:`StopOnReturn` (``stop_on_return``, SB3's ``StopTrainingOnRewardThreshold``). Others are
registered with :func:`adarl.plugins.register_callback`.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from tensordict import TensorDict
from torchrl.trainers import TrainerHookBase

from adarl import plugins
from adarl.errors import AdaRLValueError, one_of
from adarl.runtime import metrics

__all__ = ["HOOK_POINTS", "Callback", "StopOnReturn", "TrainerHooks", "build_callbacks", "stop_holds", "recorded"]

#: the trainer's hook points, in the order they come in a batch
HOOK_POINTS = ("post_optim", "post_steps", "post_eval", "post_rank_event")


class Callback(TrainerHookBase):
    """Base of a recipe's callbacks: define any of :data:`HOOK_POINTS` as a method and it is registered there.

    ``self.trainer`` and ``self.name`` are set by :meth:`register`. Override :meth:`state_dict` and
    :meth:`load_state_dict` to keep counters across a kill and resume (plain Python values and tensors: checkpoints
    load with ``torch.load(weights_only=True)``)."""

    trainer: Any = None
    name: str | None = None

    def register(self, trainer, name: str) -> None:
        self.trainer, self.name = trainer, name
        for point in HOOK_POINTS:
            op = getattr(self, point, None)
            if callable(op):
                trainer.register_op(point, op)
        trainer.register_module(name, self)

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        return None

    def request_stop(self, reason: str) -> None:
        """Ask the run to stop at the end of the current batch (``reason`` goes into summary.json)."""
        self.trainer.request_stop(reason, by=self.name)


class StopOnReturn(Callback):
    """``stop_on_return``: stop after the first evaluation whose mean return is >= ``threshold`` (and not before
    ``min_frames``), as SB3's ``StopTrainingOnRewardThreshold`` in an ``EvalCallback``."""

    def __init__(self, threshold: float, min_frames: int = 0) -> None:
        self.threshold, self.min_frames = float(threshold), int(min_frames)

    def post_eval(self, result: dict) -> None:
        mean = float(result[metrics.EVAL_RETURN])
        if result["frames"] >= self.min_frames and mean >= self.threshold:
            self.request_stop(f"{metrics.EVAL_RETURN} {mean:.6g} >= threshold {self.threshold:g}")


def _names(recipe) -> list[str]:
    """Each entry's name on the trainer: its callback name, with ``#i`` (its index) where a name is listed twice."""
    names = [c.name for c in recipe.callbacks]
    return [n if names.count(n) == 1 else f"{n}#{i}" for i, n in enumerate(names)]


def build_callbacks(recipe) -> list[tuple[str, TrainerHookBase]]:
    """``[(name, callback)]``: each entry of ``recipe.callbacks`` built from its registered class with its options."""
    out = []
    for name, entry in zip(_names(recipe), recipe.callbacks, strict=True):
        spec = plugins.callback(entry.name)
        obj = spec.callback_class()(**entry.options)
        if not isinstance(obj, TrainerHookBase):
            raise AdaRLValueError(
                f"callback {entry.name!r} ({spec.callback_path}) built a {type(obj).__name__}, not a TorchRL "
                "TrainerHookBase; subclass adarl.runtime.callbacks.Callback"
            )
        out.append((name, obj))
    return out


def recorded(recipe) -> list[dict]:
    """The recipe's callbacks as a stop records them (names and options): a stop holds while they are the same."""
    return [{"name": c.name, "options": dict(c.options)} for c in recipe.callbacks]


def stop_holds(stop: dict | None, recipe) -> bool:
    """Whether a recorded stop still ends the run under ``recipe``: the same frame budget and the same callbacks
    (``adarl resume RUN collector.total_frames=M`` or ``callbacks=...`` lets it train on)."""
    return (
        stop is not None
        and int(stop.get("total_frames", -1)) == int(recipe.collector.total_frames)
        and stop.get("callbacks") == recorded(recipe)
    )


class TrainerHooks:
    """A trainer's hook points, registered modules and stop request (TorchRL ``Trainer``'s ``register_op`` and
    ``register_module``, for adarl's hook points); its :meth:`state_dict` is the checkpoint's ``callbacks``."""

    def __init__(self) -> None:
        self.ops: dict[str, list[Callable]] = {point: [] for point in HOOK_POINTS}
        self.modules: dict[str, TrainerHookBase] = {}
        self.stop: dict | None = None  # the stop request of this run: frames, updates, callback, reason, ...
        self.earlier: list[dict] = []  # stops a resume trained on past (a raised budget, changed callbacks)

    def register_op(self, dest: str, op: Callable) -> None:
        if dest not in self.ops:
            raise AdaRLValueError(f"unknown hook point {dest!r}; allowed: {one_of(HOOK_POINTS)}")
        if not callable(op):
            raise AdaRLValueError(f"register_op({dest!r}, ...): the op must be callable, got {op!r}")
        self.ops[dest].append(op)

    def register_module(self, name: str, module: TrainerHookBase) -> None:
        if name in self.modules:
            raise AdaRLValueError(f"a callback named {name!r} is already registered on this trainer")
        self.modules[name] = module

    def request_stop(self, reason: str, *, by: str | None, frames: int, updates: int, recipe) -> None:
        """Record a stop request (the first one is kept): where, by which callback, why, and under which budget
        and callbacks it holds (:func:`stop_holds`)."""
        if self.stop is None:
            self.stop = {"frames": int(frames), "updates": int(updates), "callback": by, "reason": str(reason)}
            self.stop.update(total_frames=int(recipe.collector.total_frames), callbacks=recorded(recipe))

    def on_resume(self, recipe, *, quiet: bool = False) -> None:
        """Before training: a run a callback stopped is complete (said), unless its budget or callbacks changed
        since; then it trains on (said even when ``quiet``: it is what the resume decided, and why; the stop is
        kept in summary.json's ``earlier_stops``)."""
        stop = self.stop
        if stop is None:
            return
        where = f"this run stopped early at {stop['frames']} frames ({stop['reason']}; callback {stop['callback']})"
        if stop_holds(stop, recipe):
            line = f"{where}; it is complete"
        else:
            self.earlier.append(stop)
            self.stop = None
            line = (
                f"{where}; training on to collector.total_frames={recipe.collector.total_frames}: the frame budget "
                "or the callbacks changed since"
            )
        if not quiet or self.stop is None:
            print(f"adarl: {line}", file=sys.stderr, flush=True)

    def wants(self, dest: str) -> bool:
        return bool(self.ops[dest])

    def call(self, dest: str, arg: Any) -> None:
        for op in self.ops[dest]:
            op(arg)

    def post_optim(self, losses: dict) -> None:
        """The ``post_optim`` ops, with the step's losses as a TensorDict (built only when an op is registered)."""
        if self.ops["post_optim"]:
            self.call("post_optim", TensorDict({k: v.detach() for k, v in losses.items()}, []))

    def state_dict(self) -> dict:
        return {
            "modules": {name: m.state_dict() for name, m in self.modules.items()},
            "stop": self.stop,
            "earlier": list(self.earlier),
        }

    def load_state_dict(self, state: dict | None) -> None:
        """Each registered callback gets its saved state (by name); one the checkpoint lacks starts fresh (a
        checkpoint from before callbacks, or callbacks changed on resume)."""
        state = state or {}
        saved = state.get("modules") or {}
        for name, module in self.modules.items():
            if name in saved:
                module.load_state_dict(saved[name])
        self.stop = state.get("stop")
        self.earlier = list(state.get("earlier") or [])
