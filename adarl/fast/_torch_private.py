"""The torch-private functions and attributes :mod:`adarl.fast` uses, behind one version guard.

Why: the fast path calls kernels and reads hook tables that torch does not promise to keep (``torch._fused_adam_``,
``torch._foreach_add_``, ``torch._foreach_lerp_``, the ``*_backward`` ATen ops, the optimiser's and modules' hook
dicts). On a torch this module was tested on (:data:`TESTED`, checked by version and by the ops' schemas) they are
used as before, bit for bit; on any other torch every caller takes its public path instead (``opt.step()`` of
``torch.optim.Adam``, per-tensor ``lerp_``, autograd, ``Module.__call__``) and one :class:`TorchFallbackWarning`
says so, once a process.

Mirrors: what the callers would do without it: ``torch.optim.Adam(fused=True).step()`` (the same kernels),
``torch._foreach_lerp_`` as one ``lerp_`` a tensor, the hook checks ``Module.__call__`` and ``Optimizer.step`` make.
Equality: ``tests/test_fast_torch_private.py::test_fallback_computes_the_fast_paths_update`` (a forced fallback
against the fast path over SAC updates), ``tests/test_fast_torch_private.py::test_the_notice_is_emitted_once``.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import torch
from torch.nn.modules import module as nn_module
from torch.optim import optimizer as optim_mod

from adarl.errors import TorchFallbackWarning

__all__ = [
    "TESTED",
    "aten",
    "foreach_lerp_",
    "fused_adam_step",
    "module_hooked",
    "global_module_hooks",
    "optimizer_hooked",
    "reason",
    "usable",
]

#: torch releases (major.minor) the private calls were tested on; any other takes the public paths
TESTED = ("2.13",)
#: the ATen ops used, overload -> the argument names expected in its schema
SCHEMAS = {
    "_fused_adam_.default": (
        "self grads exp_avgs exp_avg_sqs max_exp_avg_sqs state_steps lr beta1 beta2 weight_decay eps amsgrad "
        "maximize grad_scale found_inf"
    ),
    "_foreach_add_.Scalar": "self scalar",
    "_foreach_lerp_.Scalar": "self tensors1 weight",
    "threshold_backward.default": "grad_output self threshold",
    "tanh_backward.default": "grad_output output",
    "softplus_backward.default": "grad_output self beta threshold",
    "elu_backward.default": "grad_output alpha scale input_scale is_result self_or_result",
    "gelu_backward.default": "grad_output self approximate",
    "silu_backward.default": "grad_output self",
    "leaky_relu_backward.default": "grad_output self negative_slope self_is_result",
}
_OPTIM_GLOBALS = ("_global_optimizer_pre_hooks", "_global_optimizer_post_hooks")
_NN_GLOBALS = (
    "_global_forward_hooks",
    "_global_forward_pre_hooks",
    "_global_backward_hooks",
    "_global_backward_pre_hooks",
)

aten = torch.ops.aten
_checked: dict[str, str | None] = {}  # "reason" -> the cached probe's answer
_warned: list[bool] = []  # non-empty once the notice was emitted


def _probe() -> str | None:
    """Why the private calls cannot be used on this torch (None: they can)."""
    version = torch.__version__.split("+")[0]
    if not any(version == t or version.startswith(t + ".") for t in TESTED):
        return f"torch {torch.__version__} is not a version adarl.fast was tested on ({', '.join(TESTED)})"
    for name, expected in SCHEMAS.items():
        packet, _, overload = name.partition(".")
        try:
            schema = getattr(getattr(aten, packet), overload)._schema
        except (AttributeError, RuntimeError):
            return f"torch {torch.__version__} has no aten::{name}"
        if [a.name for a in schema.arguments] != expected.split():
            return f"torch {torch.__version__}'s aten::{name} has another signature"
    for name in ("_fused_adam_", "_foreach_add_", "_foreach_lerp_"):
        if not callable(getattr(torch, name, None)):
            return f"torch {torch.__version__} has no torch.{name}"
    for module, names in ((optim_mod, _OPTIM_GLOBALS), (nn_module, _NN_GLOBALS)):
        for name in names:
            if not isinstance(getattr(module, name, None), dict):
                return f"torch {torch.__version__} has no {module.__name__}.{name}"
    return None


def reason() -> str | None:
    """Why the fast path takes its public fallbacks on this torch (None: it uses the private calls); cached."""
    if "reason" not in _checked:
        _checked["reason"] = _probe()
    return _checked["reason"]


def usable() -> bool:
    """Whether the private calls may be used; the first False emits the one-line :class:`TorchFallbackWarning`."""
    why = reason()
    if why is not None and not _warned:
        _warned.append(True)
        warnings.warn(
            f"adarl.fast: {why}; using the public paths instead (torch.optim.Adam.step, lerp_, autograd)",
            TorchFallbackWarning,
            stacklevel=3,
        )
    return why is None


def optimizer_hooked(opt: torch.optim.Optimizer) -> bool:
    """Whether ``opt.step()`` would run a hook (its own or a global one): then only ``opt.step()`` may step it.

    Read on every step, so as plain attribute reads (True where a table is missing: take the public path)."""
    if not usable():
        return True
    try:
        return bool(
            opt._optimizer_step_pre_hooks
            or opt._optimizer_step_post_hooks
            or optim_mod._global_optimizer_pre_hooks
            or optim_mod._global_optimizer_post_hooks
        )
    except AttributeError:
        return True


def global_module_hooks() -> bool:
    """Whether a global module hook is registered (``Module.__call__`` must then run every module)."""
    return not usable() or any(getattr(nn_module, name) for name in _NN_GLOBALS)


def module_hooked(m: torch.nn.Module) -> bool:
    """Whether ``m`` has a hook of its own (``m.forward`` alone would skip it; True where a table is missing)."""
    if not usable():
        return True
    try:
        return bool(m._forward_hooks or m._forward_pre_hooks or m._backward_hooks or m._backward_pre_hooks)
    except AttributeError:
        return True


def fused_adam_step(group: dict, params: list, avgs: list, sqs: list, steps: list) -> None:
    """One group's ``Adam(fused=True)`` step, the kernels its ``step()`` calls (callers check :func:`usable`)."""
    beta1, beta2 = group["betas"]
    torch._foreach_add_(steps, 1)
    torch._fused_adam_(
        params,
        [p.grad for p in params],
        avgs,
        sqs,
        [],
        steps,
        amsgrad=False,
        lr=group["lr"],
        beta1=float(beta1),
        beta2=float(beta2),
        weight_decay=group["weight_decay"],
        eps=group["eps"],
        maximize=group["maximize"],
        grad_scale=None,
        found_inf=None,
    )


def foreach_lerp_(targets: Sequence[torch.Tensor], sources: Sequence[torch.Tensor], weight: float) -> None:
    """``t.lerp_(s, weight)`` for each pair: one ``torch._foreach_lerp_`` where :func:`usable`, else one a tensor."""
    if usable():
        torch._foreach_lerp_(targets, sources, weight)
        return
    for t, s in zip(targets, sources):
        t.lerp_(s, weight)
