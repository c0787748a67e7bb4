"""Fused Adam without its per-call Python: the same kernels ``torch.optim.Adam(fused=True).step()`` runs.

Mirrors: ``torch.optim.Adam(fused=True).step()`` followed by ``zero_grad(set_to_none=True)``.
Equality: ``tests/test_fast_sac.py::test_direct_adam_step_is_bit_identical_to_fused_adam_and_falls_back``
(bit-identical parameters and optimiser state, fall-back to ``opt.step()`` where an assumption does not hold).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from adarl.fast import _torch_private as private

__all__ = ["DirectAdamStep", "make_adam"]


def make_adam(
    params: Sequence[torch.Tensor], lr: float, *, fused: bool, scaled: Sequence[torch.Tensor] = (), scale: float = 1.0
) -> torch.optim.Adam:
    """Adam, fused into one kernel per step when ``fused`` (same maths as the for-loop Adam, fp tolerance).

    ``scaled`` tensors (e.g. the low-rank factors, ``algorithm.factor_lr_scale``) form a second parameter group
    whose learning rate is ``lr * scale``; the learning-rate schedules scale both groups alike (they multiply each
    group's own base rate). Without them, or with ``scale == 1``, there is one group, as before."""
    params, scaled = list(params), list(scaled)
    if not scaled or scale == 1.0:
        groups = [{"params": params + scaled}]
    else:
        groups = [g for g in ({"params": params}, {"params": scaled, "lr": lr * scale}) if g["params"]]
    if fused:
        return torch.optim.Adam(groups, lr=lr, fused=True)
    return torch.optim.Adam(groups, lr=lr)


class DirectAdamStep:
    """``opt.step(); opt.zero_grad(set_to_none=True)`` of a fused ``torch.optim.Adam``, without its per-call Python.

    Why: at (64, 64) the three optimisers' ``step()`` took ~0.55 ms of a ~4.6 ms update, nearly all of it Python
    (grouping tensors, state look-ups, hooks, the profiler wrapper); the fused kernel itself is tens of
    microseconds. This calls the very kernels ``Adam(fused=True)`` calls (``torch._foreach_add_`` on the step
    counters, then ``torch._fused_adam_``, through the version guard :mod:`adarl.fast._torch_private`) on lists
    cached from ``opt.state``, with the group's current hyper-parameters, so the result is bit-identical (tested).
    It falls back to ``opt.step()`` whenever an assumption does not hold: state not created yet or replaced (first
    step, a rank event popping a factor's state, ``load_state_dict``), a missing gradient, hooks, options other than
    plain fused Adam (amsgrad, capturable, differentiable, decoupled weight decay), or a torch the guard does not
    know. Several parameter groups
    (``algorithm.factor_lr_scale``) take one kernel call each, with each group's own learning rate, as
    ``Adam(fused=True)`` does.
    """

    def __init__(self, opt: torch.optim.Optimizer) -> None:
        self.opt = opt
        self._cache: tuple | None = None
        self.fast_steps = 0  # steps taken by the direct path (the rest went through opt.step())

    def _hooked(self) -> bool:
        """Whether ``opt.step()`` must run (a hook to honour, or a torch the private kernels were not tested on)."""
        return private.optimizer_hooked(self.opt)

    def _supported(self) -> bool:
        o = self.opt
        if not isinstance(o, torch.optim.Adam) or not o.param_groups:
            return False
        return all(
            bool(g.get("fused"))
            and not g.get("amsgrad")
            and not g.get("capturable")
            and not g.get("differentiable")
            and not g.get("decoupled_weight_decay")
            for g in o.param_groups
        )

    def _build_cache(self) -> list | None:
        """Per parameter group: the group's ``params`` list, a copy of it, and its tensors' states."""
        cache = []
        for group in self.opt.param_groups:
            params = group["params"]
            states = [self.opt.state.get(p) for p in params]
            if any(st is None or "exp_avg" not in st for st in states):
                return None
            if len({(p.device, p.dtype) for p in params}) != 1:
                return None
            cache.append(
                (
                    params,
                    list(params),
                    states,
                    [st["exp_avg"] for st in states],
                    [st["exp_avg_sq"] for st in states],
                    [st["step"] for st in states],
                )
            )
        return cache

    def _valid(self, cache) -> bool:
        groups = self.opt.param_groups
        if len(groups) != len(cache):
            return False
        state = self.opt.state
        for group, (params, plist, states, avgs, sqs, steps) in zip(groups, cache):
            if group["params"] is not params or len(params) != len(plist):
                return False
            for p, q, st, a, b, c in zip(params, plist, states, avgs, sqs, steps):
                if p is not q or p.grad is None:
                    return False
                got = state.get(p)
                if (
                    got is not st
                    or got.get("exp_avg") is not a
                    or got.get("exp_avg_sq") is not b
                    or got.get("step") is not c
                ):
                    return False
        return True

    @torch.no_grad()
    def step(self) -> None:
        cache = self._cache
        if self._hooked():
            cache = self._cache = None
        if cache is None or not self._valid(cache):
            cache = self._cache = self._build_cache() if self._supported() and not self._hooked() else None
            if cache is None or not self._valid(cache):
                self._cache = None
                self.opt.step()
                self.opt.zero_grad(set_to_none=True)
                return
        for g, (_, plist, _, avgs, sqs, steps) in zip(self.opt.param_groups, cache):
            private.fused_adam_step(g, plist, avgs, sqs, steps)
            for p in plist:
                p.grad = None
        self.fast_steps += 1
