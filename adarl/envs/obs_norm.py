"""Observation normalisation (``env.normalize_observations``), SB3's ``VecNormalize`` observation part done with
TorchRL's own transform.

Why ``VecNormV2`` (``VecNorm(new_api=True)``) and not ``ObservationNorm``: ``ObservationNorm`` holds fixed
statistics (computed once, ``init_stats``), ``VecNormV2`` keeps running ones that it updates at every reset and
step, can be frozen (:meth:`~torchrl.envs.transforms.VecNormV2.freeze`: evaluation reads them without moving them),
and says what it holds through ``get_extra_state`` (plain tensors: a checkpoint loads them with
``weights_only=True``). TorchRL's own ``to_observation_norm`` turns its statistics into the affine map an exported
policy applies; here that map is :class:`ObservationAffine`, a plain torch layer (``(x - loc) / scale``, the same
float32 operations on the same constants as the transform), so it goes into an exported program as it is.

The transform sits last on the training env (``make_env(..., normalize_observations=True)``): collectors, the
replay buffer and the losses see normalised ``"observation"``, as with TorchRL's ``VecNorm`` examples. The
evaluation env holds a frozen transform sharing the training statistics (:func:`share_observation_norm`); a
checkpoint saves them (:func:`obs_norm_state_dict`) and a resume writes them back in place
(:func:`load_obs_norm_state_dict`: the evaluation env keeps seeing them).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import Compose, EnvBase, TransformedEnv, VecNorm
from torchrl.envs.transforms.vecnorm import VecNormV2

from adarl.errors import AdaRLValueError, CheckpointError

__all__ = [
    "OBS_KEY",
    "make_observation_norm",
    "find_observation_norm",
    "share_observation_norm",
    "obs_norm_state_dict",
    "load_obs_norm_state_dict",
    "ObservationAffine",
    "observation_affine",
    "with_observation_norm",
]

#: the entry normalised (what adarl's actors and critics read)
OBS_KEY = "observation"


def make_observation_norm() -> VecNormV2:
    """TorchRL's running mean/std normaliser of ``"observation"`` (defaults: ``decay=0.9999``, ``eps=1e-4``),
    averaging over a batched env's workers (one set of statistics for all)."""
    return VecNorm(in_keys=[OBS_KEY], new_api=True, reduce_batch_dims=True)


def find_observation_norm(env: EnvBase) -> VecNormV2 | None:
    """The ``VecNormV2`` on ``"observation"`` among ``env``'s own transforms (None when it has none)."""
    while isinstance(env, TransformedEnv):
        transforms = env.transform if isinstance(env.transform, Compose) else [env.transform]
        for t in transforms:
            if isinstance(t, VecNormV2) and list(t.in_keys) == [OBS_KEY]:
                return t
        env = env.base_env
    return None


def _require(env: EnvBase, what: str) -> VecNormV2:
    norm = find_observation_norm(env)
    if norm is None or norm._loc is None:
        raise AdaRLValueError(f"{what}: the env has no initialised observation normaliser (VecNormV2 on 'observation')")
    return norm


def share_observation_norm(source: EnvBase, target: EnvBase) -> VecNormV2:
    """Make ``target``'s normaliser read ``source``'s statistics (the same tensors, updated in place by the training
    env) and freeze it, so that evaluating on ``target`` never moves them."""
    src, dst = _require(source, "share_observation_norm"), _require(target, "share_observation_norm")
    dst._loc, dst._var, dst._count = src._loc, src._var, src._count
    dst.initialized.fill_(True)
    return dst.freeze()


def obs_norm_state_dict(env: EnvBase) -> dict[str, torch.Tensor] | None:
    """The normaliser's statistics as TorchRL writes them (``get_extra_state``: plain tensors, copied); None
    without one."""
    norm = find_observation_norm(env)
    if norm is None:
        return None
    return {k: v.clone() for k, v in _require(env, "obs_norm_state_dict").get_extra_state().items()}


def _unflatten(state: Mapping[str, torch.Tensor]) -> TensorDict:
    try:
        td = TensorDict(dict(state)).unflatten_keys(VecNormV2.SEP)
        return td.select("loc", "var", "count", strict=True)
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        raise CheckpointError(
            f"the checkpoint's observation statistics are not a VecNorm state (loc, var, count): {err}"
        ) from None


def load_obs_norm_state_dict(env: EnvBase, state: Mapping[str, torch.Tensor] | None) -> None:
    """Write saved statistics back into ``env``'s normaliser in place (an evaluation env sharing them sees them
    too). A checkpoint without statistics for an env with a normaliser, or the reverse, is refused."""
    norm = find_observation_norm(env)
    if state is None and norm is None:
        return
    if state is None or norm is None:
        raise CheckpointError(
            "the checkpoint "
            + ("holds no observation statistics but this run normalises observations" if state is None else "")
            + ("holds observation statistics but this run does not normalise observations" if norm is None else "")
            + " (env.normalize_observations differs from the run that wrote it)"
        )
    td = _unflatten(state)
    norm = _require(env, "load_obs_norm_state_dict")
    for name, mine in (("loc", norm._loc), ("var", norm._var), ("count", norm._count)):
        saved = td[name]
        if saved.shape != mine.shape or set(saved.keys(True, True)) != set(mine.keys(True, True)):
            raise CheckpointError(
                f"the checkpoint's observation statistics ({name}) do not fit this env's observations: saved "
                f"{ {k: list(v.shape) for k, v in saved.items(True, True)} }, here "
                f"{ {k: list(v.shape) for k, v in mine.items(True, True)} }"
            )
        mine.update_(saved)


class ObservationAffine(nn.Module):
    """The normaliser frozen: ``(x - loc) / scale``, what ``VecNormV2`` computes from the same statistics. The
    first layer of a policy that reads raw observations (:func:`adarl.load_policy`, ``adarl export``)."""

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("loc", loc.detach().to(torch.float32).clone())
        self.register_buffer("scale", scale.detach().to(torch.float32).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale


def observation_affine(source: EnvBase | Mapping[str, torch.Tensor]) -> ObservationAffine:
    """The frozen affine map of an env's normaliser, or of a checkpoint's statistics (:func:`obs_norm_state_dict`),
    with ``loc`` and ``scale`` as TorchRL computes them (``VecNormV2``'s bias correction included)."""
    if isinstance(source, EnvBase):
        norm = _require(source, "observation_affine")
    else:
        norm = make_observation_norm()
        with warnings.catch_warnings():  # "not shared": these statistics stay in this process
            warnings.simplefilter("ignore")
            norm.set_extra_state(_unflatten(source).flatten_keys(VecNormV2.SEP).to_dict())
    loc, scale = norm._get_loc_scale()
    return ObservationAffine(loc[OBS_KEY], scale[OBS_KEY])


def with_observation_norm(actor: nn.Module, affine: ObservationAffine) -> nn.Module:
    """``actor`` (changed in place, and returned) reading raw observations: the network of its module on
    ``"observation"`` becomes ``nn.Sequential(affine, network)`` (an exported program starts with the same map)."""
    for module in actor.modules():
        if (
            isinstance(module, TensorDictModule)
            and not isinstance(module, TensorDictSequential)
            and list(module.in_keys) == [OBS_KEY]
        ):
            module.module = nn.Sequential(affine, module.module)
            return actor
    raise AdaRLValueError(
        f"cannot put the observation normaliser in front of {type(actor).__name__}: it has no module reading only "
        f"{OBS_KEY!r}"
    )
