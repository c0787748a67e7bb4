"""The recipe schema: pydantic models of every section of a recipe, with their defaults, ranges and cross-checks.

Every model forbids unknown keys and NaN/inf. A validator that finds problems raises ``_Problems`` (key path
relative to the model, value, message), which :mod:`adarl.runtime.config.validation` turns into
:class:`~adarl.errors.RecipeError` lines. Env ids, presets, parameter names and schedules are checked against
:mod:`adarl.envs` (its registry and schedule grammar), never against a copy.

Long because: it is the recipe's reference, one model per section with every key's description, default and range
(``adarl show`` and docs/recipes.md are read from it), each cross-check next to the keys it relates.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

from adarl import plugins
from adarl.envs.declared import declared_parameters, gymnasium_entry_point, gymnasium_ids
from adarl.envs.registry import (
    HOW_TO_REGISTER_ENV,
    check_any_env_id,
    is_mujoco,
    parameters_for,
    preset_names,
    validate_schedule,
)
from adarl.envs.schedules import (
    schedule_from_dict,
    schedule_parameter_names,
    schedule_parameter_paths,
    schedule_problems,
)
from adarl.errors import NO_VALUE, AdaRLValueError, UnknownNameError, did_you_mean, one_of
from adarl.runtime.config.local_plugins import entry_form_error
from adarl.runtime.families import FAMILIES, family

__all__ = [
    "SCHEMA_VERSION",
    "Recipe",
    "EnvConfig",
    "PerturbationConfig",
    "DeclaredParameterConfig",
    "NetworkConfig",
    "MLPConfig",
    "AlgorithmConfig",
    "SparseLayerConfig",
    "InitConfig",
    "ParsevalConfig",
    "PPOConfig",
    "RankConfig",
    "AcceptConfig",
    "LRScheduleConfig",
    "ReplayConfig",
    "WarmStartConfig",
    "CollectorConfig",
    "EvalConfig",
    "LoggingConfig",
    "CheckpointConfig",
    "GuardsConfig",
    "OutputConfig",
    "CallbackConfig",
    "ppo_problems",
    "td3_problems",
]

#: The recipe schema version this adarl reads. A recipe with a higher ``version`` is refused.
SCHEMA_VERSION = 1


class _WrongType(ValueError):
    """A value of the wrong kind (reported with the field's allowed values, like pydantic's own type errors)."""


def _not_bool(v: Any) -> Any:
    # pydantic's lax mode reads true as 1; a recipe saying `num_envs: true` is a mistake, not a number
    if isinstance(v, bool):
        raise _WrongType("a boolean is not a number")
    return v


def _advantage_norm(v: Any) -> Any:
    # algorithm.ppo.normalize_advantage was a boolean (true = per minibatch) before 'batch' existed
    if isinstance(v, bool):
        return "minibatch" if v else "none"
    return v


Int = Annotated[int, BeforeValidator(_not_bool)]
Float = Annotated[float, BeforeValidator(_not_bool)]
PosInt = Annotated[Int, Field(ge=1)]
NonNegInt = Annotated[Int, Field(ge=0)]
PosFloat = Annotated[Float, Field(gt=0)]


class _Problems(ValueError):
    """Raised inside validators: one or more (relative key, value, message) problems, formatted by the loader."""

    def __init__(self, problems: list[tuple[str, Any, str]]):
        self.problems = problems
        super().__init__("; ".join(f"{k or '.'}: {m}" for k, _, m in problems))


class _Section(BaseModel):
    """Base of every schema model: unknown keys are errors, NaN/inf are errors, numbers may be given for strings."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, coerce_numbers_to_str=True)


# ---- env


class PerturbationConfig(_Section):
    preset: Literal["paper", "low", "high", "nominal", "none"] = Field(
        "paper",
        description="Named uncertainty set from adarl.envs: 'paper' = the paper's schedule (App. D.3, A.1); "
        "'low'/'high' = Table 2's ranges (Hopper, Walker2d; other envs: adarl.envs' own boxes); 'nominal' = fixed "
        "at the centre; 'none' = the unmodified env. Ignored when schedule is set.",
    )
    schedule: dict[Any, Any] | None = Field(
        None,
        description="Explicit per-episode schedule that replaces the preset: {kind: sinusoid, center, amplitude, "
        "frequency, phase?} | {kind: uniform, low, high} | {kind: fixed, values} | {kind: list, values: [...], "
        "cycle?}; parameter names and ranges come from adarl.envs.env_parameters(env.id) and env.parameters.",
    )
    mode: Literal["consistent", "ompo"] = Field(
        "ompo",
        description="'ompo' (the paper's: OMPO's perturbation code) edits the live model's geometry in place, mass "
        "and inertia unchanged; 'consistent' (our extension) recompiles the body so mass/inertia follow the new "
        "lengths (docs/perturbed-dynamics.md).",
    )
    key: str = Field(
        "dynamics", min_length=1, description="TensorDict key under which the episode's dynamics parameters are logged."
    )

    @field_validator("schedule")
    @classmethod
    def _check_schedule(cls, v: dict | None) -> dict | None:
        if v is not None:
            problems = schedule_problems(v)
            if problems:
                raise _Problems(problems)
        return v

    def schedule_parameters(self) -> set[str]:
        """Parameter names the explicit schedule sets (empty without one)."""
        return schedule_parameter_names(self.schedule) if self.schedule else set()


def _declared_problem(err: AdaRLValueError) -> tuple[str, Any, str]:
    """An ``env.parameters.<name>: message`` error as a problem of the env section (key relative to it)."""
    where, _, message = str(err).partition(": ")
    if where.startswith("env.parameters") and message:
        return (where[len("env.") :], NO_VALUE, message)
    return ("parameters", NO_VALUE, str(err))


def _perturbation_shorthand(v: Any) -> Any:
    # `env.perturbation: none` (the section as one word) is `env.perturbation.preset: none`
    return {"preset": "none"} if v == "none" else v


