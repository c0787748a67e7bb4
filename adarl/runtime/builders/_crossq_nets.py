"""CrossQ's networks (Batch Renormalization layers around the recipe's MLP) and the options of the SAC loop's
variants (TQC, CrossQ, REDQ): what :func:`~adarl.runtime.builders.sac.make_recipe_actor` needs for a CrossQ actor,
below both the SAC builder and :mod:`~adarl.runtime.builders.sac_variants`, so neither imports the other's."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.envs import EnvBase
from torchrl.modules import BatchRenorm1d, ProbabilisticActor, TanhNormal

from adarl import plugins
from adarl.errors import AdaRLValueError
from adarl.runtime.builders.common import _activation, action_spec, make_mlp, recipe_mlp_kwargs

__all__ = ["VARIANTS", "variant_of", "BatchRenormLayer", "make_batch_renorm_mlp", "make_crossq_actor"]

#: the TorchRL losses built here, by the option class of adarl's own name for each
VARIANTS = {"TQCLoss": plugins.TQCOptions, "CrossQLoss": plugins.CrossQOptions, "REDQLoss": plugins.REDQOptions}


def variant_of(recipe) -> str | None:
    """``"TQCLoss"``, ``"CrossQLoss"`` or ``"REDQLoss"`` when the recipe's loss is (or subclasses) one of them, else
    None (SAC's own)."""
    return plugins.sac_variant(recipe.algorithm.name)


def _options(recipe, variant: str):
    """The variant's options: the recipe's ``algorithm.options`` for adarl's own names, the authors' defaults for a
    plugin's subclass (whose own options go to its constructor)."""
    model = VARIANTS[variant]
    spec = plugins.algorithm(recipe.algorithm.name)
    return model(**recipe.algorithm.options) if spec.options is model else model()


class BatchRenormLayer(BatchRenorm1d):
    """TorchRL's ``BatchRenorm1d`` on the last dimension of any input (one observation, a batch, a batch of
    ensembles); scriptable in eval mode, so that ``adarl export`` writes it (the train path is TorchRL's own)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training:
            return self._train_forward(x)
        return (x - self.running_mean) / torch.sqrt(self.running_var + self.eps) * self.weight + self.bias

    @torch.jit.unused
    def _train_forward(self, x):  # (no annotations: TorchScript reads this stub's as Tensor -> Tensor)
        shape = x.shape
        return super().forward(x.reshape(-1, shape[-1])).reshape(shape)


def make_batch_renorm_mlp(
    in_features: int,
    out_features: int,
    *,
    num_cells: Sequence[int],
    activation: str,
    low_rank_layers: Sequence[int],
    rank,
    device,
    momentum: float,
    warmup_steps: int,
    **variants,
) -> nn.Sequential:
    """CrossQ's MLP: ``BatchRenorm1d`` on the input, then each hidden layer (a ``LowRankLinear`` where
    ``low_rank_layers`` says so) followed by its activation and a ``BatchRenorm1d``; a plain ``Linear`` head."""
    if variants:
        raise AdaRLValueError(
            f"CrossQ's Batch Renormalization networks take no baseline network variant; asked for {sorted(variants)}"
        )
    base = make_mlp(
        in_features,
        out_features,
        num_cells=num_cells,
        activation=activation,
        low_rank_layers=low_rank_layers,
        rank=rank,
        device=device,
    )
    act = _activation(activation)

    def norm(width: int) -> BatchRenormLayer:
        return BatchRenormLayer(width, momentum=momentum, warmup_steps=warmup_steps).to(device)

    layers: list[nn.Module] = [norm(in_features)]
    widths = iter(num_cells)
    for layer in base:
        layers.append(layer)
        if isinstance(layer, act):
            layers.append(norm(next(widths)))
    return nn.Sequential(*layers)


class _Concat(nn.Sequential):
    """An ``nn.Sequential`` on its inputs concatenated (the critic's ``[s, a]``, as TorchRL's ``MLP`` takes them)."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return super().forward(torch.cat(inputs, -1))


def make_crossq_actor(recipe, env: EnvBase) -> ProbabilisticActor | None:
    """CrossQ's actor (SAC's TanhNormal actor with ``BatchRenorm1d`` layers), in eval mode; None with
    ``actor_batch_norm: false`` (SAC's plain actor then). :func:`~adarl.runtime.builders.sac.make_recipe_actor`, the
    family's actor (``load_policy``, ``adarl export``), calls it for a CrossQ recipe."""
    opts = _options(recipe, "CrossQLoss")
    if not opts.actor_batch_norm:
        return None
    spec = action_spec(env)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], spec.shape[-1]
    kwargs = recipe_mlp_kwargs(recipe.network.actor, recipe.algorithm, act_dim, recipe.device)
    net = make_batch_renorm_mlp(
        obs_dim,
        2 * act_dim,
        momentum=opts.batch_norm_momentum,
        warmup_steps=opts.renorm_warmup_steps,
        **kwargs,
    )
    module = TensorDictModule(
        nn.Sequential(net, NormalParamExtractor()), in_keys=["observation"], out_keys=["loc", "scale"]
    )
    actor = ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        return_log_prob=False,
    )
    return actor.eval()
