"""The fused SAC step with a hand-written backward: the gradients autograd would compute, without its graph.

Why: at the paper's (64, 64) sizes the fused update is bound by the number of operations, not by arithmetic
(docs/performance.md): autograd records one node per operation and walks them one by one, and each of the four
network passes of an update runs on its own. Written out by hand, the step needs fewer operations (698 ATen calls
per (64, 64) update against 914 with autograd, measured) and builds no graph:

- the actor runs once on the next and the current states stacked (``2B`` rows); only the current rows are
  back-propagated (the next-state sample is detached in ``SACLoss`` too);
- the critics run once on ``(s, a)`` and ``(s, a~pi(s))`` stacked; one backward pass gives the critic loss's
  parameter gradients from the first ``B`` rows and the actor loss's action gradient from the last ``B`` rows
  (the critics get no parameter gradient from the actor loss: ``SACLoss`` detaches them there);
- every local derivative is the ATen backward kernel autograd itself calls (``threshold_backward``,
  ``softplus_backward``, ...), and a low-rank product ``W1 W2`` gets ``dW1 = dW W2^T``, ``dW2 = W1^T dW``.

The gradients land in ``p.grad``, as ``loss.backward()`` leaves them, so clipping, (direct) fused Adam and the
rank adapter work unchanged. Used by :class:`~adarl.fast.sac.FusedSACUpdate` (``backward="manual"``).

Mirrors: the gradients ``(loss_actor + loss_qvalue + loss_alpha).backward()`` leaves on a
``torchrl.objectives.SACLoss``. Equality: ``tests/test_fast_sac.py::test_losses_and_gradients_match_sacloss`` (losses
and gradients against ``SACLoss``, and the autograd path's, over activations, critic losses, action boxes and truncated
ranks), within fp tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
from tensordict.nn.utils import biased_softplus
from torch import nn
from torch.nn import functional as F

from adarl.errors import AdaRLValueError
from adarl.fast import _torch_private as private
from adarl.fast.kernels import affine, compile_fresh

__all__ = ["ManualSACStep", "unsupported_reason"]


def _activation_backward(module: nn.Module):
    """``(grad, input, output) -> grad_input`` for a stateless activation, with autograd's own kernel; or None."""
    aten = private.aten
    if isinstance(module, nn.ReLU):
        return lambda g, x, y: aten.threshold_backward(g, y, 0)
    if isinstance(module, nn.Tanh):
        return lambda g, x, y: aten.tanh_backward(g, y)
    if isinstance(module, nn.Softplus):
        return lambda g, x, y: aten.softplus_backward(g, x, module.beta, module.threshold)
    if isinstance(module, nn.ELU):
        return lambda g, x, y: aten.elu_backward(g, module.alpha, 1, 1, False, x)
    if isinstance(module, nn.GELU):
        return lambda g, x, y: aten.gelu_backward(g, x, approximate=module.approximate)
    if isinstance(module, nn.SiLU):
        return lambda g, x, y: aten.silu_backward(g, x)
    if isinstance(module, nn.LeakyReLU):
        return lambda g, x, y: aten.leaky_relu_backward(g, x, module.negative_slope, False)
    return None


def unsupported_reason(update) -> str | None:
    """Why a :class:`~adarl.fast.sac.FusedSACUpdate` cannot use the manual backward (None: it can)."""
    if not private.usable():  # its ATen backward kernels are torch-private
        return f"torch {torch.__version__} (its ATen backward kernels are checked on torch {', '.join(private.TESTED)})"
    for what, mlp in (("actor", update.actor_mlp), ("critic", update.q_net)):
        for kind, spec in mlp.layers:
            if kind == "kernel":
                return f"{what} layer {spec[3]} (a layer with its own kernel; the autograd backward runs it)"
            if kind == "act" and (getattr(spec, "inplace", False) or _activation_backward(spec) is None):
                return (
                    f"{what} activation {type(spec).__name__} (supported: ReLU, Tanh, Softplus, ELU, GELU, SiLU, "
                    "LeakyReLU, not in place)"
                )
    ext = update._param_extractor
    if not isinstance(ext.scale_mapping, biased_softplus):
        return f"scale mapping {type(ext.scale_mapping).__name__} (supported: biased_softplus, the default)"
    return None


def _merge_is_cheaper(out_f: int, r: int, in_f: int, rows: int, grad_rows: int, back_rows: int) -> bool:
    """Whether merging ``W = W1 W2`` once costs fewer multiply-adds than keeping the factors, for ``rows`` forward
    rows, parameter gradients from ``grad_rows`` rows and ``back_rows`` rows back-propagated through the layer."""
    merged = out_f * r * in_f * (3 if grad_rows else 1) + (rows + grad_rows + back_rows) * out_f * in_f
    factored = (rows + grad_rows) * r * (in_f + out_f) + max(back_rows, grad_rows) * r * out_f + back_rows * r * in_f
    return merged < factored