class DeclaredParameterConfig(_Section):
    """One parameter a recipe declares on a MuJoCo model field (``env.parameters.<name>``)."""

    field: str = Field(
        description="MuJoCo model field the value is written to (absolutely, at every reset): body_mass, "
        "body_inertia, body_pos, geom_size, geom_pos, geom_friction, dof_damping, dof_armature, dof_frictionloss, "
        "jnt_stiffness, jnt_range, actuator_gear, actuator_ctrlrange, opt.gravity, opt.wind, opt.timestep, "
        "opt.density, opt.viscosity.",
        json_schema_extra={"allowed": "a name in adarl.envs.MODEL_FIELDS"},
    )
    index: int | str | list[int | str] | None = Field(
        None,
        description="Which entry: one per dimension of the field (body_mass: a body's index or name; geom_size: "
        "[geom, axis]; opt.gravity: 0-2; none for a scalar such as opt.timestep). Checked against the model when "
        "the env is built.",
    )
    low: Float | None = Field(None, description="Smallest value a schedule may set (null: unbounded).")
    high: Float | None = Field(None, description="Largest value a schedule may set (null: unbounded).")


class EnvConfig(_Section):
    id: str = Field(
        description="Environment id: Hopper-v5, Walker2d-v5, Ant-v5, Humanoid-v5 (paper), CartPole-v1 (discrete), "
        "another id in adarl.envs.SUPPORTED_ENVS or one an installed plugin registers (adarl.register_env), all "
        "with presets; or any other id in gymnasium's registry (Pendulum-v1, ...: perturbation preset 'none', or a "
        "schedule over env.parameters).",
        json_schema_extra={
            "allowed": "a supported env id (adarl.envs.supported_envs(): adarl's own and registered) or any id in "
            "gymnasium's registry"
        },
    )
    num_envs: PosInt = Field(1, description="Envs stepped together by the collector (a batched env when > 1).")
    parallel: bool = Field(
        False, description="Run the num_envs envs in worker processes (ParallelEnv) instead of serially."
    )
    max_episode_steps: PosInt | None = Field(
        None, description="Episode time limit; null keeps the env's own (1000 for MuJoCo, 500 for CartPole-v1)."
    )
    normalize_observations: bool = Field(
        False,
        description="Running mean/std normalisation of 'observation' (TorchRL's VecNorm, new API; SB3's "
        "VecNormalize without its reward part), off-policy loops: statistics checkpointed, frozen during "
        "evaluation, applied by load_policy and adarl export.",
    )
    parameters: dict[str, DeclaredParameterConfig] = Field(
        default_factory=dict,
        description="Perturbation parameters declared on the MuJoCo model's fields, {name: {field, index, low?, "
        "high?}}, which perturbation.schedule may then set (any MuJoCo env; docs/perturbed-dynamics.md).",
    )
    perturbation: Annotated[PerturbationConfig, BeforeValidator(_perturbation_shorthand)] = Field(
        default_factory=PerturbationConfig,
        description="Dynamics uncertainty applied during training ('none' is short for {preset: none}).",
    )

    @field_validator("id")
    @classmethod
    def _check_id(cls, v: str) -> str:
        try:
            check_any_env_id(v)  # adarl's own ids, installed plugins' (adarl.register_env), and gymnasium's
        except UnknownNameError as err:
            allowed = err.allowed
            msg = (
                f"must be a supported env: {one_of(allowed)}{did_you_mean(v, (*allowed, *gymnasium_ids()))} (or any "
                f"id in gymnasium's registry, with env.perturbation: none; or {HOW_TO_REGISTER_ENV})"
            )
            raise _Problems([("", v, msg)]) from None
        except AdaRLValueError as err:  # an installed plugin failed to load (named)
            raise _Problems([("", v, str(err))]) from None
        return v

    @field_validator("parameters")
    @classmethod
    def _check_parameters(cls, v: dict) -> dict:
        problems = []
        for name, p in v.items():
            try:
                declared_parameters({name: p.model_dump(exclude_none=True)})
            except AdaRLValueError as err:
                problems.append((str(name), NO_VALUE, str(err).split(": ", 1)[-1]))
        if problems:
            raise _Problems(problems)
        return v

    def declared(self) -> dict[str, dict] | None:
        """``env.parameters`` as plain dicts (what adarl.envs takes), None when there are none."""
        return {n: p.model_dump(exclude_none=True) for n, p in self.parameters.items()} or None

    @model_validator(mode="after")
    def _check_perturbation(self) -> EnvConfig:
        pert = self.perturbation
        sched = pert.schedule
        if self.parameters and (
            self.id in ("CartPole-v1", "LinearCartPole-v0")
            or (not is_mujoco(self.id) and gymnasium_entry_point(self.id).startswith("gymnasium.envs."))
        ):
            raise _Problems(
                [("parameters", NO_VALUE, f"declares MuJoCo model fields, but {self.id} does not simulate with MuJoCo")]
            )
        if self.parameters and sched is None:
            try:
                parameters_for(self.id, self.declared())
            except AdaRLValueError as err:  # a declared name the env already has
                raise _Problems([_declared_problem(err)]) from None
        if sched is None:
            available = [str(p) for p in preset_names(self.id)]
            if pert.preset not in available:
                raise _Problems(
                    [
                        (
                            "perturbation.preset",
                            pert.preset,
                            f"not available for {self.id}; allowed: "
                            f"{one_of(available)} (or give an explicit perturbation.schedule)"
                            + (
                                f" ({self.id} is a gymnasium env adarl has no presets for: env.perturbation: none "
                                "runs it with plain dynamics)"
                                if available == ["none"]
                                else ""
                            ),
                        )
                    ]
                )
            return self
        try:
            params = parameters_for(self.id, self.declared(), require=schedule_parameter_names(sched))
        except AdaRLValueError as err:  # a declared name the env already has
            raise _Problems([_declared_problem(err)]) from None
        known = [str(k) for k in params]
        problems = [
            (
                f"perturbation.schedule.{where}",
                NO_VALUE,
                f"unknown perturbation parameter {name!r} for "
                f"{self.id}; allowed: {one_of(known)}{did_you_mean(str(name), known)}",
            )
            for where, name in schedule_parameter_paths(sched)
            if name not in known
        ]
        if not problems:
            # adarl.envs is the authority on schedules: build it, then check every value it can produce
            try:
                validate_schedule(self.id, schedule_from_dict(_plain_copy(sched)), self.declared())
            except (ValueError, TypeError) as err:  # AdaRLValueError, or a value no schedule can take
                problems.append(("perturbation.schedule", NO_VALUE, f"rejected by adarl.envs: {err}"))
        if problems:
            raise _Problems(problems)
        return self


