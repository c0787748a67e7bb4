"""A fused SAC update that computes what TorchRL's ``SACLoss`` + ``SoftUpdate`` compute, with less overhead.

Why: at the paper's (64, 64) sizes most of a TorchRL SAC update is Python and TensorDict bookkeeping, not
arithmetic (docs/performance.md). :class:`FusedSACUpdate` reads the *same parameter objects* the ``SACLoss``
holds (actor, stacked Q ensemble, target Q ensemble, ``log_alpha``) and runs the three SAC losses on plain
tensors: the Q ensemble as batched matmuls (one ``bmm`` per layer for all critics), the target update as one
``torch._foreach_lerp_``. Because it shares the parameters, :class:`~adarl.adapter.RankAdapter` keeps
working: it resizes ``.data`` in place and pops the optimiser state, and :meth:`FusedSACUpdate.on_rank_event`
(registered as an ``on_truncate`` callback) rebuilds the compiled function so each rank event costs exactly
one recompilation, never a silent fall-back to eager.

The Gaussian noise of the two reparameterised samples is drawn eagerly, in the order ``SACLoss`` draws it
(next state first, then current state), so with the same RNG state both paths compute the same losses.
"""

from __future__ import annotations

import math
import types
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.nn import functional as F

from adarl.errors import AdaRLValueError
from adarl.lowrank import LowRankLinear

__all__ = ["BACKWARDS", "FusedSACUpdate", "compile_fresh", "make_adam", "supported_activation", "wants_fused"]

#: values of ``FusedSACUpdate(backward=...)`` / ``algorithm.backward``
BACKWARDS = ("auto", "manual", "autograd")

_ACTIVATIONS = (nn.ReLU, nn.Tanh, nn.Softplus, nn.ELU, nn.GELU, nn.SiLU, nn.LeakyReLU)


def supported_activation(module: nn.Module) -> bool:
    """Whether a stateless activation module can run inside the fused ensemble forward."""
    return isinstance(module, _ACTIVATIONS)


def make_adam(params: Sequence[torch.Tensor], lr: float, *, fused: bool) -> torch.optim.Adam:
    """Adam, fused into one kernel per step when ``fused`` (same maths as the for-loop Adam, fp tolerance)."""
    if fused:
        return torch.optim.Adam(list(params), lr=lr, fused=True)
    return torch.optim.Adam(list(params), lr=lr)


class DirectAdamStep:
    """``opt.step(); opt.zero_grad(set_to_none=True)`` of a fused ``torch.optim.Adam``, without its per-call Python.

    Why: at (64, 64) the three optimisers' ``step()`` took ~0.55 ms of a ~4.6 ms update, nearly all of it Python
    (grouping tensors, state look-ups, hooks, the profiler wrapper); the fused kernel itself is tens of
    microseconds. This calls the very kernels ``Adam(fused=True)`` calls (``torch._foreach_add_`` on the step
    counters, then ``torch._fused_adam_``) on lists cached from ``opt.state``, with the group's current
    hyper-parameters, so the result is bit-identical (tested). It falls back to ``opt.step()`` whenever an
    assumption does not hold: state not created yet or replaced (first step, a rank event popping a factor's
    state, ``load_state_dict``), a missing gradient, hooks, several parameter groups, or options other than
    plain fused Adam (amsgrad, capturable, differentiable, decoupled weight decay).
    """

    def __init__(self, opt: torch.optim.Optimizer) -> None:
        self.opt = opt
        self._cache: tuple | None = None
        self.fast_steps = 0  # steps taken by the direct path (the rest went through opt.step())

    def _hooked(self) -> bool:
        from torch.optim import optimizer as optim_mod

        o = self.opt
        return bool(o._optimizer_step_pre_hooks or o._optimizer_step_post_hooks or
                    optim_mod._global_optimizer_pre_hooks or optim_mod._global_optimizer_post_hooks)

    def _supported(self) -> bool:
        o = self.opt
        if not isinstance(o, torch.optim.Adam) or len(o.param_groups) != 1:
            return False
        g = o.param_groups[0]
        return bool(g.get("fused")) and not g.get("amsgrad") and not g.get("capturable") \
            and not g.get("differentiable") and not g.get("decoupled_weight_decay")

    def _build_cache(self) -> tuple | None:
        params = self.opt.param_groups[0]["params"]
        states = [self.opt.state.get(p) for p in params]
        if any(st is None or "exp_avg" not in st for st in states):
            return None
        if len({(p.device, p.dtype) for p in params}) != 1:
            return None
        return (params, list(params), states, [st["exp_avg"] for st in states],
                [st["exp_avg_sq"] for st in states], [st["step"] for st in states])

    def _valid(self, cache) -> bool:
        params, plist, states, avgs, sqs, steps = cache
        state = self.opt.state
        if self.opt.param_groups[0]["params"] is not params or len(params) != len(plist):
            return False
        for p, q, st, a, b, c in zip(params, plist, states, avgs, sqs, steps):
            if p is not q or p.grad is None:
                return False
            got = state.get(p)
            if got is not st or got.get("exp_avg") is not a or got.get("exp_avg_sq") is not b or got.get("step") is not c:
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
        _, plist, _, avgs, sqs, steps = cache
        g = self.opt.param_groups[0]
        beta1, beta2 = g["betas"]
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(plist, [p.grad for p in plist], avgs, sqs, [], steps, amsgrad=False, lr=g["lr"],
                           beta1=float(beta1), beta2=float(beta2), weight_decay=g["weight_decay"], eps=g["eps"],
                           maximize=g["maximize"], grad_scale=None, found_inf=None)
        for p in plist:
            p.grad = None
        self.fast_steps += 1


