"""The recipe's ``algorithm`` section: SAC's keys, the registered algorithms' options, Parseval, PPO and TD3 (each
loop family's checks across sections are the hub's, :mod:`adarl.runtime.config.schema`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, field_validator, model_validator

from adarl import plugins
from adarl.errors import AdaRLValueError, UnknownNameError, did_you_mean, one_of
from adarl.runtime.config._schema_base import (
    Float,
    NonNegInt,
    PosFloat,
    PosInt,
    _advantage_norm,
    _plain_copy,
    _Problems,
    _Section,
    _validated_options,
)


class ParsevalConfig(_Section):
    enabled: bool = Field(False, description="Add Parseval regularisation (Chung et al., 2024) to the loss.")
    lam: Annotated[Float, Field(gt=0)] = Field(
        1e-4,
        description="Weight lambda of lam * (base_width/width)^2 * sum ||W W^T - s I||_F^2 "
        "(tuned in {1e-3, 1e-4, 1e-5}).",
    )
    s: PosFloat = Field(2.0, description="Target squared row norm s of the hidden weights (the paper: 2).")
    base_width: PosInt = Field(64, description="Reference width of the (base_width/width)^2 scaling (the paper: 64).")
    diagonal: bool = Field(
        False, description="Learnable per-unit gain after every hidden linear layer (optional layer)."
    )
    input_scale: bool = Field(False, description="Learnable scalar on the network input (optional layer).")


class PPOConfig(_Section):
    minibatch_size: PosInt = Field(64, description="PPO minibatch size (RNAC's trainer: 64 of each 2048-frame batch).")
    epochs: PosInt = Field(10, description="Passes over each collected batch.")
    clip_epsilon: Annotated[Float, Field(gt=0, lt=1)] = Field(0.2, description="PPO ratio clip.")
    gae_lambda: Annotated[Float, Field(ge=0, le=1)] = Field(0.95, description="GAE lambda.")
    entropy_coeff: Annotated[Float, Field(ge=0)] = Field(0.01, description="Entropy bonus weight.")
    critic_coeff: PosFloat = Field(1.0, description="Weight of the value loss (actor and critic have separate Adams).")
    adam_eps: PosFloat = Field(1e-5, description="Adam epsilon (the original: 1e-5).")
    lr_decay: bool = Field(True, description="Decay the learning rate linearly to 0 over the run (the original does).")
    normalize_advantage: Annotated[Literal["batch", "minibatch", "none"], BeforeValidator(_advantage_norm)] = Field(
        "batch",
        description="Standardise the advantages (mean 0, std 1): 'batch' = over each whole collected batch, once, "
        "before the epochs (RNAC's trainer: (A - mean) / (std + 1e-5) over its 2048 frames); 'minibatch' = in each "
        "minibatch inside ClipPPOLoss (TorchRL's normalize_advantage); 'none'. true/false read as 'minibatch'/'none', "
        "their meaning before 'batch' existed.",
    )
    obs_norm: bool = Field(True, description="Running mean/std observation normalisation inside actor and critic.")
    reward_scaling: bool = Field(True, description="Divide rewards by the running std of the discounted return.")
    policy: Literal["clipped_gaussian", "tanh_gaussian"] = Field(
        "clipped_gaussian",
        description="PPO policy: 'clipped_gaussian' = RNAC's original, a Gaussian with mean = tanh of the head scaled "
        "to the action box, a state-independent log-std, samples clipped to the box, log-probability and entropy of "
        "the unclipped Gaussian (adarl.baselines.ClippedNormal); 'tanh_gaussian' = TorchRL's TanhNormal (samples "
        "squashed into the box; its entropy is estimated from one sample).",
    )


class TD3Config(_Section):
    policy_noise: Annotated[Float, Field(ge=0)] = Field(
        0.2, description="Std of the Gaussian noise on the target action (TD3's target policy smoothing; TD3Loss)."
    )
    noise_clip: Annotated[Float, Field(ge=0)] = Field(
        0.5, description="Clip of the target-action noise, |noise| <= noise_clip (TD3Loss)."
    )
    exploration_noise: Annotated[Float, Field(ge=0)] = Field(
        0.1,
        description="Std of the Gaussian noise added to the actor's action while collecting (TorchRL's "
        "AdditiveGaussianModule; the action is projected back into the box), in the action's units.",
    )
    policy_update_delay: PosInt = Field(
        2,
        description="Critic updates per actor and target update (TD3's delayed policy updates; 1 = every update, "
        "as DDPG does).",
    )


class AlgorithmConfig(_Section):
    name: str = Field(
        "sac",
        description="RL algorithm, a registered name (adarl.register_algorithm; installed packages add names through "
        "the 'adarl.plugins' entry-point group): 'sac' as in the paper (DiscreteSAC for discrete-action envs); "
        "'ppo' = TorchRL's ClipPPOLoss + GAE, the RNAC baselines' base (continuous actions; SAC-only keys are "
        "ignored); 'td3' / 'ddpg' = TorchRL's TD3Loss / DDPGLoss on the off-policy loop with rank control "
        "(algorithm.td3; continuous actions; SAC's alpha keys are ignored); 'tqc' / 'crossq' / 'redq' = TorchRL's "
        "TQCLoss / CrossQLoss / REDQLoss on the SAC loop with rank control (their authors' hyperparameters in "
        "algorithm.options); a plugin's name runs its loss on the loop of its base (docs/custom-loss.md).",
        json_schema_extra={
            "allowed": "a registered algorithm name ('sac', 'ppo', 'td3', 'ddpg', 'tqc', 'crossq', 'redq', "
            "'rnac_ipm', 'rnac_ds', or one an installed plugin adds)"
        },
    )
    options: dict[str, Any] = Field(
        default_factory=dict,
        description="The registered algorithm's own options (its pydantic model: unknown keys, types and ranges are "
        "checked like every other key; every default is written into the run's recipe.yaml). 'sac' and 'ppo' "
        "have none; those of 'tqc', 'crossq' and 'redq' are their authors' hyperparameters (docs/custom-loss.md).",
    )
    gamma: Annotated[Float, Field(gt=0, le=1)] = Field(0.99, description="Discount factor.")
    tau: Annotated[Float, Field(gt=0, le=1)] = Field(0.005, description="Polyak rate of the target critics.")
    polyak: Literal["factors", "product"] = Field(
        "factors",
        description="How the target critics' factorised layers follow the online ones (SAC): 'factors' averages "
        "W1 and W2 each (TorchRL's SoftUpdate, per tensor: the target product is then not the average of the "
        "online products); 'product' averages the product, (1 - tau) W1' W2' + tau W1 W2, and re-derives the "
        "target factors from it (balanced, at the layer's rank: adarl.core.product_polyak). Dense layers and "
        "biases are averaged per tensor either way.",
    )
    factor_lr_scale: PosFloat = Field(
        1.0,
        description="Multiplies the learning rate of the low-rank factors W1, W2 (SAC; a second Adam parameter "
        "group, scheduled like the first): Adam on the balanced factors moves W = W1 W2 further than a dense "
        "step would (docs/low-rank-linear.md); < 1 makes one factor step move W as a dense one does. 1 = the "
        "rate of every other parameter.",
    )
    lr: PosFloat = Field(3e-3, description="Adam learning rate of actor and critic (paper: 3e-3).")
    alpha_lr: PosFloat = Field(3e-4, description="Adam learning rate of the entropy temperature.")
    batch_size: PosInt = Field(256, description="Transitions per optimisation step.")
    utd_ratio: PosFloat = Field(1.0, description="Optimisation steps per collected frame (update-to-data ratio).")
    update_after: NonNegInt | None = Field(
        None,
        description="Frames collected before the first optimisation step (spinningup's update_after: 1000, while "
        "actions stay random for collector.init_random_frames); null = collector.init_random_frames.",
    )
    num_qvalue_nets: PosInt = Field(2, description="Critics in the ensemble (clipped double-Q with 2).")
    loss_function: Literal["l2", "smooth_l1", "l1"] = Field(
        "l2", description="Critic regression loss; l2 like the reference SAC (TorchRL's default is smooth_l1)."
    )
    init_alpha: PosFloat = Field(1.0, description="Initial entropy temperature.")
    fixed_alpha: bool = Field(False, description="Keep alpha at init_alpha instead of tuning it.")
    target_entropy: Literal["auto"] | Float = Field(
        "auto",
        description="Entropy target of the alpha tuning; 'auto' = -action_dim (continuous) or TorchRL's default.",
    )
    max_grad_norm: PosFloat | None = Field(None, description="Clip gradient norm per optimiser; null = no clipping.")
    fused: Literal["auto"] | bool = Field(
        "auto",
        description="Fused SAC update (adarl.fast.sac: same losses as SACLoss, batched critics, fused Adam, foreach "
        "target update); 'auto' = on for continuous actions, TorchRL's SACLoss path for discrete; false = SACLoss.",
    )
    compile: bool = Field(
        False, description="torch.compile the fused SAC update (needs fused; one recompilation per rank event)."
    )
    backward: Literal["auto", "manual", "autograd"] = Field(
        "auto",
        description="Backward of the fused update: 'manual' (adarl.fast.manual_backward: the gradients written out by "
        "hand, no autograd graph), 'autograd' (loss.backward()); 'auto' = manual where the networks allow it.",
    )
    num_threads: PosInt | None = Field(
        None,
        description="torch.set_num_threads for the run; null = leave torch's setting (1 is best at (64, 64) on CPU).",
    )
    parseval: ParsevalConfig = Field(default_factory=ParsevalConfig, description="Parseval regularisation baseline.")
    ppo: PPOConfig = Field(default_factory=PPOConfig, description="PPO hyperparameters (algorithm.name=ppo).")
    td3: TD3Config = Field(
        default_factory=TD3Config,
        description="TD3/DDPG hyperparameters (algorithms on the 'td3' loop: td3, ddpg, a plugin's TD3Loss/DDPGLoss).",
    )

    @model_validator(mode="before")
    @classmethod
    def _legacy_rnac(cls, data: Any) -> Any:
        """Recipes and run folders written before RNAC was a registered algorithm said ``algorithm.name: ppo`` and
        ``algorithm.rnac.{mode, kappa, num_candidates, noise}``: read as ``rnac_ipm`` / ``rnac_ds`` with options."""
        if not isinstance(data, Mapping) or "rnac" not in data:
            return data
        data = dict(data)
        rnac = data.pop("rnac")
        mode = rnac.get("mode", "none") if isinstance(rnac, Mapping) else rnac
        if mode in (None, "none"):
            return data
        if mode not in ("ipm", "ds") or data.get("name", "sac") != "ppo" or data.get("options"):
            raise _Problems(
                [
                    (
                        "rnac",
                        _plain_copy(rnac),
                        "is the old form of the RNAC baselines (it needs name 'ppo' and mode 'ipm' or 'ds'); "
                        "write algorithm.name: rnac_ipm (options: kappa) or rnac_ds (options: num_candidates, noise)",
                    )
                ]
            )
        keys = ("kappa",) if mode == "ipm" else ("num_candidates", "noise")
        data["name"] = f"rnac_{mode}"
        data["options"] = {k: rnac[k] for k in keys if k in rnac}
        return data

    @field_validator("name")
    @classmethod
    def _check_name(cls, v: str) -> str:
        try:
            plugins.algorithm(v)
        except UnknownNameError as err:
            msg = f"not a registered algorithm; allowed: {one_of(err.allowed)}{did_you_mean(v, err.allowed)}{err.hint}"
            raise _Problems([("", v, msg)]) from None
        except AdaRLValueError as err:  # an installed plugin failed to load (named)
            raise _Problems([("", v, str(err))]) from None
        return v

    @model_validator(mode="after")
    def _check_options(self) -> AlgorithmConfig:
        spec = plugins.algorithm(self.name)
        self.options = _validated_options(spec.options, self.options, "options", f"algorithm {self.name!r}")
        # keys the algorithm's options decide (REDQ's G is algorithm.utd_ratio): copied, unless set to another value
        for key, option in spec.sets.items():
            value, current = self.options[option], getattr(self, key)
            if current not in (value, AlgorithmConfig.model_fields[key].default):
                msg = (
                    f"is set by algorithm.options.{option} ({value!r}) with algorithm.name {self.name!r}; set that "
                    f"option instead (or this key to {value!r})"
                )
                raise _Problems([(key, current, msg)])
            setattr(self, key, type(current)(value))
        return self

    @property
    def base(self) -> str:
        """The training loop of :attr:`name` ('sac', 'ppo' or 'td3'; :func:`adarl.plugins.algorithm`)."""
        return plugins.algorithm(self.name).base