# ---- networks


class SparseLayerConfig(_Section):
    layer: NonNegInt | None = Field(
        None,
        description="Hidden layer replaced by the sparsification layer of Tiwari et al. (2025): a wide linear layer "
        "whose activations keep only the k largest units per input (docs/baselines/sparsification.md); null = none.",
        json_schema_extra={"allowed": "null or a hidden-layer index 0 .. len(num_cells)-1 not in low_rank_layers"},
    )
    width: PosInt = Field(1024, description="Units of the sparsification layer (the paper: 1024).")
    k: PosInt | None = Field(
        None,
        description="Active units per input; null = 2 * action_dim + 1, the paper's bound on the attainable-state "
        "manifold dimension.",
        json_schema_extra={"allowed": "null or an integer >= 1, <= width"},
    )

    @model_validator(mode="after")
    def _check_k(self) -> SparseLayerConfig:
        if self.k is not None and self.k > self.width:
            raise _Problems([("k", self.k, f"must be <= width ({self.width})")])
        return self


class InitConfig(_Section):
    scheme: Literal["default", "orthogonal", "independent_factors"] = Field(
        "default",
        description="Initial weights: 'default' = each layer's own (PyTorch's nn.Linear, LowRankLinear's factorised "
        "nn.Linear init: the balanced SVD of a dense draw); 'orthogonal' = torch.nn.init.orthogonal_ with gain on the "
        "hidden layers and head_gain on the output layer, zero biases, every critic of an ensemble drawn apart (the "
        "RNAC and Parseval originals); 'independent_factors' = each factorised layer's W1 and W2 drawn apart as the "
        "bias-free nn.Linear pair of the paper's Fig. 5 would start (Kaiming-uniform at each factor's fan-in; biases "
        "and other layers their own; needs low_rank_layers). adarl.baselines.init.",
    )
    gain: PosFloat = Field(
        1.0,
        description="Gain of the hidden layers' orthogonal init: singular values = gain, so W W^T starts at gain^2 I "
        "where rows <= columns (RNAC's trainer: 1; Parseval's code: sqrt(2) = 1.4142135623730951, i.e. s = 2). "
        "Used by scheme 'orthogonal' only.",
    )
    head_gain: PosFloat = Field(
        1.0,
        description="Gain of the output layer's orthogonal init (both originals: 0.01 for the policy head, 1 for the "
        "value head). Used by scheme 'orthogonal' only.",
    )


class MLPConfig(_Section):
    num_cells: list[PosInt] = Field(
        default_factory=lambda: [64, 64],
        min_length=1,
        description="Hidden widths; the paper uses (64, 64) for actor and critic.",
    )
    activation: Literal["relu", "tanh", "softplus", "elu", "gelu"] = Field(
        "relu", description="Hidden activation; the paper uses ReLU (Softplus gives the same results, App. D.5.4)."
    )
    low_rank_layers: list[NonNegInt] = Field(
        default_factory=lambda: [0, 1],
        description="Hidden layers factorised as W1 @ W2 (layer i maps num_cells[i-1] -> num_cells[i], layer 0 "
        "maps the input); the paper factorises the first two.",
        json_schema_extra={"allowed": "a list of distinct hidden-layer indices 0 .. len(num_cells)-1"},
    )
    rank: PosInt | list[PosInt] | None = Field(
        None,
        description="Initial rank of the factorised layers: one integer for all, or one per layer in the order of "
        "low_rank_layers (sorted), e.g. [9, 30] for the ranks another run ended with; null = full rank (the rank "
        "controller then shrinks it).",
        json_schema_extra={
            "allowed": "null, an integer >= 1 <= the smallest width of the low-rank layers, or a list of one such "
            "integer per low-rank layer (each <= that layer's width)"
        },
    )
    sparse: SparseLayerConfig = Field(
        default_factory=SparseLayerConfig, description="Optional sparsification layer (Tiwari et al. baseline)."
    )
    init: InitConfig = Field(
        default_factory=InitConfig, description="Initial weights (orthogonal for the RNAC and Parseval baselines)."
    )

    def layer_max_ranks(self) -> dict[int, int]:
        """Largest rank each low-rank layer can have, as far as known before the env's input size is: the smaller
        of the layer's input and output widths (layer 0: its output width only)."""
        n = len(self.num_cells)
        caps = {}
        for i in self.low_rank_layers:
            if 0 <= i < n:
                caps[i] = self.num_cells[i] if i == 0 else min(self.num_cells[i - 1], self.num_cells[i])
        return caps

    def layer_ranks(self) -> dict[int, int | None]:
        """``{layer: initial rank}`` of each low-rank layer (``None`` = full rank), from one rank or a list."""
        layers = sorted(self.low_rank_layers)
        if isinstance(self.rank, list):
            return dict(zip(layers, self.rank))
        return {i: self.rank for i in layers}

    def max_rank(self) -> int | None:
        """The smallest initial rank of the factorised layers if set, else the smallest known layer width (None: no
        layer)."""
        caps = self.layer_max_ranks()
        if not caps:
            return None
        ranks = [caps[i] if r is None else r for i, r in self.layer_ranks().items() if i in caps]
        return min(ranks) if ranks else min(caps.values())

    @model_validator(mode="after")
    def _check_layers(self) -> MLPConfig:
        problems: list[tuple[str, Any, str]] = []
        n = len(self.num_cells)
        bad = [i for i in self.low_rank_layers if i >= n]
        if bad:
            problems.append(
                (
                    "low_rank_layers",
                    self.low_rank_layers,
                    f"each entry must index a hidden layer, 0 .. {n - 1} (num_cells has {n} entries); "
                    f"out of range: {bad}",
                )
            )
        dup = sorted({i for i in self.low_rank_layers if self.low_rank_layers.count(i) > 1})
        if dup:
            problems.append(("low_rank_layers", self.low_rank_layers, f"entries must be distinct; repeated: {dup}"))
        if not problems and isinstance(self.rank, list):
            caps = self.layer_max_ranks()
            layers = sorted(self.low_rank_layers)
            if len(self.rank) != len(layers):
                problems.append(
                    (
                        "rank",
                        self.rank,
                        f"has {len(self.rank)} entries but low_rank_layers {layers} has {len(layers)}: give one rank "
                        "per low-rank layer (in that order) or a single integer",
                    )
                )
            else:
                for i, r in zip(layers, self.rank):
                    if r > caps[i]:
                        problems.append(
                            ("rank", self.rank, f"layer {i}'s rank {r} must be <= {caps[i]}, the layer's width")
                        )
        elif not problems and self.rank is not None and self.low_rank_layers:
            caps = self.layer_max_ranks()
            cap = min(caps.values())
            if self.rank > cap:
                layer = min(caps, key=lambda i: caps[i])
                problems.append(
                    (
                        "rank",
                        self.rank,
                        f"must be <= {cap}, the smallest width of the low-rank layers (layer {layer}: "
                        + (
                            f"{self.num_cells[layer - 1]} -> {self.num_cells[layer]}"
                            if layer
                            else f"input -> {self.num_cells[0]}"
                        )
                        + ")",
                    )
                )
        if self.init.scheme == "independent_factors" and not self.low_rank_layers:
            problems.append(
                (
                    "init.scheme",
                    self.init.scheme,
                    "'independent_factors' draws the factors of the low-rank layers, and low_rank_layers is empty: "
                    "factorise a layer or use 'default' or 'orthogonal'",
                )
            )
        sp = self.sparse.layer
        if sp is not None:
            if sp >= n:
                problems.append(
                    ("sparse.layer", sp, f"must index a hidden layer, 0 .. {n - 1} (num_cells has {n} entries)")
                )
            elif sp in self.low_rank_layers:
                problems.append(
                    (
                        "sparse.layer",
                        sp,
                        f"is also in low_rank_layers {self.low_rank_layers}; a layer is either "
                        "low-rank or the sparsification layer",
                    )
                )
        if problems:
            raise _Problems(problems)
        return self