def compile_fresh(function, owner, name: str, backend: str):
    """``torch.compile`` of ``function`` bound to ``owner``, from a fresh copy of its code object.

    Why: a fresh code object has a fresh dynamo cache, so rebuilding at each rank event compiles exactly once per
    event and dynamo's recompile limit (8 by default) is never reached: no silent fall-back to eager."""
    fresh = types.FunctionType(function.__code__.replace(), function.__globals__, name)
    return torch.compile(types.MethodType(fresh, owner), backend=backend, fullgraph=True, dynamic=False)


def wants_fused(setting, loss) -> bool:
    """Resolve ``algorithm.fused``: ``'auto'`` is on for a continuous ``SACLoss``; ``True`` insists (clear error)."""
    from torchrl.objectives import SACLoss

    if setting == "auto":
        return type(loss) is SACLoss
    if setting is True and type(loss) is not SACLoss:
        raise AdaRLValueError(f"algorithm.fused: true needs a continuous-action SACLoss, got {type(loss).__name__}; "
                              "allowed for discrete actions: 'auto' or false")
    return bool(setting)


def _mlp_layers(net: nn.Module, what: str) -> list[nn.Module]:
    layers = list(net.children()) if isinstance(net, nn.Sequential) else [net]
    for layer in layers:
        if not isinstance(layer, (nn.Linear, LowRankLinear)) and not supported_activation(layer):
            raise AdaRLValueError(
                f"the fused SAC update supports {what} MLPs of Linear, LowRankLinear and activation layers; "
                f"found {type(layer).__name__} (set algorithm.fused: false to use TorchRL's SACLoss)"
            )
    return layers


class _StackedMLP:
    """Forward of an ensemble MLP whose parameters are stacked ``[N, ...]`` tensors (the SACLoss layout)."""

    def __init__(self, net: nn.Module, params: dict[str, torch.Tensor], prefix: str = "module",
                 what: str = "critic") -> None:
        self.layers: list[tuple[str, object]] = []
        for i, layer in enumerate(_mlp_layers(net, what)):
            key = f"{prefix}.{i}"
            if isinstance(layer, LowRankLinear):
                self.layers.append(("lowrank", (key + ".w1", key + ".w2", key + ".bias" if layer.bias is not None else None)))
            elif isinstance(layer, nn.Linear):
                self.layers.append(("linear", (key + ".weight", key + ".bias" if layer.bias is not None else None)))
            else:
                self.layers.append(("act", layer))
        missing = [k for kind, ks in self.layers if kind != "act" for k in ks if k is not None and k not in params]
        if missing:
            raise AdaRLValueError(f"fused SAC update: Q parameters {missing} not found in the loss's parameters")

    def prepare(self, params: dict[str, torch.Tensor], rows: int) -> list[tuple]:
        """Per layer ``(kind, weight(s), bias)`` for :meth:`forward`; merges ``W1 W2`` once where that is cheaper.

        Why: one update runs the same weights on several batches (the actor on the current and the next
        states, the critics for the critic loss and, detached, for the actor loss). Merging a near-full-rank
        product once per update instead of once per forward saves one ``out x r x in`` product per reuse."""
        out = []
        for kind, spec in self.layers:
            if kind == "act":
                out.append(("act", spec, None))
            elif kind == "linear":
                out.append(("linear", params[spec[0]], params[spec[1]] if spec[1] is not None else None))
            else:
                w1, w2 = params[spec[0]], params[spec[1]]
                b = params[spec[2]] if spec[2] is not None else None
                out_f, r, in_f = w1.shape[-2], w1.shape[-1], w2.shape[-1]
                if out_f * r * in_f + rows * in_f * out_f < rows * r * (in_f + out_f):
                    out.append(("linear", torch.matmul(w1, w2), b))
                else:
                    out.append(("lowrank", (w1, w2), b))
        return out

    @staticmethod
    def detached(prepared: list[tuple]) -> list[tuple]:
        """The same layers with every tensor detached (the critics inside the actor loss)."""
        def d(t):
            return None if t is None else tuple(x.detach() for x in t) if isinstance(t, tuple) else t.detach()
        return [(k, w if k == "act" else d(w), d(b)) for k, w, b in prepared]

    @staticmethod
    def forward(prepared: list[tuple], x: torch.Tensor) -> torch.Tensor:
        """``x`` is ``[B, in]`` (shared by all critics) or ``[N, B, in]``; returns ``[N, B, out]``."""
        for kind, w, b in prepared:
            if kind == "act":
                x = w(x)
                continue
            if kind == "linear":
                x = _affine(x, w.transpose(-1, -2), b)
            else:
                x = _affine(torch.matmul(x, w[1].transpose(-1, -2)), w[0].transpose(-1, -2), b)
        return x