class _Layer(NamedTuple):
    """One layer of a manual pass."""

    kind: str  # "act" | "dense" | "merged" | "factored"
    weight: Any  # the (merged) weight, the factors (W1, W2) when factored, or the activation module
    bias: torch.Tensor | None
    keys: tuple  # names of the gradients: (W,) or (W1, W2), then the bias's (None when there is none)
    factors: tuple = ()  # (W1, W2) of a merged product: their gradients need them
    act_backward: Callable | None = None  # (grad, input, output) -> grad input, for "act"


class _Net:
    """One MLP (the actor, or a stacked ``[N, ...]`` critic ensemble) whose passes are written out by hand."""

    def __init__(self, name: str, mlp, params: dict[str, torch.Tensor]) -> None:
        self.name, self.params = name, params
        # per layer: (kind, activation module or parameter names, gradient keys), fixed for the update's life
        self.layers = []
        for kind, spec in mlp.layers:
            if kind == "act":
                self.layers.append((kind, spec, _activation_backward(spec)))
            else:
                keys = tuple(None if k is None else f"{name}:{k}" for k in spec)
                self.layers.append((kind, spec, keys))

    def prepare(self, rows: int, grad_rows: int, back_rows: int) -> list[_Layer]:
        """The layers for one update; a low-rank product is merged once where that is cheaper (see
        :func:`_merge_is_cheaper`), else kept factored."""
        p, out = self.params, []
        for kind, spec, extra in self.layers:
            if kind == "act":
                out.append(_Layer("act", spec, None, (), act_backward=extra))
                continue
            b = None if spec[-1] is None else p[spec[-1]]
            if kind == "linear":
                out.append(_Layer("dense", p[spec[0]], b, extra))
                continue
            w1, w2 = p[spec[0]], p[spec[1]]
            if _merge_is_cheaper(w1.shape[-2], w1.shape[-1], w2.shape[-1], rows, grad_rows, back_rows):
                out.append(_Layer("merged", _mm(w1, w2), b, extra, (w1, w2)))
            else:
                out.append(_Layer("factored", (w1, w2), b, extra))
        return out