class NetworkConfig(_Section):
    actor: MLPConfig = Field(
        default_factory=MLPConfig, description="Policy network (tanh-Gaussian or categorical head)."
    )
    critic: MLPConfig = Field(default_factory=MLPConfig, description="Q network (each of num_qvalue_nets copies).")


# ---- algorithm


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


class AcceptConfig(_Section):
    mode: Literal["projection", "always"] = Field(
        "projection",
        description="Algorithm 1's acceptance step (Sec. 4.2): 'projection' applies the rule's candidate only if the "
        "truncated network's outputs on recent transitions change by at most the tolerance (else the layer keeps "
        "its rank, r_new = r_old); 'always' applies every candidate (with rule 'energy': Eq. 10 alone, the literal "
        "ratchet that lowers every rank at every event). Rule 'fixed' is an instruction, not a proposal: always "
        "applied.",
    )
    actor_tol: Annotated[Float, Field(ge=0)] = Field(
        0.05,
        description="Largest relative change of the actor's outputs (distribution parameters) accepted at an event.",
    )
    critic_tol: Annotated[Float, Field(ge=0)] = Field(
        0.02, description="Largest relative change of each critic's Q-values on recent (state, action) pairs accepted."
    )
    search: bool = Field(
        True,
        description="When the candidate is refused, search the ranks between it and the current rank - 1 for the "
        "smallest within the tolerance (false: keep the rank at once).",
    )
    samples: PosInt = Field(
        2048, description="Most recent replay transitions the outputs are compared on (also recorded with 'always')."
    )