def _affine(x: torch.Tensor, w_t: torch.Tensor, b: torch.Tensor | None) -> torch.Tensor:
    """``x @ w_t + b`` with the bias added inside the matmul kernel (``addmm``/``baddbmm``): one operation, and
    one autograd node, instead of three (matmul, unsqueeze, add); at (64, 64) the update is op-count bound.

    ``w_t`` is ``[in, out]`` (actor) or ``[N, in, out]`` (stacked critics, ``x`` then ``[B, in]`` or ``[N, B, in]``).
    """
    if b is None:
        return torch.matmul(x, w_t)
    if w_t.dim() == 2 and x.dim() == 2:
        return torch.addmm(b, x, w_t)
    if w_t.dim() == 3 and x.dim() in (2, 3):
        if x.dim() == 2:
            x = x.expand(w_t.shape[0], *x.shape)
        return torch.baddbmm(b.unsqueeze(-2), x, w_t)
    return torch.matmul(x, w_t) + b.unsqueeze(-2)


def _actor_net(loss) -> nn.Module:
    """The module mapping observation -> (loc, scale) inside a TorchRL ``ProbabilisticActor``."""
    actor = loss.actor_network
    first = actor.module[0] if hasattr(actor, "module") and isinstance(actor.module, nn.ModuleList) else None
    net = getattr(first, "module", None)
    if net is None or list(first.in_keys) != ["observation"] or list(first.out_keys) != ["loc", "scale"]:
        raise AdaRLValueError("the fused SAC update needs an actor built by adarl.builders.make_sac_actor "
                              "(observation -> loc, scale -> TanhNormal)")
    from tensordict.nn import NormalParamExtractor

    if not (isinstance(net, nn.Sequential) and len(net) == 2 and isinstance(net[1], NormalParamExtractor)):
        raise AdaRLValueError("the fused SAC update needs the actor network Sequential(MLP, NormalParamExtractor) "
                              "that adarl.builders.make_sac_actor builds (set algorithm.fused: false otherwise)")
    _mlp_layers(net[0], "actor")
    return net