def forward(layers: list[_Layer], x: torch.Tensor) -> tuple[torch.Tensor, list]:
    """The MLP's output and, per layer, what its backward needs: ``(input, bottleneck or activation output)``."""
    saved = []
    for layer in layers:
        if layer.kind == "act":
            y = layer.weight(x)
            saved.append((x, y))
            x = y
        elif layer.kind == "factored":
            h = _mm(x, layer.weight[1].transpose(-1, -2))
            saved.append((x, h))
            x = affine(h, layer.weight[0].transpose(-1, -2), layer.bias)
        else:
            saved.append((x, None))
            x = affine(x, layer.weight.transpose(-1, -2), layer.bias)
    return x, saved


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` as one ``mm``/``bmm`` call (``torch.matmul`` adds several view and reshape operations per call, and
    at (64, 64) the step is bound by the number of operations); a shared 2-D operand is expanded over the batch."""
    if a.dim() == b.dim() == 2:
        return torch.mm(a, b)
    if a.dim() == b.dim() == 3:
        return torch.bmm(a, b)
    if a.dim() == 2 and b.dim() == 3:
        return torch.bmm(a.expand(b.shape[0], *a.shape), b)
    if a.dim() == 3 and b.dim() == 2:
        return torch.bmm(a, b.expand(a.shape[0], *b.shape))
    return torch.matmul(a, b)


def _rows(t: torch.Tensor, rows: slice) -> torch.Tensor:
    """Rows ``rows`` (a ``slice(start, stop)`` or ``slice(None)``) of ``t`` along its second-to-last dimension."""
    if rows.start is None and rows.stop is None:
        return t
    return t.narrow(-2, rows.start, rows.stop - rows.start)


def _add(grads: dict[str, torch.Tensor], key: str, g: torch.Tensor) -> None:
    grads[key] = g if key not in grads else grads[key] + g


def _param_grad(dy: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``sum_rows dy^T x`` for ``dy`` ``[(N,) R, out]`` and ``x`` ``[(N,) R, in]`` (``x`` may be shared ``[R, in]``)."""
    return _mm(dy.transpose(-1, -2), x)


def backward(
    grads: dict[str, torch.Tensor],
    layers: list[_Layer],
    saved: list,
    dy: torch.Tensor,
    *,
    rows: slice,
    grad_rows: slice | None,
    input_rows: slice | None = None,
    input_cols: slice | None = None,
) -> torch.Tensor | None:
    """Back-propagate ``dy``, the gradient at the output for the forward rows ``rows``, through the layers.

    Parameter gradients come from the rows ``grad_rows`` of ``dy`` (None: none) and are added to ``grads`` under
    the layers' keys. Returns the gradient at the input for ``dy``'s rows ``input_rows`` and the input columns
    ``input_cols`` (summed over a critic ensemble that shares its input), or None."""
    for i in range(len(layers) - 1, -1, -1):
        layer = layers[i]
        x, h = (None if t is None else _rows(t, rows) for t in saved[i])
        if layer.kind == "act":
            dy = layer.act_backward(dy, x, h)
            continue
        w = layer.weight
        if grad_rows is not None:
            dyg, xg = _rows(dy, grad_rows), _rows(x, grad_rows)
            if layer.bias is not None:
                _add(grads, layer.keys[-1], dyg.sum(-2))
            if layer.kind == "dense":
                _add(grads, layer.keys[0], _param_grad(dyg, xg))
            elif layer.kind == "merged":
                gw = _param_grad(dyg, xg)
                w1, w2 = layer.factors
                _add(grads, layer.keys[0], _mm(gw, w2.transpose(-1, -2)))
                _add(grads, layer.keys[1], _mm(w1.transpose(-1, -2), gw))
            else:
                _add(grads, layer.keys[0], _param_grad(dyg, _rows(h, grad_rows)))
        if layer.kind == "factored":
            dy = _mm(dy, w[0])  # the gradient at the bottleneck
            if grad_rows is not None:
                _add(grads, layer.keys[1], _param_grad(_rows(dy, grad_rows), xg))
            w = w[1]
        if i == 0:
            if input_rows is None:
                return None
            dy, w = _rows(dy, input_rows), (w if input_cols is None else w[..., input_cols])
        dy = _mm(dy, w)
    if dy.dim() == 3 and saved[0][0].dim() == 2:  # an ensemble that shares its input: the gradients add up
        dy = dy.sum(0)
    return dy


class ManualSACStep:
    """The losses and gradients of one SAC v2 step for a :class:`~adarl.fast.sac.FusedSACUpdate`, by hand.

    Call it with the update's seven tensors (as ``FusedSACUpdate.losses``); it adds the gradients to ``.grad`` of
    the actor, critic and ``log_alpha`` parameters (as ``backward()`` would) and returns ``(loss_actor,
    loss_qvalue, loss_alpha, alpha, entropy)``. With ``compile`` the computation is one ``torch.compile``d
    function without autograd, rebuilt by :meth:`on_rank_event` (one compilation per event).
    """

    def __init__(self, update, *, compile: bool = False, compile_backend: str = "inductor") -> None:
        reason = unsupported_reason(update)
        if reason is not None:
            raise AdaRLValueError(f"the manual backward does not support the {reason}; use backward='autograd'")
        self.u = update
        self.actor = _Net("actor", update.actor_mlp, update.actor_params)
        self.critic = _Net("critic", update.q_net, update.q_params)
        self.target = _Net("target", update.q_net, update.target_q_params)
        self._by_key = {f"{net.name}:{k}": p for net in (self.actor, self.critic) for k, p in net.params.items()}
        self._by_key["log_alpha"] = update.loss.log_alpha
        ext = update._param_extractor
        self._sp_bias, self._sp_min = float(ext.scale_mapping.bias), float(ext.scale_mapping.min_val)
        self._scale_lb = float(ext.scale_lb)
        self.compile, self.compile_backend, self.compilations = compile, compile_backend, 0
        self._fn = self._build()

    def _build(self):
        if not self.compile:
            return self.compute
        self.compilations += 1  # one per build: the first and one per rank event (see compile_fresh)
        return compile_fresh(ManualSACStep.compute, self, "manual_sac_step", self.compile_backend)

    def on_rank_event(self, event=None) -> None:
        """Shapes changed (the adapter resized ``.data`` in place): rebuild the compiled function."""
        if self.compile:
            self._fn = self._build()

    # ------------------------------------------------------------------ the TanhNormal sample
    def _sample(self, out: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, tuple]:
        """Action and log-probability as ``FusedSACUpdate._sample`` computes them, and what the backward needs."""
        u = self.u
        loc, raw = out.chunk(2, -1)
        z = raw + self._sp_bias
        s0 = F.softplus(z) + self._sp_min
        scale = s0.clamp_min(self._scale_lb)
        pre = loc + noise * scale
        lim = 1.0 - torch.finfo(pre.dtype).resolution
        a = pre.tanh().clamp(-lim, lim)
        log_prob = (-0.5 * noise.pow(2) - scale.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        m2pre = -2.0 * pre
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre - F.softplus(m2pre))).sum(-1)
        action = a
        if u._affine:
            action = a * u._half + u._mid
            log_prob = log_prob - u._log_half_sum
        return action, log_prob, (z, s0, scale, a, m2pre, noise)

    def _sample_backward(self, saved: tuple, rows: slice, d_action: torch.Tensor, d_logp: torch.Tensor) -> torch.Tensor:
        """Gradient at the actor network's output (``loc``, raw scale) for the rows ``rows`` of a :meth:`_sample`."""
        aten = private.aten
        z, s0, scale, a, m2pre, noise = (_rows(t, rows) for t in saved)
        if self.u._affine:
            d_action = d_action * self.u._half
        d_pre = d_action * (1 - a.pow(2))  # safetanh's backward
        # log_prob's tanh correction -2 (log 2 - pre - softplus(-2 pre)): d/dpre = 2 - 4 softplus'(-2 pre)
        d_pre = d_pre + 2.0 * d_logp + aten.softplus_backward((-4.0 * d_logp).expand_as(m2pre), m2pre, 1.0, 20.0)
        d_scale = d_pre * noise - d_logp / scale
        d_s0 = torch.where(s0 >= self._scale_lb, d_scale, 0.0)  # clamp_min's backward
        d_raw = aten.softplus_backward(d_s0, z, 1.0, 20.0)
        return torch.cat([d_pre, d_raw], -1)

    def _distance_grad(self, pred: torch.Tensor, target: torch.Tensor, scale: float) -> torch.Tensor:
        diff = pred - target
        kind = self.u.loss_function
        if kind == "l2":
            return diff * (2.0 * scale)
        if kind == "l1":
            return diff.sign() * scale
        return diff.clamp(-1.0, 1.0) * scale  # smooth_l1, beta 1

    # ------------------------------------------------------------------ one step
    @torch.no_grad()
    def __call__(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        *out, grads = self._fn(*args)
        for key, g in grads.items():
            p = self._by_key[key]
            if p.grad is None:
                p.grad = g.contiguous()
            else:
                p.grad.add_(g)
        return tuple(out)

    def compute(self, obs, action, reward, next_obs, terminated, noise_next, noise_now):
        """The five outputs of :meth:`__call__` and the gradients by parameter key, without touching ``.grad``
        (call it under ``torch.no_grad()``)."""
        u = self.u
        log_alpha = u.loss.log_alpha
        alpha = log_alpha.detach().exp()
        b = obs.shape[-2]
        nxt, now = slice(0, b), slice(b, 2 * b)
        ds = obs.shape[-1]

        actor = self.actor.prepare(2 * b, b, b)
        a_out, a_saved = forward(actor, torch.cat([next_obs, obs]))
        act_all, logp_all, s_saved = self._sample(a_out, torch.cat([noise_next, noise_now]))
        next_action, new_action = act_all[nxt], act_all[now]
        next_logp, logp = logp_all[nxt], logp_all[now]

        target_q = self.target.prepare(b, 0, 0)
        q_next, _ = forward(target_q, torch.cat([next_obs, next_action], -1))  # [N, B, 1]
        next_value = (q_next - alpha * next_logp.unsqueeze(-1)).min(0)[0]
        target = (reward + u.gamma * (~terminated).to(reward.dtype) * next_value).squeeze(-1)

        critic = self.critic.prepare(2 * b, b, 2 * b)
        q_all, c_saved = forward(critic, torch.cat([torch.cat([obs, action], -1), torch.cat([obs, new_action], -1)]))
        q_all = q_all.squeeze(-1)  # [N, 2B]: the critic loss's predictions, then the actor loss's values
        pred, q_new = q_all[:, nxt], q_all[:, now]
        tgt = target.expand_as(pred)
        loss_q = u._distance(pred, tgt).sum(0).mean()
        q_min, q_idx = q_new.min(0)
        loss_actor = (alpha * logp - q_min).mean()
        loss_alpha = (-log_alpha.detach() * (logp + u.target_entropy)).mean()

        # critics: d loss_q / d pred on the first rows, d loss_actor / d q (the minimum's critic) on the last
        d_q = torch.zeros_like(q_new).scatter_(0, q_idx.unsqueeze(0), -1.0 / b)
        d_all = torch.cat([self._distance_grad(pred, tgt, 1.0 / b), d_q], -1).unsqueeze(-1)
        grads: dict[str, torch.Tensor] = {}
        d_new_action = backward(
            grads, critic, c_saved, d_all, rows=slice(None), grad_rows=nxt, input_rows=now, input_cols=slice(ds, None)
        )
        # actor: through the sample (current rows), then the network; alpha is a constant in the actor loss
        d_out = self._sample_backward(s_saved, now, d_new_action, alpha / b)
        backward(grads, actor, a_saved, d_out, rows=now, grad_rows=slice(None))
        grads["log_alpha"] = (-(logp + u.target_entropy).mean()).reshape(log_alpha.shape)
        return loss_actor, loss_q, loss_alpha, alpha, -logp.mean(), grads