class RankConfig(_Section):
    enabled: bool = Field(True, description="Run the adaptive rank controller (false = plain or fixed-rank SAC).")
    truncate: bool = Field(
        True,
        description="false: the events run every `interval` steps and do everything an event that changed a rank "
        "does (LR warm-up from zero, replay.warm_start) but truncate nothing: the control arm that separates AdaRL's "
        "restarts from its truncations (recipes/baselines/*_sac_restarts.yaml); the networks may then be dense.",
    )
    rule: str = Field(
        "energy",
        description="Rank rule, a registered name (adarl.register_rank_rule; installed packages add names through "
        "the 'adarl.plugins' entry-point group): 'energy' = paper Eq. 10; 'energy_inclusive' = smallest rank with "
        "energy >= beta; 'ratio' = Eq. 33 (App. D.4); 'fixed' = target_rank; 'policy_fit' = fit/penalty trade-off "
        "with lam; a plugin's rule takes rule_options (docs/adding-a-component.md).",
        json_schema_extra={
            "allowed": "a registered rank rule name ('energy', 'energy_inclusive', 'ratio', 'fixed', 'policy_fit', "
            "or one an installed plugin adds)"
        },
    )
    rule_options: dict[str, Any] = Field(
        default_factory=dict,
        description="A registered plugin rule's own keyword arguments (its pydantic model: unknown keys, types and "
        "ranges are checked like every other key; every default is written into the run's recipe.yaml). adarl's "
        "own rules have none: they read beta, target_rank and lam.",
    )
    beta: Annotated[Float, Field(gt=0, lt=1)] = Field(
        0.98, description="Energy threshold of the energy and ratio rules (paper: 0.98)."
    )
    target_rank: PosInt | None = Field(None, description="Rank the 'fixed' rule truncates to (required by it).")
    lam: Annotated[Float, Field(ge=0)] = Field(1e-3, description="Rank penalty of the 'policy_fit' rule.")
    interval: PosInt = Field(
        1_000_000,
        description="Optimisation steps between rank events (paper: 1e6; Walker2d 0.7e6).",
    )
    scope: Literal["actor", "critic", "both"] = Field(
        "both", description="Networks the controller truncates (Table 2: 'both' is the most reliable)."
    )
    min_rank: PosInt = Field(1, description="Never truncate below this rank.")
    target_mode: Literal["sync", "project"] = Field(
        "sync",
        description="Target critics after a truncation: 'sync' copies the new online factors; 'project' applies "
        "the same change of basis to the target factors (keeps the Polyak lag).",
    )
    num_threads: Literal["auto"] | PosInt | None = Field(
        "auto",
        description="Torch threads during a rank event (restored afterwards; training is paused anyway): 'auto' = "
        "every core this process may use, or OMP_NUM_THREADS when set (adarl experiment -j N>1 sets 1, Ray and SLURM "
        "cpus_per_run); null = the run's own (algorithm.num_threads). Events on wide layers are float64 "
        "eigendecompositions that scale with cores.",
    )
    accept: AcceptConfig = Field(
        default_factory=AcceptConfig,
        description="Acceptance step: whether the rule's candidate rank is applied (docs/rank-rules.md).",
    )

    @field_validator("rule")
    @classmethod
    def _check_rule_name(cls, v: str) -> str:
        try:
            plugins.rank_rule(v)
        except UnknownNameError as err:
            msg = f"must be one of {one_of(err.allowed)}{did_you_mean(v, err.allowed)}{err.hint}"
            raise _Problems([("", v, msg)]) from None
        except AdaRLValueError as err:  # an installed plugin failed to load (named)
            raise _Problems([("", v, str(err))]) from None
        return v

    @model_validator(mode="after")
    def _check_rule(self) -> RankConfig:
        spec = plugins.rank_rule(self.rule)
        if spec.builtin and self.rule_options:
            raise _Problems(
                [
                    (
                        "rule_options",
                        _plain_copy(self.rule_options),
                        f"must be empty with adarl's own rule {self.rule!r}: set rank.beta, rank.target_rank or "
                        "rank.lam instead (rule_options are a registered plugin rule's keyword arguments)",
                    )
                ]
            )
        self.rule_options = _validated_options(
            spec.options, self.rule_options, "rule_options", f"rank rule {self.rule!r}"
        )
        if self.rule == "fixed":
            if self.target_rank is None:
                raise _Problems([("target_rank", None, "rule 'fixed' needs target_rank: an integer >= 1")])
            if self.target_rank < self.min_rank:
                raise _Problems([("target_rank", self.target_rank, f"must be >= min_rank ({self.min_rank})")])
        return self


class LRScheduleConfig(_Section):
    warmup_steps: NonNegInt = Field(
        2000, description="Linear warm-up from 0 after the start and after every rank event (paper: 2000 steps)."
    )
    cosine: bool = Field(True, description="Cosine decay after the warm-up over the planned optimisation steps.")
    min_factor: Annotated[Float, Field(ge=0, le=1)] = Field(
        0.0, description="Floor of the cosine decay as a fraction of lr."
    )


class WarmStartConfig(_Section):
    mode: Literal["refill", "prefill", "reset", "keep"] = Field(
        "refill",
        description="Replay buffer after a rank event (App. D.5.3): 'refill' empties it and collects `frames` with "
        "the truncated policy; 'prefill' adds `frames` fresh ones to the old data; 'reset' empties it and optimisation "
        "resumes on the few new samples (Fig. 9's control); 'keep' leaves it.",
    )
    frames: NonNegInt = Field(10_000, description="Frames collected before optimisation resumes after a rank event.")
    count_frames: bool = Field(
        True,
        description="Warm-start frames count towards collector.total_frames (true: never past it; a warm start "
        "with less of the budget left collects only what is left), or not (false: every arm of a comparison then "
        "trains on the same frames and takes the same optimisation steps; summary.json reports the warm-start frames "
        "either way).",
    )


class ReplayConfig(_Section):
    size: PosInt = Field(1_000_000, description="Replay buffer capacity in transitions (paper: 1e6).")
    storage: Literal["memory", "memmap"] = Field(
        "memory",
        description="Replay storage: 'memory' (LazyTensorStorage) or 'memmap' (LazyMemmapStorage, on disk in the "
        "run folder; for Humanoid's 1e6 transitions on small machines).",
    )
    warm_start: WarmStartConfig = Field(default_factory=WarmStartConfig, description="Warm-start after rank events.")


class CollectorConfig(_Section):
    total_frames: PosInt = Field(description="Environment frames of the whole run (paper: 3.5e6).")
    frames_per_batch: PosInt = Field(1000, description="Frames per collector batch; optimisation runs between batches.")
    init_random_frames: NonNegInt = Field(
        10_000, description="Uniform-random actions before the policy acts (TorchRL rounds up to a batch multiple)."
    )
    lean: Literal["auto"] | bool = Field(
        "auto",
        description="LeanCollector (adarl.fast.collector: same env, policy sampled straight from the actor network, "
        "no Collector overhead); 'auto' = on for one env with a TanhNormal actor; false = torchrl Collector.",
    )
    overlap: Literal["thread", "process"] | bool = Field(
        False,
        description="Collect the next batch while the updates of the current one run (needs the lean collector): "
        "'process' in a worker process (a second core), 'thread' (or true) in a background thread. The next batch "
        "then comes from the policy as it was one batch earlier, as with TorchRL's asynchronous collectors; both "
        "modes give the same batches, and exact resume still holds.",
    )