class FusedSACUpdate:
    """One SAC optimisation step (losses, backward, optimisers, LR schedules, Polyak update) on ``loss``'s tensors.

    Args:
        loss: a continuous-action TorchRL ``SACLoss`` with the TD(0) estimator (as :func:`adarl.builders.make_sac_loss`).
        optimizers: optimisers over the loss's parameters (``make_adam(..., fused=True)`` for fused Adam).
        schedulers: LR schedulers stepped after the optimisers.
        tau: Polyak rate of the target critics (``SoftUpdate(loss, tau=tau)`` does the same).
        max_grad_norm: per-optimiser gradient clipping as in the plain loop; ``None`` = none.
        compile: ``torch.compile`` the update's computation (the manual step, or the autograd path's losses); one
            recompilation per rank event.
        compile_backend: backend passed to ``torch.compile`` (``"inductor"``; ``"aot_eager"`` for tests).
        backward: ``"manual"``: the losses and gradients written out by hand (:mod:`adarl.manual_backward`:
            fewer operations, no autograd graph); ``"autograd"``: the losses as plain tensor code and
            ``loss.backward()``; ``"auto"``: manual unless a network the manual backward does not know (see
            :func:`adarl.manual_backward.unsupported_reason`). ``compile`` compiles whichever is used.
    """

    def __init__(self, loss, optimizers: Sequence[torch.optim.Optimizer], *, tau: float,
                 schedulers: Sequence = (), max_grad_norm: float | None = None, compile: bool = False,
                 compile_backend: str = "inductor", backward: str = "auto") -> None:
        from torchrl.objectives import SACLoss

        if type(loss) is not SACLoss:
            raise AdaRLValueError(f"the fused SAC update needs a continuous-action SACLoss, got {type(loss).__name__} "
                                  "(set algorithm.fused: false)")
        if getattr(loss, "_version", 2) != 2:
            raise AdaRLValueError("the fused SAC update implements SAC v2 (no value network)")
        if loss.loss_function not in ("l2", "smooth_l1", "l1"):
            raise AdaRLValueError(f"unknown loss_function {loss.loss_function!r}")
        if not 0 < tau <= 1:
            raise AdaRLValueError(f"tau must be in (0, 1], got {tau}")
        self.loss = loss
        self.optimizers = list(optimizers)
        # Adam(fused=True).step() + zero_grad() without their Python overhead (same kernels, falls back by itself)
        self._adam_steps = [DirectAdamStep(o) for o in self.optimizers]
        self.schedulers = list(schedulers)
        self.tau = float(tau)
        self.max_grad_norm = max_grad_norm
        self.gamma = float(loss.value_estimator.gamma)
        self.loss_function = loss.loss_function
        self.target_entropy = float(loss.target_entropy)
        self.min_log_alpha, self.max_log_alpha = loss.min_log_alpha, loss.max_log_alpha
        self.actor_net = _actor_net(loss)
        mlp, self._param_extractor = self.actor_net[0], self.actor_net[1]
        self.actor_params = dict(mlp.named_parameters(prefix="module"))
        self.actor_mlp = _StackedMLP(mlp, self.actor_params, what="actor")
        spec = loss.actor_network.module[1]
        kw = getattr(spec, "distribution_kwargs", {}) or {}
        low, high = kw.get("low", -1.0), kw.get("high", 1.0)
        low, high = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
        self._affine = bool((low != -1).any() or (high != 1).any())
        self._mid, self._half = (high + low) / 2, (high - low) / 2
        self._log_half_sum = torch.log(self._half).expand_as(torch.empty(low.shape)).sum() if self._affine else None
        self.q_params = dict(loss.qvalue_network_params.flatten_keys().items())
        self.target_q_params = dict(loss.target_qvalue_network_params.flatten_keys().items())
        self.q_net = _StackedMLP(loss.qvalue_network.module, self.q_params)
        keys = list(self.q_params)
        self._q_sources = [self.q_params[k] for k in keys]
        self._q_targets = [self.target_q_params[k] for k in keys]
        self.compile = compile
        self.compile_backend = compile_backend
        self._compilations = 0
        self.backward = self._resolve_backward(backward)
        self._manual = None
        if self.backward == "manual":
            from adarl.manual_backward import ManualSACStep

            self._manual = ManualSACStep(self, compile=compile, compile_backend=compile_backend)
            self._fn = None
        else:
            self._fn = self._build()

    @property
    def compilations(self) -> int:
        """How many times the update was compiled (the first build plus one per rank event)."""
        return self._manual.compilations if self._manual is not None else self._compilations

    def _resolve_backward(self, setting: str) -> str:
        from adarl.manual_backward import unsupported_reason

        if setting not in BACKWARDS:
            raise AdaRLValueError(f"backward must be one of {BACKWARDS}, got {setting!r}")
        reason = unsupported_reason(self)
        if setting == "manual" and reason is not None:
            raise AdaRLValueError(f"backward='manual' does not support the {reason}; allowed here: 'auto' or "
                                  "'autograd'")
        if setting == "auto":
            return "autograd" if reason is not None else "manual"
        return setting

    # ------------------------------------------------------------------ the maths
    def _sample(self, actor: list[tuple], obs: torch.Tensor,
                noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised TanhNormal sample and its log-probability, scored at the exact pre-tanh value."""
        from torchrl.modules.distributions.utils import safetanh_noeps

        loc, scale = self._param_extractor(_StackedMLP.forward(actor, obs))
        pre = loc + noise * scale
        action = safetanh_noeps(pre)
        log_prob = (-0.5 * noise.pow(2) - scale.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))).sum(-1)
        if self._affine:
            action = action * self._half + self._mid
            log_prob = log_prob - self._log_half_sum
        return action, log_prob

    def _distance(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        if self.loss_function == "l2":
            return F.mse_loss(pred, target, reduction="none")
        if self.loss_function == "l1":
            return F.l1_loss(pred, target, reduction="none")
        return F.smooth_l1_loss(pred, target, reduction="none")

    def losses(self, obs, action, reward, next_obs, terminated, noise_next, noise_now):
        """SAC v2 losses ``(loss_actor, loss_qvalue, loss_alpha, alpha, entropy)``, as ``SACLoss.forward``."""
        log_alpha = self.loss.log_alpha
        alpha = log_alpha.detach().exp()
        rows = obs.shape[-2]
        actor = self.actor_mlp.prepare(self.actor_params, rows)  # shared by both actor passes
        critic = self.q_net.prepare(self.q_params, rows)  # shared (detached) by the actor loss
        with torch.no_grad():
            next_action, next_logp = self._sample(actor, next_obs, noise_next)
            target_q = self.q_net.prepare(self.target_q_params, rows)
            q_next = _StackedMLP.forward(target_q, torch.cat([next_obs, next_action], -1))  # [N, B, 1]
            next_value = (q_next - alpha * next_logp.unsqueeze(-1)).min(0)[0]
            target = (reward + self.gamma * (~terminated).to(reward.dtype) * next_value).squeeze(-1)
        pred = _StackedMLP.forward(critic, torch.cat([obs, action], -1)).squeeze(-1)  # [N, B]
        loss_q = self._distance(pred, target.expand_as(pred)).sum(0).mean()
        new_action, logp = self._sample(actor, obs, noise_now)
        q_new = _StackedMLP.forward(_StackedMLP.detached(critic), torch.cat([obs, new_action], -1))
        q_new = q_new.min(0)[0].squeeze(-1)
        loss_actor = (alpha * logp - q_new).mean()
        logp_d = logp.detach()
        loss_alpha = (-log_alpha * (logp_d + self.target_entropy)).mean()
        return loss_actor, loss_q, loss_alpha, alpha, -logp_d.mean()

    def _build(self):
        if not self.compile:
            return self.losses
        self._compilations += 1
        return compile_fresh(FusedSACUpdate.losses, self, "fused_sac_losses", self.compile_backend)

    def on_rank_event(self, event=None) -> None:
        """Re-bind after a rank event (the adapter resized ``.data`` in place): rebuild the compiled function."""
        if self._manual is not None:
            self._manual.on_rank_event(event)
        elif self.compile:
            self._fn = self._build()

    # ------------------------------------------------------------------ one step
    @staticmethod
    def batch_tensors(batch: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """The five tensors an update reads from a replay sample."""
        return (batch.get("observation"), batch.get("action"), batch.get(("next", "reward")),
                batch.get(("next", "observation")), batch.get(("next", "terminated")))

    def draw_noise(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Standard-normal noise for the next-state and current-state samples, in SACLoss's order."""
        shape = (*obs.shape[:-1], action.shape[-1])
        return torch.randn(shape, dtype=obs.dtype), torch.randn(shape, dtype=obs.dtype)

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        return self.step(*self.batch_tensors(batch))

    def step(self, obs: torch.Tensor, action: torch.Tensor, reward: torch.Tensor, next_obs: torch.Tensor,
             terminated: torch.Tensor) -> dict[str, torch.Tensor]:
        """One update from the five tensors of :meth:`batch_tensors` (e.g. from a
        :class:`~adarl.fast_replay.UniformTensorSampler`)."""
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            self.loss.log_alpha.data.clamp_(self.min_log_alpha, self.max_log_alpha)
        noise_next, noise_now = self.draw_noise(obs, action)
        args = (obs, action, reward, next_obs, terminated.bool(), noise_next, noise_now)
        if self._manual is not None:  # fills the parameters' .grad itself
            loss_actor, loss_q, loss_alpha, alpha, entropy = self._manual(*args)
        else:
            loss_actor, loss_q, loss_alpha, alpha, entropy = self._fn(*args)
            (loss_actor + loss_q + loss_alpha).backward()
        if self.max_grad_norm is not None:
            for opt in self.optimizers:
                for group in opt.param_groups:
                    torch.nn.utils.clip_grad_norm_(group["params"], self.max_grad_norm)
        for opt in self._adam_steps:
            opt.step()
        for sched in self.schedulers:
            sched.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._q_targets, self._q_sources, self.tau)
        return {"loss_actor": loss_actor.detach(), "loss_qvalue": loss_q.detach(),
                "loss_alpha": loss_alpha.detach(), "alpha": alpha, "entropy": entropy}

    #: keys of a replay sample that :meth:`step` reads, in its argument order
    KEYS = ("observation", "action", ("next", "reward"), ("next", "observation"), ("next", "terminated"))
