"""A fused SAC update that computes what TorchRL's ``SACLoss`` + ``SoftUpdate`` compute, with less overhead.

Mirrors: ``torchrl.objectives.SACLoss`` (v2, TD(0) value estimator, ``reduction="mean"``) followed by ``backward``,
the optimisers' steps and ``torchrl.objectives.SoftUpdate``.
Equality: ``tests/test_fast_sac.py::test_losses_and_gradients_match_sacloss`` (losses and gradients, parametrised
over activations, critic losses, action boxes and truncated ranks) and
``tests/test_fast_sac.py::test_full_step_matches_plain_step`` (parameters after whole steps),
``tests/test_fast_path_whole_run.py`` (a whole run through rank events, beside TorchRL's path); what it does not
implement is refused by name (``tests/test_fast_sac.py::test_fused_update_refuses_what_it_does_not_implement``).

Why: at the paper's (64, 64) sizes most of a TorchRL SAC update is Python and TensorDict bookkeeping, not
arithmetic (docs/performance.md). :class:`FusedSACUpdate` reads the *same parameter objects* the ``SACLoss``
holds (actor, stacked Q ensemble, target Q ensemble, ``log_alpha``) and runs the three SAC losses on plain
tensors: the Q ensemble as batched matmuls (one ``bmm`` per layer for all critics), the target update as one
``torch._foreach_lerp_`` (behind :mod:`adarl.fast._torch_private`'s version guard). Because it shares the
parameters, :class:`~adarl.core.adapter.RankAdapter` keeps working: it resizes ``.data`` in place and pops the
optimiser state, and :meth:`FusedSACUpdate.on_rank_event` (registered as an ``on_truncate`` callback) rebuilds the
compiled function so each rank event costs exactly one recompilation, never a silent fall-back to eager.

The Gaussian noise of the two reparameterised samples is drawn eagerly, in the order ``SACLoss`` draws it
(next state first, then current state), so with the same RNG state both paths compute the same losses. The
tensordict keys it reads are the loss's (``loss.tensor_keys``, the value estimator's ``tensor_keys`` and the
actor's ``in_keys``), as ``SACLoss`` reads them: :attr:`FusedSACUpdate.keys`.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import NormalParamExtractor
from torch import nn
from torch.nn import functional as F
from torchrl.modules import TanhNormal
from torchrl.modules.distributions.utils import safetanh_noeps
from torchrl.objectives import SACLoss
from torchrl.objectives.value import TD0Estimator

from adarl.core.lowrank import LowRankLinear
from adarl.core.product_polyak import factor_keys, factor_pairs, product_polyak_
from adarl.core.target_shift import TargetShiftSACLoss
from adarl.errors import AdaRLValueError
from adarl.fast import _torch_private as private
from adarl.fast.adam import DirectAdamStep
from adarl.fast.kernels import affine, compile_fresh
from adarl.fast.manual_backward import ManualSACStep, unsupported_reason

__all__ = [
    "BACKWARDS",
    "LOSS_FUNCTIONS",
    "FUSABLE_OVERRIDES",
    "FusedSACUpdate",
    "check_fusable",
    "check_fusable_terms",
    "fused_fallback_reason",
    "supported_activation",
    "wants_fused",
]

#: values of ``FusedSACUpdate(polyak=...)`` / ``algorithm.polyak``
POLYAK_MODES = ("factors", "product")

#: values of ``FusedSACUpdate(backward=...)`` / ``algorithm.backward``
BACKWARDS = ("auto", "manual", "autograd")

_ACTIVATIONS = (nn.ReLU, nn.Tanh, nn.Softplus, nn.ELU, nn.GELU, nn.SiLU, nn.LeakyReLU)


def supported_activation(module: nn.Module) -> bool:
    """Whether a stateless activation module can run inside the fused ensemble forward."""
    return isinstance(module, _ACTIVATIONS)


#: methods a :class:`~adarl.core.target_shift.TargetShiftSACLoss` subclass may define and keep the fused update
FUSABLE_OVERRIDES = frozenset({"__init__", "target_shift"})


def fused_fallback_reason(loss) -> str | None:
    """Why the fused update cannot compute ``loss`` as its own ``forward`` does (None: it can, as far as the loss
    class goes). It computes ``SACLoss`` exactly, and a :class:`~adarl.core.target_shift.TargetShiftSACLoss`
    subclass that overrides only :data:`FUSABLE_OVERRIDES` (its shift is applied to the reward)."""
    cls = type(loss)
    if cls is SACLoss or cls is TargetShiftSACLoss:
        return None
    if not isinstance(loss, SACLoss):
        return f"{cls.__name__} is not a continuous-action SACLoss"
    if not isinstance(loss, TargetShiftSACLoss):
        return (
            f"{cls.__name__} subclasses SACLoss, and the fused update computes SACLoss's own losses only (to keep it, "
            "change only the TD target: subclass adarl.TargetShiftSACLoss and override target_shift)"
        )
    # methods the subclasses define themselves (TorchRL re-wraps `forward` in every subclass: unwrap it first)
    extra = sorted(
        {
            name
            for klass in cls.__mro__[: cls.__mro__.index(TargetShiftSACLoss)]
            for name, value in vars(klass).items()
            if callable(value)
            and name not in FUSABLE_OVERRIDES
            and getattr(inspect.unwrap(value), "__qualname__", "").startswith(f"{klass.__qualname__}.")
        }
    )
    if extra:
        return (
            f"{cls.__name__} overrides {extra} besides target_shift, which the fused update does not run "
            f"(allowed overrides: {sorted(FUSABLE_OVERRIDES)})"
        )
    return None


def wants_fused(setting, loss) -> bool:
    """Resolve ``algorithm.fused``: ``'auto'`` is on for a loss the fused update computes exactly (a continuous
    ``SACLoss``, or a TD-target shift of one: :func:`fused_fallback_reason`); ``True`` insists (clear error)."""
    reason = fused_fallback_reason(loss)
    if setting == "auto":
        return reason is None
    if setting is True and reason is not None:
        raise AdaRLValueError(f"algorithm.fused: true cannot run this loss: {reason}; allowed: 'auto' or false")
    return bool(setting)


def fused_kernel(layer: nn.Module):
    """``layer.fused_kernel()`` (``(kernel(x, weight, bias), weight name, bias name)``, weight maybe stacked ``[N, out,
    in]``; e.g. the sparsification layer's), or None. Asked of the module: the speed engine sits below the baselines."""
    ask = getattr(layer, "fused_kernel", None)
    return ask() if callable(ask) else None


def _mlp_layers(net: nn.Module, what: str) -> list[nn.Module]:
    has_kernel = callable(getattr(net, "fused_kernel", None))
    layers = list(net.children()) if isinstance(net, nn.Sequential) and not has_kernel else [net]
    for layer in layers:
        if callable(getattr(layer, "fused_kernel", None)):
            if fused_kernel(layer) is None:
                raise AdaRLValueError(
                    f"the fused SAC update cannot compute the {what}'s {layer!r} (its fused_kernel() says None; "
                    "set algorithm.fused: false to use TorchRL's SACLoss)"
                )
        elif not isinstance(layer, (nn.Linear, LowRankLinear)) and not supported_activation(layer):
            raise AdaRLValueError(
                f"the fused SAC update supports {what} MLPs of Linear, LowRankLinear, activation layers and layers "
                f"with a fused_kernel() (the sparsification layer); found {type(layer).__name__} (set "
                "algorithm.fused: false to use TorchRL's SACLoss)"
            )
    return layers


class _StackedMLP:
    """Forward of an ensemble MLP whose parameters are stacked ``[N, ...]`` tensors (the SACLoss layout)."""

    def __init__(
        self, net: nn.Module, params: dict[str, torch.Tensor], prefix: str = "module", what: str = "critic"
    ) -> None:
        self.layers: list[tuple[str, object]] = []
        for i, layer in enumerate(_mlp_layers(net, what)):
            key = f"{prefix}.{i}"
            if isinstance(layer, LowRankLinear):
                self.layers.append(
                    ("lowrank", (key + ".w1", key + ".w2", key + ".bias" if layer.bias is not None else None))
                )
            elif (kernel := fused_kernel(layer)) is not None:  # e.g. the sparsification layer
                fn, weight, bias = kernel
                bias = None if bias is None else f"{key}.{bias}"
                self.layers.append(("kernel", (f"{key}.{weight}", bias, fn, type(layer).__name__)))
            elif isinstance(layer, nn.Linear):
                self.layers.append(("linear", (key + ".weight", key + ".bias" if layer.bias is not None else None)))
            else:
                self.layers.append(("act", layer))
        names = [ks[:2] if kind == "kernel" else ks for kind, ks in self.layers if kind != "act"]  # a kernel's: 2
        missing = [k for ks in names for k in ks if k is not None and k not in params]
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
            elif kind == "kernel":
                out.append(("kernel", (params[spec[0]], spec[2]), params[spec[1]] if spec[1] is not None else None))
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

        def d(t):  # a kernel layer's (weight, kernel) keeps its kernel
            if isinstance(t, tuple):
                return tuple(x.detach() if isinstance(x, torch.Tensor) else x for x in t)
            return None if t is None else t.detach()

        return [(k, w if k == "act" else d(w), d(b)) for k, w, b in prepared]

    @staticmethod
    def forward(prepared: list[tuple], x: torch.Tensor) -> torch.Tensor:
        """``x`` is ``[B, in]`` (shared by all critics) or ``[N, B, in]``; returns ``[N, B, out]``."""
        for kind, w, b in prepared:
            if kind == "act":
                x = w(x)
                continue
            if kind == "linear":
                x = affine(x, w.transpose(-1, -2), b)
            elif kind == "kernel":
                weight, kernel = w
                if weight.dim() == 3 and x.dim() == 2:  # the critics' first layer: one input for every critic
                    x = x.expand(weight.shape[0], *x.shape)
                x = kernel(x, weight, b)
            else:
                x = affine(torch.matmul(x, w[1].transpose(-1, -2)), w[0].transpose(-1, -2), b)
        return x


def _actor_net(loss) -> nn.Module:
    """The module mapping observation -> (loc, scale) inside a TorchRL ``ProbabilisticActor``."""
    actor = loss.actor_network
    first = actor.module[0] if hasattr(actor, "module") and isinstance(actor.module, nn.ModuleList) else None
    net = getattr(first, "module", None)
    if net is None or len(first.in_keys) != 1 or len(first.out_keys) != 2:
        raise AdaRLValueError(
            "the fused SAC update needs an actor built by adarl.runtime.builders.make_sac_actor "
            "(one observation key -> loc, scale -> TanhNormal)"
        )
    if not (isinstance(net, nn.Sequential) and len(net) == 2 and isinstance(net[1], NormalParamExtractor)):
        raise AdaRLValueError(
            "the fused SAC update needs the actor network Sequential(MLP, NormalParamExtractor) "
            "that adarl.runtime.builders.make_sac_actor builds (set algorithm.fused: false otherwise)"
        )
    _mlp_layers(net[0], "actor")
    return net


#: critic losses the fused update implements (``SACLoss(loss_function=...)``)
LOSS_FUNCTIONS = ("l2", "smooth_l1", "l1")


def _refuse(setting: str, why: str) -> AdaRLValueError:
    return AdaRLValueError(
        f"the fused SAC update does not implement {setting}: {why}; set algorithm.fused: false "
        "(TorchRL's SACLoss) or change the setting"
    )


def check_fusable(loss) -> tuple[NestedKey, ...]:
    """Refuse, by name, every ``SACLoss`` setting :class:`FusedSACUpdate` does not compute as ``SACLoss`` does;
    returns the keys it reads (see :attr:`FusedSACUpdate.keys`).

    Implemented: SAC v2 with the TD(0) value estimator (``average_rewards=False``), ``reduction="mean"``,
    ``loss_function`` in :data:`LOSS_FUNCTIONS`, ``skip_done_states=False``, a TanhNormal actor with its default
    ``tanh_loc=False`` and ``safe_tanh=True``, an actor reading one observation key and critics reading
    ``[observation, action]`` (the keys may have any names)."""
    reason = fused_fallback_reason(loss)
    if reason is not None:
        raise AdaRLValueError(f"the fused SAC update cannot run this loss: {reason} (set algorithm.fused: false)")
    if getattr(loss, "_version", 2) != 2:
        raise _refuse("SAC v1 (a value network)", "it computes SAC v2's losses")
    estimator = loss.value_estimator
    if type(estimator) is not TD0Estimator:
        raise _refuse(
            f"the value estimator {type(estimator).__name__}",
            "it computes TD(0) targets; allowed: loss.make_value_estimator(ValueEstimators.TD0, gamma=...)",
        )
    if getattr(estimator, "average_rewards", False):
        raise _refuse("TD0Estimator(average_rewards=True)", "it bootstraps on the raw rewards")
    if loss.reduction != "mean":
        raise _refuse(f"reduction={loss.reduction!r}", "it averages the losses over the batch; allowed: 'mean'")
    if loss.loss_function not in LOSS_FUNCTIONS:
        raise _refuse(f"loss_function={loss.loss_function!r}", f"allowed: {list(LOSS_FUNCTIONS)}")
    if getattr(loss, "skip_done_states", False):
        raise _refuse("skip_done_states=True", "it evaluates the next state of every transition")
    _actor_net(loss)
    dist = loss.actor_network.module[1]
    kw = getattr(dist, "distribution_kwargs", {}) or {}
    if getattr(dist, "distribution_class", None) is not TanhNormal:
        raise _refuse(f"the actor distribution {getattr(dist, 'distribution_class', None)}", "allowed: TanhNormal")
    for name, default in (("tanh_loc", False), ("safe_tanh", True)):
        if kw.get(name, default) != default:
            raise _refuse(f"TanhNormal({name}={kw[name]!r})", f"it samples as TanhNormal({name}={default!r})")
    actor_keys = list(loss.actor_network.module[0].in_keys)
    obs_key, action_key = actor_keys[0] if len(actor_keys) == 1 else None, loss.tensor_keys.action
    critic_keys = list(loss.qvalue_network.in_keys)
    if obs_key is None or critic_keys != [obs_key, action_key]:
        raise _refuse(
            f"the tensordict keys actor in_keys={actor_keys}, qvalue_network.in_keys={critic_keys}",
            f"the critics must read [observation, action] = [the actor's one in_key, "
            f"loss.tensor_keys.action={action_key!r}], in that order",
        )
    keys = estimator.tensor_keys
    return obs_key, action_key, ("next", keys.reward), ("next", obs_key), ("next", keys.terminated)


def check_fusable_terms(terms: Mapping[str, nn.Module] | None) -> dict[str, nn.Module]:
    """The loss terms the fused update can add, or an error naming the one it cannot.

    A term (e.g. :class:`~adarl.baselines.parseval.ParsevalRegularizer`) declares ``reads_batch = False`` when its
    value depends on the parameters alone: the fused update calls it with no arguments after the SAC gradients
    and adds its gradient to theirs, which is what ``(sum of every loss_*).backward()`` gives on TorchRL's path. A
    term that reads the batch (no such attribute, or ``True``) needs TorchRL's path."""
    terms = dict(terms or {})
    for name, term in terms.items():
        if getattr(term, "reads_batch", True):
            raise AdaRLValueError(
                f"the fused SAC update adds loss terms of the parameters alone (reads_batch = False); the loss term "
                f"{name!r} ({type(term).__name__}) does not say so (set algorithm.fused: false or 'auto')"
            )
        if name in ("actor", "qvalue", "alpha"):
            raise AdaRLValueError(f"a loss term may not be named {name!r}: SAC's own loss_{name} has that name")
    return terms


class FusedSACUpdate:
    """One SAC optimisation step (losses, backward, optimisers, LR schedules, Polyak update) on ``loss``'s tensors.

    Args:
        loss: a continuous-action TorchRL ``SACLoss`` with the TD(0) estimator (as
        :func:`adarl.runtime.builders.make_sac_loss`). optimizers: optimisers over the loss's parameters
        (``make_adam(..., fused=True)`` for fused Adam). schedulers: LR schedulers stepped after the optimisers.
        tau: Polyak rate of the target critics (``SoftUpdate(loss, tau=tau)`` does the same).
        max_grad_norm: per-optimiser gradient clipping as in the plain loop; ``None`` = none.
        compile: ``torch.compile`` the update's computation (the manual step, or the autograd path's losses); one
            recompilation per rank event.
        compile_backend: backend passed to ``torch.compile`` (``"inductor"``; ``"aot_eager"`` for tests).
        backward: ``"manual"``: the losses and gradients written out by hand (:mod:`adarl.fast.manual_backward`:
            fewer operations, no autograd graph); ``"autograd"``: the losses as plain tensor code and
            ``loss.backward()``; ``"auto"``: manual unless a network the manual backward does not know (see
            :func:`adarl.fast.manual_backward.unsupported_reason`). ``compile`` compiles whichever is used.
        terms: loss terms of the parameters alone (``{name: term}``, each with ``reads_batch = False``, e.g. the
            Parseval regulariser): each ``term()`` is added to the total, its gradient to the SAC gradients before
            clipping, and its value returned as ``loss_<name>`` (:func:`check_fusable_terms`).

    A loss setting the update does not compute as ``SACLoss`` does (a TD(lambda) estimator, ``reduction="sum"``,
    critics that do not read ``[observation, action]``, ...) raises :class:`~adarl.errors.AdaRLValueError` naming
    it (:func:`check_fusable`). :attr:`keys` are the tensordict keys a step reads, taken from the loss.

    >>> from tensordict import TensorDict
    >>> from tensordict.nn import TensorDictModule
    >>> from torchrl.data import Bounded
    >>> from torchrl.modules import ProbabilisticActor, ValueOperator
    >>> from torchrl.objectives import ValueEstimators
    >>> from adarl.core.lowrank import low_rank_mlp
    >>> actor = ProbabilisticActor(
    ...     TensorDictModule(nn.Sequential(low_rank_mlp(3, 4), NormalParamExtractor()), ["observation"],
    ...                      ["loc", "scale"]),
    ...     in_keys=["loc", "scale"], distribution_class=TanhNormal)
    >>> critic = ValueOperator(low_rank_mlp(3 + 2, 1), in_keys=["observation", "action"])
    >>> loss = SACLoss(actor, critic, action_spec=Bounded(-1.0, 1.0, (2,)))
    >>> loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    >>> loss.set_keys(reward="r")  # the keys are the loss's: read where SACLoss reads them
    >>> update = FusedSACUpdate(loss, [torch.optim.Adam(loss.parameters(), lr=3e-4)], tau=0.005)
    >>> update.keys
    ('observation', 'action', ('next', 'r'), ('next', 'observation'), ('next', 'terminated'))
    >>> batch = TensorDict({"observation": torch.randn(32, 3), "action": torch.rand(32, 2) * 2 - 1,
    ...                     "next": {"observation": torch.randn(32, 3), "r": torch.randn(32, 1),
    ...                              "terminated": torch.zeros(32, 1, dtype=torch.bool)}}, [32])
    >>> sorted(update(batch))  # one step: losses, backward, Adam, the target critics' Polyak update
    ['alpha', 'entropy', 'loss_actor', 'loss_alpha', 'loss_qvalue']
    >>> loss.make_value_estimator(ValueEstimators.TDLambda, gamma=0.99, lmbda=0.95)
    >>> FusedSACUpdate(loss, [], tau=0.005)
    Traceback (most recent call last):
        ...
    adarl.errors.AdaRLValueError: the fused SAC update does not implement the value estimator TDLambdaEstimator: ...
    """

    def __init__(
        self,
        loss,
        optimizers: Sequence[torch.optim.Optimizer],
        *,
        tau: float,
        schedulers: Sequence = (),
        max_grad_norm: float | None = None,
        compile: bool = False,
        compile_backend: str = "inductor",
        backward: str = "auto",
        terms: Mapping[str, nn.Module] | None = None,
        polyak: str = "factors",
    ) -> None:
        self.keys = check_fusable(loss)
        if polyak not in POLYAK_MODES:
            raise AdaRLValueError(f"polyak must be one of {POLYAK_MODES}, got {polyak!r}")
        self.terms = check_fusable_terms(terms)
        if not 0 < tau <= 1:
            raise AdaRLValueError(f"tau must be in (0, 1], got {tau}")
        self.loss = loss
        self.optimizers = list(optimizers)
        # Adam(fused=True).step() + zero_grad() without their Python overhead (same kernels, falls back by itself)
        self._adam_steps = [DirectAdamStep(o) for o in self.optimizers]
        # the tensors a loss term's gradient may reach: what the optimisers step
        self._term_params = [p for o in self.optimizers for g in o.param_groups for p in g["params"]]
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
        # 'product': the factorised layers' targets follow the averaged product (adarl.core.product_polyak)
        self.polyak = polyak
        products = factor_keys(self.q_params) if polyak == "product" else set()
        self._product_pairs = factor_pairs(
            {k: v for k, v in self.target_q_params.items() if k in products}, self.q_params
        )
        keys = [k for k in self.q_params if k not in products]
        self._q_sources = [self.q_params[k] for k in keys]
        self._q_targets = [self.target_q_params[k] for k in keys]
        self.compile = compile
        self.compile_backend = compile_backend
        self._compilations = 0
        self.backward = self._resolve_backward(backward)
        self._manual = None
        if self.backward == "manual":
            self._manual = ManualSACStep(self, compile=compile, compile_backend=compile_backend)
            self._fn = None
        else:
            self._fn = self._build()

    @property
    def compilations(self) -> int:
        """How many times the update was compiled (the first build plus one per rank event)."""
        return self._manual.compilations if self._manual is not None else self._compilations

    def _resolve_backward(self, setting: str) -> str:
        if setting not in BACKWARDS:
            raise AdaRLValueError(f"backward must be one of {BACKWARDS}, got {setting!r}")
        reason = unsupported_reason(self)
        if setting == "manual" and reason is not None:
            raise AdaRLValueError(
                f"backward='manual' does not support the {reason}; allowed here: 'auto' or 'autograd'"
            )
        if setting == "auto":
            return "autograd" if reason is not None else "manual"
        return setting

    # ------------------------------------------------------------------ the maths
    def _sample(self, actor: list[tuple], obs: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised TanhNormal sample and its log-probability, scored at the exact pre-tanh value."""
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
    def batch_tensors(self, batch: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """The five tensors an update reads from a replay sample (at :attr:`keys`)."""
        return tuple(batch.get(k) for k in self.keys)

    def draw_noise(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Standard-normal noise for the next-state and current-state samples, in SACLoss's order."""
        shape = (*obs.shape[:-1], action.shape[-1])
        kw = {"dtype": obs.dtype, "device": obs.device}  # the batch's device: its generator (CPU: the global one)
        return torch.randn(shape, **kw), torch.randn(shape, **kw)

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        return self.step(*self.batch_tensors(batch))

    def step(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        reward: torch.Tensor,
        next_obs: torch.Tensor,
        terminated: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """One update from the five tensors of :meth:`batch_tensors` (e.g. from a
        :class:`~adarl.fast.replay.UniformTensorSampler`)."""
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            self.loss.log_alpha.data.clamp_(self.min_log_alpha, self.max_log_alpha)
        shift = None
        if isinstance(self.loss, TargetShiftSACLoss):  # only the target reads the reward: r - shift is exact
            shift = self.loss.target_shift().detach().reshape(())
            reward = reward - shift
        noise_next, noise_now = self.draw_noise(obs, action)
        args = (obs, action, reward, next_obs, terminated.bool(), noise_next, noise_now)
        if self._manual is not None:  # fills the parameters' .grad itself
            loss_actor, loss_q, loss_alpha, alpha, entropy = self._manual(*args)
        else:
            loss_actor, loss_q, loss_alpha, alpha, entropy = self._fn(*args)
            (loss_actor + loss_q + loss_alpha).backward()
        term_values = self._add_terms() if self.terms else {}
        if self.max_grad_norm is not None:
            for opt in self.optimizers:
                for group in opt.param_groups:
                    torch.nn.utils.clip_grad_norm_(group["params"], self.max_grad_norm)
        for opt in self._adam_steps:
            opt.step()
        for sched in self.schedulers:
            sched.step()
        with torch.no_grad():
            private.foreach_lerp_(self._q_targets, self._q_sources, self.tau)
        if self._product_pairs:
            product_polyak_(self._product_pairs, self.tau)
        return {
            "loss_actor": loss_actor.detach(),
            "loss_qvalue": loss_q.detach(),
            "loss_alpha": loss_alpha.detach(),
            "alpha": alpha,
            "entropy": entropy,
            **term_values,
            **({} if shift is None else {"target_shift": shift}),
        }

    def _add_terms(self) -> dict[str, torch.Tensor]:
        """Each loss term's value (``loss_<name>``), its gradient added to the parameters' SAC gradients."""
        values = {}
        with torch.enable_grad():
            total = None
            for name, term in self.terms.items():
                value = term()
                values[f"loss_{name}"] = value.detach()
                total = value if total is None else total + value
            params = [p for p in self._term_params if p.requires_grad]
            grads = torch.autograd.grad(total, params, allow_unused=True)
        with torch.no_grad():
            for p, g in zip(params, grads, strict=True):
                if g is None:
                    continue
                if p.grad is None:
                    p.grad = g
                else:
                    p.grad.add_(g)
        return values