class EvalConfig(_Section):
    interval: PosInt = Field(10_000, description="Frames between evaluations.")
    episodes: PosInt = Field(5, description="Episodes per evaluation (deterministic policy).")
    max_steps: PosInt = Field(1000, description="Step cap of an evaluation episode.")
    nominal: bool = Field(
        True, description="Evaluate on the nominal dynamics, the centre of the uncertainty set (paper)."
    )


class LoggingConfig(_Section):
    backends: list[Literal["csv", "tensorboard", "wandb"]] = Field(
        default_factory=lambda: ["csv"],
        description="TorchRL loggers; csv needs nothing, tensorboard and wandb their optional packages.",
    )
    wandb_project: str = Field("adarl", min_length=1, description="wandb project name.")
    wandb_mode: Literal["offline", "online", "disabled"] = Field(
        "offline", description="wandb mode; offline by default so nothing leaves the machine unasked."
    )
    log_interval: PosInt = Field(1000, description="Frames between training-metric log lines.")

    @field_validator("backends")
    @classmethod
    def _distinct(cls, v: list[str]) -> list[str]:
        dup = sorted({b for b in v if v.count(b) > 1})
        if dup:
            raise _Problems([("", v, f"entries must be distinct; repeated: {dup}")])
        return v


class CheckpointConfig(_Section):
    interval: PosInt = Field(50_000, description="Frames between checkpoints.")
    keep_last: PosInt = Field(3, description="Checkpoints kept (older ones are deleted).")
    replay_buffer: bool = Field(
        True, description="Also dump the replay buffer (needed for an exact resume; up to GBs on disk for 1e6 frames)."
    )
    keep_best: bool = Field(
        True, description="Also keep checkpoints/best.pt, the policy of the best nominal evaluation."
    )


class GuardsConfig(_Section):
    on_nonfinite: Literal["stop", "rollback"] = Field(
        "stop",
        description="NaN/inf in a loss, gradient or parameter: 'stop' the run (the last good checkpoint is kept) or "
        "'rollback' to the last checkpoint with the learning rate scaled by lr_factor.",
    )
    lr_factor: Annotated[Float, Field(gt=0, lt=1)] = Field(
        0.5,
        description="Learning-rate multiplier applied at each rollback.",
        json_schema_extra={"allowed": "a number in (0, 1)"},
    )
    max_rollbacks: NonNegInt = Field(3, description="Rollbacks allowed before the run stops anyway.")


class OutputConfig(_Section):
    root: str = Field("runs", min_length=1, description="Folder that holds run folders.")
    dir: Annotated[str, Field(min_length=1)] | None = Field(
        None, description="Explicit run folder; null = <root>/<name>-<YYYYmmdd-HHMMSS>."
    )


class CallbackConfig(_Section):
    """One entry of ``callbacks``: a registered callback and its options (docs/callbacks.md)."""

    name: str = Field(
        description="Callback, a registered name (adarl.register_callback, in a module the recipe's plugins list "
        "names or an installed package): 'stop_on_return' = stop after the evaluation whose mean return reaches "
        "options.threshold (SB3's StopTrainingOnRewardThreshold).",
        json_schema_extra={"allowed": "a registered callback name ('stop_on_return', or one a plugin adds)"},
    )
    options: dict[str, Any] = Field(
        default_factory=dict,
        description="The callback's own keyword arguments (its pydantic model: unknown keys, types and ranges are "
        "checked like every other key; every default is written into the run's recipe.yaml).",
    )

    @field_validator("name")
    @classmethod
    def _check_name(cls, v: str) -> str:
        try:
            plugins.callback(v)
        except UnknownNameError as err:
            msg = f"not a registered callback; allowed: {one_of(err.allowed)}{did_you_mean(v, err.allowed)}{err.hint}"
            raise _Problems([("", v, msg)]) from None
        except AdaRLValueError as err:  # an installed plugin failed to load (named)
            raise _Problems([("", v, str(err))]) from None
        return v

    @model_validator(mode="after")
    def _check_options(self) -> CallbackConfig:
        spec = plugins.callback(self.name)
        self.options = _validated_options(spec.options, self.options, "options", f"callback {self.name!r}")
        return self


# ---- the recipe


class Recipe(_Section):
    """One run, completely described. Build it with :func:`load_recipe` (files, extends, overrides) or
    :func:`validate_recipe` (a mapping); both raise :class:`~adarl.errors.RecipeError` on any problem."""

    name: str = Field(
        pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}$",
        description="Run name, used in the run folder's name; defaults to the recipe file's stem (not inherited).",
        json_schema_extra={"allowed": "1-100 characters from letters, digits and _ . + - (not starting with . - +)"},
    )
    description: str = Field("", description="One line shown by `adarl recipes` (not inherited through extends).")
    version: Annotated[Int, Field(ge=1)] = Field(
        1,
        description=f"Recipe schema version; this adarl reads up to {SCHEMA_VERSION}.",
        json_schema_extra={
            "allowed": f"an integer from 1 to {SCHEMA_VERSION}"
            if SCHEMA_VERSION > 1
            else "1 (the only schema version so far)"
        },
    )
    plugins: list[Annotated[str, Field(min_length=1)]] = Field(
        default_factory=list,
        description="Local Python modules imported before the recipe is validated, whose import registers what it "
        "names (register_algorithm, register_env, register_rank_rule, register_callback): a module name (beside the "
        "recipe file, else on PYTHONPATH) or a path to a .py file relative to the recipe. Recorded with each file's "
        "sha256 in the run folder's plugins.json: resume refuses a changed or missing module (docs/custom-loss.md).",
        json_schema_extra={"allowed": "a list of module names or .py paths"},
    )
    seed: Annotated[Int, Field(ge=0, le=2**32 - 1)] = Field(0, description="Seed of Python, NumPy, torch and the envs.")
    device: str = Field(
        "cpu",
        pattern=r"^(cpu|cuda(:[0-9]+)?)$",
        description="Torch device of networks, buffer and collector.",
        json_schema_extra={"allowed": "'cpu', 'cuda' or 'cuda:N'"},
    )
    env: EnvConfig = Field(description="Environment and its dynamics perturbation.")
    network: NetworkConfig = Field(default_factory=NetworkConfig, description="Actor and critic MLPs.")
    algorithm: AlgorithmConfig = Field(default_factory=AlgorithmConfig, description="SAC hyperparameters.")
    rank: RankConfig = Field(default_factory=RankConfig, description="Adaptive rank controller (paper Alg. 1).")
    lr_schedule: LRScheduleConfig = Field(default_factory=LRScheduleConfig, description="Warm-up + cosine LR.")
    replay: ReplayConfig = Field(default_factory=ReplayConfig, description="Replay buffer.")
    collector: CollectorConfig = Field(description="Frame budget and batching.")
    eval: EvalConfig = Field(default_factory=EvalConfig, description="Periodic evaluation.")
    logging: LoggingConfig = Field(default_factory=LoggingConfig, description="Metric loggers.")
    checkpoint: CheckpointConfig = Field(default_factory=CheckpointConfig, description="Checkpoints for resume.")
    guards: GuardsConfig = Field(default_factory=GuardsConfig, description="What to do when training diverges.")
    callbacks: list[CallbackConfig] = Field(
        default_factory=list,
        description="Training callbacks, called at the trainer's hook points in this order; any may stop the run "
        "early, which the run folder records (docs/callbacks.md).",
        json_schema_extra={"allowed": "a list of {name: <registered callback>, options: {...}}"},
    )
    output: OutputConfig = Field(default_factory=OutputConfig, description="Where the run folder goes.")

    @field_validator("plugins", mode="before")
    @classmethod
    def _plugin_entries_have_a_form(cls, v: Any) -> Any:
        """The loader's own check of an entry's form (one rule), so that a recipe validated here loads from its file."""
        for entry in v if isinstance(v, list) else []:
            if (problem := entry_form_error(entry)) is not None:
                raise AdaRLValueError(f"{entry!r}: {problem}")
        return v

    @field_validator("version")
    @classmethod
    def _check_version(cls, v: int) -> int:
        if v > SCHEMA_VERSION:
            raise _Problems([("", v, _newer_version_message(v))])
        return v

    @model_validator(mode="after")
    def _cross_checks(self) -> Recipe:
        p: list[tuple[str, Any, str]] = []
        if self.algorithm.batch_size > self.replay.size:
            p.append(
                ("algorithm.batch_size", self.algorithm.batch_size, f"must be <= replay.size ({self.replay.size})")
            )
        w = self.replay.warm_start
        if w.frames > self.replay.size and self.rank.enabled:  # warm starts only follow rank events
            p.append(("replay.warm_start.frames", w.frames, f"must be <= replay.size ({self.replay.size})"))
        c = self.collector
        if c.init_random_frames > c.total_frames:
            p.append(
                (
                    "collector.init_random_frames",
                    c.init_random_frames,
                    f"must be <= collector.total_frames ({c.total_frames})",
                )
            )
        if c.frames_per_batch > c.total_frames:
            p.append(
                (
                    "collector.frames_per_batch",
                    c.frames_per_batch,
                    f"must be <= collector.total_frames ({c.total_frames})",
                )
            )
        if self.algorithm.compile and self.algorithm.fused is False:
            p.append(
                ("algorithm.compile", True, "needs algorithm.fused: true or 'auto' (it compiles the fused update)")
            )
        if self.algorithm.backward != "auto" and self.algorithm.fused is False:
            p.append(
                (
                    "algorithm.backward",
                    self.algorithm.backward,
                    "needs algorithm.fused: true or 'auto' (it is the fused update's backward); allowed with "
                    "fused: false: 'auto'",
                )
            )
        p += self._algorithm_checks()
        r = self.rank
        if r.enabled and r.truncate:
            scoped = ["actor", "critic"] if r.scope == "both" else [r.scope]
            for net in scoped:
                mlp: MLPConfig = getattr(self.network, net)
                if not mlp.low_rank_layers:
                    p.append(
                        (
                            f"network.{net}.low_rank_layers",
                            mlp.low_rank_layers,
                            f"is empty but rank.scope={r.scope!r} asks the controller to truncate the {net}; "
                            "list the layers to factorise, or set rank.enabled=false or another rank.scope",
                        )
                    )
                    continue
                cap = mlp.max_rank()
                if r.min_rank > cap:
                    p.append(("rank.min_rank", r.min_rank, f"must be <= the {net}'s largest possible rank ({cap})"))
                if r.rule == "fixed" and r.target_rank is not None and r.target_rank > cap:
                    p.append(
                        ("rank.target_rank", r.target_rank, f"must be <= the {net}'s largest possible rank ({cap})")
                    )
        if p:
            raise _Problems(p)
        return self

    def _algorithm_checks(self) -> list[tuple[str, Any, str]]:
        """The combinations the recipe's loop refuses (its family's checks: :func:`ppo_problems`,
        :func:`td3_problems`), the keys another loop owns left at their defaults, and the algorithms' own."""
        alg, env = self.algorithm, self.env
        mine = family(alg.base)
        p: list[tuple[str, Any, str]] = mine.problems(self)
        for other in FAMILIES.entries.values():
            if other.base == alg.base:
                continue
            for key in other.owns:
                value, default = getattr(alg, key), AlgorithmConfig.model_fields[key].default
                if value != default:
                    p.append(
                        (
                            f"algorithm.{key}",
                            value,
                            f"is implemented for {other.base.upper()}'s loop ({other.base!r}) only; algorithm.name "
                            f"{alg.name!r} runs on the {alg.base!r} loop; allowed there: {default!r}",
                        )
                    )
        if alg.name == "rnac_ds":
            if env.num_envs != 1:
                p.append(
                    ("env.num_envs", env.num_envs, "must be 1 with algorithm.name='rnac_ds' (it steps one MuJoCo env)")
                )
            if not is_mujoco(env.id):
                p.append(("algorithm.name", "rnac_ds", f"needs a MuJoCo env; {env.id} is not one"))
        return p


def ppo_problems(recipe: Recipe) -> list[tuple[str, Any, str]]:
    """The ``ppo`` family's combinations (the RNAC baselines' loop, adarl.runtime.trainers.ppo)."""
    p: list[tuple[str, Any, str]] = []
    alg, env = recipe.algorithm, recipe.env
    if recipe.rank.enabled:
        p.append(
            (
                "rank.enabled",
                True,
                f"must be false with algorithm.name={alg.name!r} (on the PPO loop): it runs the RNAC "
                "baselines without rank adaptation (docs/custom-loss.md shows RankAdapter on another loss)",
            )
        )
    if env.id == "CartPole-v1":
        p.append(("algorithm.name", alg.name, f"needs a continuous-action env; {env.id} is discrete (use 'sac')"))
    if env.normalize_observations:
        p.append(
            (
                "env.normalize_observations",
                True,
                f"is the off-policy loops' option; algorithm.name {alg.name!r} runs on the PPO loop, which "
                "normalises inside its networks: algorithm.ppo.obs_norm (allowed here: false)",
            )
        )
    if alg.ppo.minibatch_size > recipe.collector.frames_per_batch:
        p.append(
            (
                "algorithm.ppo.minibatch_size",
                alg.ppo.minibatch_size,
                f"must be <= collector.frames_per_batch ({recipe.collector.frames_per_batch})",
            )
        )
    return p


def td3_problems(recipe: Recipe) -> list[tuple[str, Any, str]]:
    """The ``td3`` family's combinations: box actions, and none of SAC's fast path (TorchRL's plain path)."""
    p: list[tuple[str, Any, str]] = []
    alg, env = recipe.algorithm, recipe.env
    if env.id in ("CartPole-v1", "LinearCartPole-v0"):
        p.append(("algorithm.name", alg.name, f"needs a continuous-action env; {env.id} is discrete (use 'sac')"))
    for key, value, allowed in (
        ("algorithm.fused", alg.fused, "'auto' or false"),
        ("algorithm.compile", alg.compile, "false"),
        ("collector.lean", recipe.collector.lean, "'auto' or false"),
    ):
        if value is True:
            p.append(
                (
                    key,
                    True,
                    f"is SAC's fast path (a fused SACLoss update, a TanhNormal actor); algorithm.name "
                    f"{alg.name!r} runs on the 'td3' loop, TorchRL's plain path; allowed: {allowed}",
                )
            )
    return p


def sac_problems(recipe: Recipe) -> list[tuple[str, Any, str]]:
    """The ``sac`` family's combinations for TQC, CrossQ and REDQ (adarl.runtime.builders.sac_variants): box actions,
    TorchRL's plain path (the fused update computes SACLoss only), and what their losses have no use for."""
    p: list[tuple[str, Any, str]] = []
    alg, env = recipe.algorithm, recipe.env
    variant = plugins.sac_variant(alg.name)
    if variant is None:
        return p
    if env.id in ("CartPole-v1", "LinearCartPole-v0"):
        p.append(("algorithm.name", alg.name, f"needs a continuous-action env; {env.id} is discrete (use 'sac')"))
    for key, value, allowed in (
        ("algorithm.fused", alg.fused, "'auto' or false"),
        ("algorithm.compile", alg.compile, "false"),
        ("algorithm.backward", alg.backward, "'auto'"),
    ):
        if value is True or (key == "algorithm.backward" and value != "auto"):
            p.append(
                (
                    key,
                    value,
                    f"is the fused SAC update's, which computes SACLoss only; algorithm.name {alg.name!r} runs "
                    f"TorchRL's {variant} on its plain path; allowed: {allowed}",
                )
            )
    if variant == "TQCLoss" and alg.loss_function != "l2":
        p.append(
            (
                "algorithm.loss_function",
                alg.loss_function,
                "is not used by TQCLoss, whose critic loss is the quantile Huber loss; allowed: 'l2' (the default)",
            )
        )
    if variant == "CrossQLoss":
        for key, default in (("polyak", "factors"), ("tau", AlgorithmConfig.model_fields["tau"].default)):
            if getattr(alg, key) != default:
                p.append(
                    (
                        f"algorithm.{key}",
                        getattr(alg, key),
                        f"moves target critics, and CrossQ has none; allowed: {default!r} (the default)",
                    )
                )
    return p


def _validated_options(model: type[BaseModel], options: Any, key: str, what: str) -> dict:
    """``options`` checked by a registered options model (an algorithm's, a rank rule's: unknown key, type, range,
    each a problem under ``key``), returned with every default filled in (what recipe.yaml records)."""
    try:
        return model.model_validate(_plain_copy(options)).model_dump(mode="python")
    except ValidationError as err:
        allowed = list(model.model_fields)
        problems = []
        for e in err.errors():
            msg = e["msg"]
            if e["type"] == "extra_forbidden":
                msg = (
                    f"unknown option of {what}; allowed: {one_of(allowed) if allowed else 'none (it has no options)'}"
                    f"{did_you_mean(str(e['loc'][-1]), allowed)}"
                )
            problems.append((f"{key}.{'.'.join(str(x) for x in e['loc'])}", e.get("input", NO_VALUE), msg))
        raise _Problems(problems) from None


def _show(v: Any, limit: int = 80) -> str:
    s = "null" if v is None else ("true" if v else "false") if isinstance(v, bool) else repr(v)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _plain_copy(obj: Any) -> Any:
    """A deep copy made of plain dicts and lists (what the env module and YAML expect)."""
    if isinstance(obj, Mapping):
        return {k: _plain_copy(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_plain_copy(v) for v in obj]
    return obj


def _newer_version_message(v: Any) -> str:
    return (
        f"this recipe needs schema version {v}, but this adarl reads versions up to {SCHEMA_VERSION}; "
        "upgrade adarl or lower `version`"
    )
