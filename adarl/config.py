"""Recipes: the YAML schema of an adarl run and the loader that reads, merges and validates it.

A recipe is a YAML file (``recipes/<name>.yaml`` or any path) that describes one run completely: env and
perturbation schedule, networks, SAC, the rank controller, learning-rate schedule, replay buffer, collector,
evaluation, logging, checkpoints and the output folder. Two libraries split the work:

* **OmegaConf** reads the YAML (its loader is PyYAML's *safe* loader, with alias-expansion limits and
  duplicate-key detection), merges ``extends`` chains (dicts merge, lists replace) and applies dotlist overrides
  (``rank.beta=0.9``), the same style TorchRL's Hydra-based scripts use.
* **pydantic v2** validates the merged document against the models below (every model forbids unknown keys),
  and :class:`~adarl.errors.RecipeError` reports each problem with its key path, the offending value and what is
  allowed, with a "did you mean" suggestion for typos.

Interpolation: plain node references (``${collector.total_frames}``) are allowed and resolved after merging;
resolver calls (``${oc.env:HOME}``, ``${oc.decode:...}`` or any custom resolver) are rejected, so a recipe never
depends on the process environment and the resolved copy saved in a run folder is exactly what ran.

Public API: :func:`load_recipe`, :func:`validate_recipe`, :func:`list_recipes`, :func:`recipes_dir`,
:func:`recipe_to_yaml`, :func:`save_resolved`, :func:`describe_schema`, :class:`Recipe` and its sections.
"""

from __future__ import annotations

import difflib
import math
import os
import re
import types
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

from adarl.errors import RecipeError

__all__ = [
    "SCHEMA_VERSION",
    "RECIPES_PATH_ENV",
    "Recipe",
    "EnvConfig",
    "PerturbationConfig",
    "NetworkConfig",
    "MLPConfig",
    "AlgorithmConfig",
    "SparseLayerConfig",
    "InitConfig",
    "ParsevalConfig",
    "PPOConfig",
    "RNACConfig",
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
    "load_recipe",
    "validate_recipe",
    "list_recipes",
    "recipes_dir",
    "recipe_to_yaml",
    "save_resolved",
    "describe_schema",
]

#: The recipe schema version this adarl reads. A recipe with a higher ``version`` is refused.
SCHEMA_VERSION = 1
#: Extra recipe folders, searched before the shipped ``recipes/`` (``os.pathsep``-separated).
RECIPES_PATH_ENV = "ADARL_RECIPES_PATH"

_MAX_FILE_BYTES = 1 << 20  # a recipe is a few KB; refuse anything absurd before parsing it
_MAX_YAML_NODES = 10_000  # OmegaConf's alias-expansion cap, pinned (its env var could lift it)
_MAX_EXTENDS_DEPTH = 32
_SCHEDULE_PATH = "env.perturbation.schedule"

# ----------------------------------------------------------------------------------------------- schema types

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


_NO_VALUE = object()


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
        "cycle?}; parameter names and ranges come from adarl.envs.env_parameters(env.id).",
    )
    mode: Literal["consistent", "ompo"] = Field(
        "consistent",
        description="'consistent' recompiles the body so mass/inertia follow the new lengths; 'ompo' edits the "
        "live model in place like OMPO's code (the paper's perturbation code).",
    )
    key: str = Field(
        "dynamics", min_length=1, description="TensorDict key under which the episode's dynamics parameters are logged."
    )

    @field_validator("schedule")
    @classmethod
    def _check_schedule(cls, v: dict | None) -> dict | None:
        if v is not None:
            _check_schedule_structure(v)
        return v

    def schedule_parameters(self) -> set[str]:
        """Parameter names the explicit schedule sets (empty without one)."""
        return _schedule_parameter_names(self.schedule) if self.schedule else set()


class EnvConfig(_Section):
    id: str = Field(
        description="Environment id: Hopper-v5, Walker2d-v5, Ant-v5, Humanoid-v5 (paper), CartPole-v1 (discrete), "
        "or another id in adarl.envs.SUPPORTED_ENVS.",
        json_schema_extra={"allowed": "a supported env id (adarl.envs.SUPPORTED_ENVS)"},
    )
    num_envs: PosInt = Field(1, description="Envs stepped together by the collector (a batched env when > 1).")
    parallel: bool = Field(False, description="Run the num_envs envs in worker processes (ParallelEnv) instead of serially.")
    max_episode_steps: PosInt | None = Field(
        None, description="Episode time limit; null keeps the env's own (1000 for MuJoCo, 500 for CartPole-v1)."
    )
    perturbation: PerturbationConfig = Field(
        default_factory=PerturbationConfig, description="Dynamics uncertainty applied during training."
    )

    @field_validator("id")
    @classmethod
    def _check_id(cls, v: str) -> str:
        supported = _supported_envs()
        if supported is not None and v not in supported:
            raise _Problems([("", v, f"must be a supported env: {_one_of(supported)}{_suggest(v, supported)}")])
        return v

    @model_validator(mode="after")
    def _check_perturbation(self) -> EnvConfig:
        api = _envs_module()
        if api is None:
            return self
        pert = self.perturbation
        sched = pert.schedule
        if sched is None:
            preset_names = getattr(api, "preset_names", None)
            if preset_names is not None:
                try:
                    available = [str(p) for p in preset_names(self.id)]
                except Exception as err:
                    raise _Problems([("id", self.id, f"cannot list its presets: {err}")]) from None
                if pert.preset not in available:
                    raise _Problems(
                        [
                            (
                                "perturbation.preset",
                                pert.preset,
                                f"not available for {self.id}; allowed: {_one_of(available)} "
                                "(or give an explicit perturbation.schedule)",
                            )
                        ]
                    )
            return self
        problems: list[tuple[str, Any, str]] = []
        env_parameters = getattr(api, "env_parameters", None)
        if env_parameters is not None:
            try:
                known = [str(k) for k in env_parameters(self.id)]
            except Exception as err:  # the env module's own error, reported as a recipe problem
                raise _Problems([("id", self.id, f"cannot list its perturbation parameters: {err}")]) from None
            for where, name in _schedule_parameter_paths(sched):
                if name not in known:
                    problems.append(
                        (
                            f"perturbation.schedule.{where}",
                            _NO_VALUE,
                            f"unknown perturbation parameter {name!r} for {self.id}; allowed: {_one_of(known)}"
                            f"{_suggest(str(name), known)}",
                        )
                    )
        schedule_from_dict = getattr(api, "schedule_from_dict", None)
        if not problems and schedule_from_dict is not None:
            # the env module is the authority on schedules: build it, then check every value it can produce
            try:
                built = schedule_from_dict(_plain(sched))
                validate_schedule = getattr(api, "validate_schedule", None)
                if validate_schedule is not None:
                    validate_schedule(self.id, built)
            except Exception as err:
                problems.append(("perturbation.schedule", _NO_VALUE, f"rejected by adarl.envs: {err}"))
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
    scheme: Literal["default", "orthogonal"] = Field(
        "default",
        description="Initial weights: 'default' = each layer's own (PyTorch's nn.Linear, LowRankLinear's factorised "
        "nn.Linear init); 'orthogonal' = torch.nn.init.orthogonal_ with gain on the hidden layers and head_gain on the "
        "output layer, zero biases, every critic of an ensemble drawn apart (the RNAC and Parseval originals; "
        "adarl.baselines.init).",
    )
    gain: PosFloat = Field(
        1.0,
        description="Gain of the hidden layers' orthogonal init: singular values = gain, so W W^T starts at gain^2 I "
        "where rows <= columns (RNAC's trainer: 1; Parseval's code: sqrt(2) = 1.4142135623730951, i.e. s = 2). "
        "Ignored with scheme 'default'.",
    )
    head_gain: PosFloat = Field(
        1.0,
        description="Gain of the output layer's orthogonal init (both originals: 0.01 for the policy head, 1 for the "
        "value head). Ignored with scheme 'default'.",
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
    rank: PosInt | None = Field(
        None,
        description="Initial rank of the factorised layers; null = full rank (the rank controller then shrinks it).",
        json_schema_extra={"allowed": "null or an integer >= 1, <= the smallest width of the low-rank layers"},
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

    def max_rank(self) -> int | None:
        """The initial rank of the factorised layers if set, else the smallest known layer width (None: no layer)."""
        caps = self.layer_max_ranks()
        if not caps:
            return None
        return self.rank if self.rank is not None else min(caps.values())

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
        if not problems and self.rank is not None and self.low_rank_layers:
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
        sp = self.sparse.layer
        if sp is not None:
            if sp >= n:
                problems.append(("sparse.layer", sp, f"must index a hidden layer, 0 .. {n - 1} (num_cells has {n} entries)"))
            elif sp in self.low_rank_layers:
                problems.append(
                    ("sparse.layer", sp, f"is also in low_rank_layers {self.low_rank_layers}; a layer is either "
                     "low-rank or the sparsification layer")
                )
        if problems:
            raise _Problems(problems)
        return self


class NetworkConfig(_Section):
    actor: MLPConfig = Field(default_factory=MLPConfig, description="Policy network (tanh-Gaussian or categorical head).")
    critic: MLPConfig = Field(default_factory=MLPConfig, description="Q network (each of num_qvalue_nets copies).")


# ---- algorithm


class ParsevalConfig(_Section):
    enabled: bool = Field(False, description="Add Parseval regularisation (Chung et al., 2024) to the loss.")
    lam: Annotated[Float, Field(gt=0)] = Field(
        1e-4, description="Weight lambda of lam * (base_width/width)^2 * sum ||W W^T - s I||_F^2 (tuned in {1e-3, 1e-4, 1e-5})."
    )
    s: PosFloat = Field(2.0, description="Target squared row norm s of the hidden weights (the paper: 2).")
    base_width: PosInt = Field(64, description="Reference width of the (base_width/width)^2 scaling (the paper: 64).")
    diagonal: bool = Field(False, description="Learnable per-unit gain after every hidden linear layer (optional layer).")
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


class RNACConfig(_Section):
    mode: Literal["none", "ipm", "ds"] = Field(
        "none",
        description="RNAC's robust critic (Zhou et al., 2023), PPO only: 'ipm' shifts the reward by kappa*||theta_critic|| "
        "in GAE; 'ds' picks the worst of num_candidates noisy next states with probability 1/(m+1); 'none' = plain PPO.",
    )
    kappa: Annotated[Float, Field(ge=0)] = Field(1e-5, description="RNAC-IPM's radius: reward shift per unit of ||theta_critic||.")
    num_candidates: PosInt = Field(2, description="RNAC-DS's m: noisy next states probed per step.")
    noise: Annotated[Float, Field(ge=0)] = Field(5e-3, description="RNAC-DS's actuation noise half-width, U[-noise, noise].")


class AlgorithmConfig(_Section):
    name: Literal["sac", "ppo"] = Field(
        "sac",
        description="Base RL algorithm: 'sac' as in the paper (DiscreteSAC for discrete-action envs); 'ppo' = TorchRL's "
        "ClipPPOLoss + GAE, the RNAC baselines' base (continuous actions; SAC-only keys are ignored).",
    )
    gamma: Annotated[Float, Field(gt=0, le=1)] = Field(0.99, description="Discount factor.")
    tau: Annotated[Float, Field(gt=0, le=1)] = Field(0.005, description="Polyak rate of the target critics.")
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
        "auto", description="Entropy target of the alpha tuning; 'auto' = -action_dim (continuous) or TorchRL's default."
    )
    max_grad_norm: PosFloat | None = Field(None, description="Clip gradient norm per optimiser; null = no clipping.")
    fused: Literal["auto"] | bool = Field(
        "auto",
        description="Fused SAC update (adarl.fast_sac: same losses as SACLoss, batched critics, fused Adam, foreach "
        "target update); 'auto' = on for continuous actions, TorchRL's SACLoss path for discrete; false = SACLoss.",
    )
    compile: bool = Field(
        False, description="torch.compile the fused SAC update (needs fused; one recompilation per rank event)."
    )
    backward: Literal["auto", "manual", "autograd"] = Field(
        "auto",
        description="Backward of the fused update: 'manual' (adarl.manual_backward: the gradients written out by "
        "hand, no autograd graph), 'autograd' (loss.backward()); 'auto' = manual where the networks allow it.",
    )
    num_threads: PosInt | None = Field(
        None, description="torch.set_num_threads for the run; null = leave torch's setting (1 is best at (64, 64) on CPU)."
    )
    parseval: ParsevalConfig = Field(default_factory=ParsevalConfig, description="Parseval regularisation baseline.")
    ppo: PPOConfig = Field(default_factory=PPOConfig, description="PPO hyperparameters (algorithm.name=ppo).")
    rnac: RNACConfig = Field(default_factory=RNACConfig, description="RNAC's robust critic (algorithm.name=ppo).")


class AcceptConfig(_Section):
    mode: Literal["projection", "always"] = Field(
        "projection",
        description="Algorithm 1's acceptance step (Sec. 4.2): 'projection' applies the rule's candidate only if the "
        "truncated network's outputs on recent transitions change by at most the tolerance (else the layer keeps "
        "its rank, r_new = r_old); 'always' applies every candidate (with rule 'energy': Eq. 10 alone, the literal "
        "ratchet that lowers every rank at every event). Rule 'fixed' is an instruction, not a proposal: always applied.",
    )
    actor_tol: Annotated[Float, Field(ge=0)] = Field(
        0.05, description="Largest relative change of the actor's outputs (distribution parameters) accepted at an event."
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
    rule: Literal["energy", "energy_inclusive", "ratio", "fixed", "policy_fit"] = Field(
        "energy",
        description="Rank rule: 'energy' = paper Eq. 10; 'energy_inclusive' = smallest rank with energy >= beta; "
        "'ratio' = Eq. 33 (App. D.4); 'fixed' = target_rank; 'policy_fit' = fit/penalty trade-off with lam.",
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
    num_threads: PosInt | None = Field(
        None,
        description="Torch threads during a rank event (restored afterwards); null = the run's own "
        "(algorithm.num_threads). Events on wide layers are float64 eigendecompositions that scale with cores.",
    )
    accept: AcceptConfig = Field(
        default_factory=AcceptConfig,
        description="Acceptance step: whether the rule's candidate rank is applied (docs/rank-rules.md).",
    )

    @model_validator(mode="after")
    def _check_rule(self) -> RankConfig:
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
        description="Warm-start frames count towards collector.total_frames (true), or not (false: every arm of a "
        "comparison then trains on the same frames and takes the same optimisation steps; summary.json reports the "
        "warm-start frames either way).",
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
        description="LeanCollector (adarl.lean_collector: same env, policy sampled straight from the actor network, "
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
    nominal: bool = Field(True, description="Evaluate on the nominal dynamics, the centre of the uncertainty set (paper).")


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
    keep_best: bool = Field(True, description="Also keep checkpoints/best.pt, the policy of the best nominal evaluation.")


class GuardsConfig(_Section):
    on_nonfinite: Literal["stop", "rollback"] = Field(
        "stop",
        description="NaN/inf in a loss, gradient or parameter: 'stop' the run (the last good checkpoint is kept) or "
        "'rollback' to the last checkpoint with the learning rate scaled by lr_factor.",
    )
    lr_factor: Annotated[Float, Field(gt=0, lt=1)] = Field(
        0.5, description="Learning-rate multiplier applied at each rollback.",
        json_schema_extra={"allowed": "a number in (0, 1)"},
    )
    max_rollbacks: NonNegInt = Field(3, description="Rollbacks allowed before the run stops anyway.")


class OutputConfig(_Section):
    root: str = Field("runs", min_length=1, description="Folder that holds run folders.")
    dir: Annotated[str, Field(min_length=1)] | None = Field(
        None, description="Explicit run folder; null = <root>/<name>-<YYYYmmdd-HHMMSS>."
    )


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
            "allowed": f"an integer from 1 to {SCHEMA_VERSION}" if SCHEMA_VERSION > 1 else "1 (the only schema version so far)"
        },
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
    output: OutputConfig = Field(default_factory=OutputConfig, description="Where the run folder goes.")

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
            p.append(("algorithm.batch_size", self.algorithm.batch_size, f"must be <= replay.size ({self.replay.size})"))
        w = self.replay.warm_start
        if w.frames > self.replay.size and self.rank.enabled:  # warm starts only follow rank events
            p.append(("replay.warm_start.frames", w.frames, f"must be <= replay.size ({self.replay.size})"))
        c = self.collector
        if c.init_random_frames > c.total_frames:
            p.append(
                ("collector.init_random_frames", c.init_random_frames, f"must be <= collector.total_frames ({c.total_frames})")
            )
        if c.frames_per_batch > c.total_frames:
            p.append(
                ("collector.frames_per_batch", c.frames_per_batch, f"must be <= collector.total_frames ({c.total_frames})")
            )
        if self.algorithm.compile and self.algorithm.fused is False:
            p.append(("algorithm.compile", True, "needs algorithm.fused: true or 'auto' (it compiles the fused update)"))
        if self.algorithm.backward != "auto" and self.algorithm.fused is False:
            p.append(("algorithm.backward", self.algorithm.backward,
                      "needs algorithm.fused: true or 'auto' (it is the fused update's backward); allowed with "
                      "fused: false: 'auto'"))
        p += self._algorithm_checks()
        r = self.rank
        if r.enabled:
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
        """PPO/RNAC combinations (the baselines' loop, adarl.training_ppo)."""
        p: list[tuple[str, Any, str]] = []
        alg, env = self.algorithm, self.env
        if alg.name == "ppo":
            if self.rank.enabled:
                p.append(("rank.enabled", True, "must be false with algorithm.name='ppo': the PPO loop runs the RNAC "
                          "baselines without rank adaptation (docs/custom-loss.md shows RankAdapter on another loss)"))
            if env.id == "CartPole-v1":
                p.append(("algorithm.name", "ppo", f"needs a continuous-action env; {env.id} is discrete (use 'sac')"))
            if alg.ppo.minibatch_size > self.collector.frames_per_batch:
                p.append(("algorithm.ppo.minibatch_size", alg.ppo.minibatch_size,
                          f"must be <= collector.frames_per_batch ({self.collector.frames_per_batch})"))
        elif alg.rnac.mode != "none":
            p.append(("algorithm.rnac.mode", alg.rnac.mode, "needs algorithm.name='ppo' (RNAC is built on PPO)"))
        if alg.rnac.mode == "ds":
            if env.num_envs != 1:
                p.append(("env.num_envs", env.num_envs, "must be 1 with algorithm.rnac.mode='ds' (it steps one MuJoCo env)"))
            if env.id == "CartPole-v1":
                p.append(("algorithm.rnac.mode", "ds", f"needs a MuJoCo env; {env.id} is not one"))
        return p


# ------------------------------------------------------------------------------------ env module (lazy import)


def _envs_module():
    """``adarl.envs`` (imported lazily: it pulls in TorchRL and MuJoCo), or None while it does not exist."""
    try:
        from adarl import envs
    except ModuleNotFoundError as err:
        if err.name in ("adarl.envs",):
            return None
        raise _Problems([("", _NO_VALUE, f"cannot check the env: importing adarl.envs failed: {err}")]) from None
    except Exception as err:
        raise _Problems([("", _NO_VALUE, f"cannot check the env: importing adarl.envs failed: {err!r}")]) from None
    return envs


def _supported_envs() -> list[str] | None:
    api = _envs_module()
    supported = getattr(api, "SUPPORTED_ENVS", None) if api is not None else None
    if supported is None:
        return None
    return [str(s) for s in supported]


# ------------------------------------------------------------------------------------------ schedule structure

_SCHEDULE_KINDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    # kind: (required keys, optional keys), besides `kind`; the same format as adarl.envs.schedule_from_dict
    "sinusoid": (("center", "amplitude", "frequency"), ("phase",)),
    "uniform": (("low", "high"), ()),
    "fixed": (("values",), ()),
    "list": (("values",), ("cycle",)),
}


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _plain(obj: Any) -> Any:
    """A deep copy made of plain dicts and lists (what the env module and YAML expect)."""
    if isinstance(obj, Mapping):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_plain(v) for v in obj]
    return obj


def _check_param_map(where: str, m: Any, problems: list) -> bool:
    if not isinstance(m, Mapping):
        problems.append((where, m, "must be a mapping {parameter: number}"))
        return False
    ok = True
    for k, x in m.items():
        if not isinstance(k, str) or not k:
            problems.append((where, m, f"parameter names must be non-empty strings, got {k!r}"))
            ok = False
        elif not _is_number(x):
            problems.append((f"{where}.{k}", x, "must be a finite number"))
            ok = False
    return ok


def _same_params(where: str, m: Mapping, ref: Mapping, ref_name: str, problems: list) -> None:
    if set(m) != set(ref):
        problems.append((where, m, f"must name the same parameters as {ref_name}: {sorted(map(str, ref))}"))


def _check_schedule_structure(s: Mapping) -> None:
    """Shape of an explicit schedule, with key paths in the messages (values and names are checked against the
    env in :class:`EnvConfig`, by adarl.envs itself)."""
    problems: list[tuple[str, Any, str]] = []
    kind = s.get("kind", _NO_VALUE)
    kinds = list(_SCHEDULE_KINDS)
    if kind is _NO_VALUE:
        raise _Problems([("kind", _NO_VALUE, f"is required: one of {_one_of(kinds)}")])
    if not isinstance(kind, str) or kind not in _SCHEDULE_KINDS:
        raise _Problems([("kind", kind, f"must be one of {_one_of(kinds)}{_suggest(str(kind), kinds)}")])
    required, optional = _SCHEDULE_KINDS[kind]
    allowed = ["kind", *required, *optional]
    for k in s:
        if k not in allowed:
            problems.append(
                (str(k), s[k], f"unknown key for a {kind} schedule; allowed: {_one_of(allowed)}{_suggest(str(k), allowed)}")
            )
    for k in required:
        if k not in s:
            problems.append((k, _NO_VALUE, f"is required by a {kind} schedule"))
    if problems:
        raise _Problems(problems)
    if kind == "sinusoid":
        ok_c = _check_param_map("center", s["center"], problems)
        if _check_param_map("amplitude", s["amplitude"], problems) and ok_c:
            _same_params("amplitude", s["amplitude"], s["center"], "center", problems)
        for key in ("frequency", "phase"):
            if key not in s:
                continue
            v = s[key]
            if isinstance(v, Mapping):
                if _check_param_map(key, v, problems) and ok_c:
                    _same_params(key, v, s["center"], "center", problems)
            elif not _is_number(v):
                problems.append((key, v, "must be a finite number (radians per episode) or a mapping {parameter: number}"))
    elif kind == "uniform":
        ok_lo = _check_param_map("low", s["low"], problems)
        if _check_param_map("high", s["high"], problems) and ok_lo:
            if set(s["low"]) != set(s["high"]):
                _same_params("high", s["high"], s["low"], "low", problems)
            else:
                for k, lo in s["low"].items():
                    if s["high"][k] < lo:
                        problems.append((f"high.{k}", s["high"][k], f"must be >= low.{k} ({lo})"))
    elif kind == "fixed":
        _check_param_map("values", s["values"], problems)
    else:  # list
        vals = s["values"]
        if not isinstance(vals, list) or not vals:
            problems.append(("values", vals, "must be a non-empty list of mappings {parameter: number}"))
        else:
            oks = [_check_param_map(f"values[{i}]", m, problems) for i, m in enumerate(vals)]
            if all(oks):
                for i, m in enumerate(vals[1:], 1):
                    _same_params(f"values[{i}]", m, vals[0], "values[0]", problems)
        if "cycle" in s and not isinstance(s["cycle"], bool):
            problems.append(("cycle", s["cycle"], "must be true or false"))
    if problems:
        raise _Problems(problems)


def _schedule_parameter_paths(s: Mapping) -> list[tuple[str, Any]]:
    out = []
    for field in ("center", "amplitude", "frequency", "phase", "low", "high"):
        if isinstance(s.get(field), Mapping):
            out += [(f"{field}.{k}", k) for k in s[field]]
    vals = s.get("values")
    if isinstance(vals, Mapping):
        out += [(f"values.{k}", k) for k in vals]
    elif isinstance(vals, list):
        for i, m in enumerate(vals):
            if isinstance(m, Mapping):
                out += [(f"values[{i}].{k}", k) for k in m]
    seen, unique = set(), []
    for where, k in out:  # report each unknown name once, at its first use
        if k not in seen:
            seen.add(k)
            unique.append((where, k))
    return unique


def _schedule_parameter_names(s: Mapping) -> set[str]:
    return {str(k) for _, k in _schedule_parameter_paths(s)}


# ------------------------------------------------------------------------------------ describing the schema


def _one_of(options: Iterable[Any]) -> str:
    return ", ".join(repr(o) for o in options)


def _suggest(word: str, options: Iterable[Any]) -> str:
    opts = [str(o) for o in options]
    match = difflib.get_close_matches(str(word), opts, n=1, cutoff=0.6)
    if not match:  # case-only typos ('hopper-v5') score low in difflib
        match = [o for o in opts if o.lower() == str(word).lower()][:1]
    return f"; did you mean {match[0]!r}?" if match else ""


def _constraints(meta: Iterable[Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m in meta:
        for sub in getattr(m, "metadata", None) or [m]:  # FieldInfo inside Annotated carries annotated_types objects
            for attr in ("gt", "ge", "lt", "le", "min_length", "pattern"):
                v = getattr(sub, attr, None)
                if v is not None and attr not in out:
                    out[attr] = v
    return out


def _fmt_num(x: Any) -> str:
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}" if isinstance(x, float) else str(x)


def _bounds(c: dict[str, Any]) -> str:
    lo = ("(", c["gt"]) if "gt" in c else ("[", c["ge"]) if "ge" in c else None
    hi = (")", c["lt"]) if "lt" in c else ("]", c["le"]) if "le" in c else None
    if lo and hi:
        return f" in {lo[0]}{_fmt_num(lo[1])}, {_fmt_num(hi[1])}{hi[0]}"
    if lo:
        return f" {'>' if lo[0] == '(' else '>='} {_fmt_num(lo[1])}"
    if hi:
        return f" {'<' if hi[0] == ')' else '<='} {_fmt_num(hi[1])}"
    return ""


def _describe_type(tp: Any, meta: Iterable[Any] = (), plural: bool = False) -> str:
    meta = list(meta)
    origin = get_origin(tp)
    if origin is Annotated:
        base, *extra = get_args(tp)
        return _describe_type(base, [*meta, *extra], plural)
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        parts = [_describe_type(a, meta, plural) for a in args if a is not type(None)]
        if type(None) in args:
            parts.append("null")
        return " or ".join(parts)
    c = _constraints(meta)
    if origin is Literal:
        vals = _one_of(get_args(tp))
        if len(get_args(tp)) == 1:
            return vals
        return f"values from {vals}" if plural else f"one of {vals}"
    if origin is list or tp is list:
        (item,) = get_args(tp) or (Any,)
        s = f"a {'non-empty ' if c.get('min_length') else ''}list of {_describe_type(item, plural=True)}"
        return s
    if tp is bool:
        return "true or false"
    if tp is int:
        return ("integers" if plural else "an integer") + _bounds(c)
    if tp is float:
        return ("numbers" if plural else "a number") + _bounds(c)
    if tp is str:
        s = "strings" if plural else "a string"
        if c.get("pattern"):
            s += f" matching {c['pattern']}"
        elif c.get("min_length"):
            s = "non-empty " + s if plural else "a non-empty string"
        return s
    if origin is dict or tp is dict:
        return "mappings" if plural else "a mapping"
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return f"a mapping with keys {', '.join(tp.model_fields)}"
    return "values" if plural else "a value"


def _describe_field(field) -> str:
    extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
    if "allowed" in extra:
        return str(extra["allowed"])
    return _describe_type(field.annotation, field.metadata)


def _model_of(tp: Any) -> type[BaseModel] | None:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    return tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def _list_item(tp: Any) -> Any | None:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    if get_origin(tp) in (Union, types.UnionType):
        lists = [a for a in get_args(tp) if _list_item(a) is not None]
        return _list_item(lists[0]) if lists else None
    if get_origin(tp) is list:
        return get_args(tp)[0]
    return None


def _is_free_mapping(tp: Any) -> bool:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    if get_origin(tp) in (Union, types.UnionType):
        return any(_is_free_mapping(a) for a in get_args(tp))
    return tp is dict or get_origin(tp) is dict


def describe_schema(model: type[BaseModel] = None, prefix: str = "") -> list[tuple[str, Any, str, str]]:
    """Every leaf key of the recipe schema as ``(key path, default, allowed values, why)`` rows.

    A required key has the default ``...`` (Ellipsis). ``docs/recipes.md`` lists the same rows."""
    from pydantic_core import PydanticUndefined

    model = model or Recipe
    rows = []
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        sub = _model_of(field.annotation)
        if sub is not None:
            rows += describe_schema(sub, path + ".")
            continue
        if field.default_factory is not None:
            default = field.default_factory()
        elif field.default is PydanticUndefined:
            default = ...
        else:
            default = field.default
        rows.append((path, default, _describe_field(field), field.description or ""))
    return rows


# ---------------------------------------------------------------------------------- formatting pydantic errors


def _show(v: Any, limit: int = 80) -> str:
    s = "null" if v is None else ("true" if v else "false") if isinstance(v, bool) else repr(v)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _walk_loc(loc: Sequence[Any]) -> tuple[str, Any, type[BaseModel] | None, int]:
    """Follow a pydantic error location through the schema.

    Returns (human key path, the field or list-item type reached, the model containing the last named key, how
    many loc items were consumed). Union-branch tags (``'float'``, ``"literal['auto']"``) stop the walk."""
    model: type[BaseModel] | None = Recipe
    tp: Any = None
    field = None
    parent: type[BaseModel] | None = None
    parts: list[str] = []
    used = 0
    for item in loc:
        if model is not None and isinstance(item, str) and item in model.model_fields:
            field = model.model_fields[item]
            parent = model
            parts.append(("." if parts else "") + item)
            tp = field.annotation
            model = _model_of(tp)
        elif model is None and isinstance(item, int) and tp is not None and _list_item(tp) is not None:
            tp = _list_item(tp)
            field = None
            parts.append(f"[{item}]")
            model = _model_of(tp)
        else:
            break
        used += 1
    return "".join(parts), (field if field is not None else tp), parent, used


def _join_path(base: str, rel: str) -> str:
    if not rel:
        return base
    if not base:
        return rel
    return base + ("" if rel.startswith("[") else ".") + rel


def _format_errors(err: ValidationError) -> list[str]:
    lines: list[str] = []
    seen: set[str] = set()
    for e in err.errors(include_url=False):
        loc = tuple(e.get("loc", ()))
        etype = e.get("type", "")
        inp = e.get("input", _NO_VALUE)
        ctx = e.get("ctx") or {}
        path, target, parent, used = _walk_loc(loc)
        if etype == "value_error" and isinstance(ctx.get("error"), _Problems):
            for rel, value, msg in ctx["error"].problems:
                full = _join_path(path, rel)
                shown = "" if value is _NO_VALUE else f" = {_show(value)}"
                line = f"{full or '<recipe>'}{shown}: {msg}"
                if line not in seen:
                    seen.add(line)
                    lines.append(line)
            continue
        if etype in ("extra_forbidden", "invalid_key"):
            bad = loc[used] if used < len(loc) else loc[-1] if loc else "?"
            container = _model_of(getattr(target, "annotation", target)) if path else Recipe
            allowed = list(container.model_fields) if container is not None else []
            full = _join_path(path, str(bad))
            where = f" under {path!r}" if path else " at the top level"
            what = f"value {_show(inp)}" if etype == "extra_forbidden" else f"{_show(inp)} is not a string"
            line = (
                f"{full}: unknown key ({what}); allowed keys{where}: {', '.join(allowed)}"
                f"{_suggest(str(bad).split('.')[0], allowed)}"
            )
            if isinstance(bad, str) and "." in bad:
                line += " (in YAML, nest keys as mappings; dotted keys are for overrides)"
        else:
            key = path or "<recipe>"
            if key in seen:  # one message per key (a union reports one error per branch)
                continue
            seen.add(key)
            allowed = (
                _describe_field(target)
                if hasattr(target, "annotation")
                else _describe_type(target) if target is not None else "a mapping with keys " + ", ".join(Recipe.model_fields)
            )
            if etype == "missing":
                line = f"{key}: required key is missing; expected {allowed}"
            elif etype == "value_error" and not isinstance(ctx.get("error"), _WrongType):
                line = f"{key} = {_show(inp)}: {ctx.get('error', e.get('msg'))}"
            else:
                line = f"{key} = {_show(inp)}: must be {allowed}"
                lits = _literal_options(getattr(target, "annotation", target))
                if lits and isinstance(inp, str):
                    line += _suggest(inp, lits)
        if line not in seen:
            seen.add(line)
            lines.append(line)
    return lines


def _literal_options(tp: Any) -> list[str]:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    if get_origin(tp) is Literal:
        return [str(a) for a in get_args(tp)]
    if get_origin(tp) in (Union, types.UnionType):
        return [x for a in get_args(tp) for x in _literal_options(a)]
    return []


def _raise_problems(label: str, lines: list[str]) -> None:
    if len(lines) == 1:
        raise RecipeError(f"invalid recipe {label}: {lines[0]}")
    body = "\n".join(f"  - {ln}" for ln in lines)
    raise RecipeError(f"invalid recipe {label}: {len(lines)} problems\n{body}")


def _newer_version_message(v: Any) -> str:
    return (
        f"this recipe needs schema version {v}, but this adarl reads versions up to {SCHEMA_VERSION}; "
        "upgrade adarl or lower `version`"
    )


def validate_recipe(data: Mapping[str, Any], *, label: str = "<mapping>") -> Recipe:
    """Validate a plain mapping (already merged and resolved) into a :class:`Recipe`.

    Raises :class:`RecipeError` listing every problem with its key path, value and allowed values."""
    if not isinstance(data, Mapping):
        raise RecipeError(f"invalid recipe {label}: the top level must be a mapping of keys to values, got {_show(data)}")
    if "extends" in data:
        raise RecipeError(
            f"invalid recipe {label}: extends = {_show(data['extends'])}: `extends` is resolved by load_recipe; "
            "validate_recipe takes an already merged mapping"
        )
    try:
        return Recipe.model_validate(dict(data))
    except ValidationError as err:
        _raise_problems(label, _format_errors(err) or [str(err)])
    except _Problems as err:  # raised outside pydantic's wrapping (e.g. an import failure)
        _raise_problems(label, [f"{k or '<recipe>'}: {m}" for k, _, m in err.problems])
    except RecipeError:
        raise
    except Exception as err:  # pragma: no cover - a validator bug must still surface as a recipe error
        raise RecipeError(f"invalid recipe {label}: {type(err).__name__}: {err}") from None
    raise AssertionError("unreachable")  # pragma: no cover


# ------------------------------------------------------------------------------------------ finding recipes


#: Subfolder of a recipes folder holding experiment specs (``adarl experiment``), not recipes.
EXPERIMENTS_DIR = "experiments"


def _package_recipes_dir() -> Path:
    """The shipped recipes: ``adarl/recipes/`` in an installed wheel (package data mapped from the source tree's
    top-level ``recipes/``, see pyproject.toml), else that top-level folder (a source checkout, an editable install)."""
    here = Path(__file__).resolve().parent
    installed = here / "recipes"
    return installed if installed.is_dir() else here.parent / "recipes"


def recipes_dir() -> list[Path]:
    """Folders searched for recipe names: each entry of ``$ADARL_RECIPES_PATH`` (``os.pathsep``-separated), then
    the shipped ``recipes/`` folder next to the package. Earlier folders shadow later ones."""
    dirs: list[Path] = []
    for entry in os.environ.get(RECIPES_PATH_ENV, "").split(os.pathsep):
        if entry.strip():
            dirs.append(Path(entry).expanduser())
    dirs.append(_package_recipes_dir())
    return dirs


def _is_path_like(s: str) -> bool:
    return s.endswith((".yaml", ".yml"))


def _valid_name(name: str) -> bool:
    p = PurePosixPath(name.replace("\\", "/"))
    return bool(name) and not p.is_absolute() and ".." not in p.parts and "" not in p.parts and "\x00" not in name


def _available_names() -> list[str]:
    return [n for n, _ in _scan_recipes(with_descriptions=False)]


def _find_by_name(name: str, first: Path | None = None, exclude: Path | None = None) -> Path | None:
    if not _valid_name(name):
        return None
    candidates = ([first] if first is not None else []) + recipes_dir()
    for d in candidates:
        p = d / f"{name}.yaml"
        try:
            if p.is_file() and (exclude is None or p.resolve() != exclude):
                return p
        except OSError:
            continue
    return None


def _locate(name_or_path: Any) -> Path:
    if isinstance(name_or_path, os.PathLike):
        name_or_path = os.fspath(name_or_path)
    if not isinstance(name_or_path, str) or not name_or_path.strip():
        raise RecipeError(f"recipe must be a shipped recipe name or a .yaml path, got {_show(name_or_path)}")
    s = name_or_path
    if _is_path_like(s):
        p = Path(s).expanduser()
        if not p.is_file():
            raise RecipeError(f"recipe file {s!r} not found" + ("" if not p.exists() else " (not a file)"))
        return p
    found = _find_by_name(s)
    if found is not None:
        return found
    p = Path(s).expanduser()
    if p.is_file():
        return p
    names = _available_names()
    raise RecipeError(
        f"no recipe named {s!r} in {', '.join(str(d) for d in recipes_dir())}; available: "
        f"{', '.join(names) or '(none)'}{_suggest(s, names)} (or pass a path to a .yaml file)"
    )


# ---------------------------------------------------------------------------------------------- reading YAML


def _yaml_loader():
    from omegaconf._yaml import get_yaml_loader  # OmegaConf's safe loader (yaml.SafeLoader/CSafeLoader based)

    return get_yaml_loader(max_yaml_expanded_nodes=_MAX_YAML_NODES)


def _parse_yaml(text: str, where: str) -> Any:
    try:
        return yaml.load(text, Loader=_yaml_loader())
    except yaml.YAMLError as err:
        raise RecipeError(f"{where}: YAML syntax error: {_one_line(err)}") from None
    except RecursionError:
        raise RecipeError(f"{where}: YAML nested too deeply") from None
    except Exception as err:
        raise RecipeError(f"{where}: cannot parse YAML: {_one_line(err)}") from None


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


def _read_file(path: Path) -> dict:
    where = str(path)
    try:
        size = path.stat().st_size
        if size > _MAX_FILE_BYTES:
            raise RecipeError(f"{where}: file too large for a recipe ({size} bytes > {_MAX_FILE_BYTES})")
        text = path.read_text(encoding="utf-8")
    except RecipeError:
        raise
    except UnicodeDecodeError as err:
        raise RecipeError(f"{where}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise RecipeError(f"cannot read recipe {where}: {err.strerror or err}") from None
    data = _parse_yaml(text, where)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise RecipeError(
            f"{where}: the top level must be a mapping of keys to values (like `env: {{id: Hopper-v5}}`), "
            f"got {type(data).__name__} {_show(data)}"
        )
    return data


def _check_version(data: Mapping, where: str) -> None:
    v = data.get("version")
    if isinstance(v, int) and not isinstance(v, bool) and v > SCHEMA_VERSION:
        raise RecipeError(f"{where}: version = {v}: {_newer_version_message(v)}")


# ----------------------------------------------------------------------------------------- interpolations


def _resolver_calls(s: str) -> list[str] | None:
    """Resolver names called in string ``s`` (``[]`` for plain text or node interpolations); None if ``s`` is
    not a valid OmegaConf string."""
    if "${" not in s:
        return []
    from omegaconf.grammar_parser import OmegaConfGrammarParser, parse

    try:
        tree = parse(s)  # the rule OmegaConf itself uses for string values
    except Exception:  # GrammarParseError, or anything the vendored ANTLR runtime raises
        return None
    found: list[str] = []

    def visit(node):
        if isinstance(node, OmegaConfGrammarParser.InterpolationResolverContext):
            rn = node.resolverName()
            found.append(rn.getText() if rn is not None else "?")
        for child in getattr(node, "getChildren", lambda: ())():
            visit(child)

    visit(tree)
    return found


def _check_strings(obj: Any, path: str, where: str) -> None:
    """Reject resolver calls and malformed interpolations anywhere in ``obj``."""
    if isinstance(obj, str):
        calls = _resolver_calls(obj)
        if calls is None:
            raise RecipeError(
                f"{where}: {path or '<value>'} = {_show(obj)}: malformed interpolation; write ${{key.path}} to "
                "reference another key, or \\${ for a literal '${'"
            )
        if calls:
            raise RecipeError(
                f"{where}: {path or '<value>'} = {_show(obj)}: resolver interpolations ({', '.join(sorted(set(calls)))}) "
                "are not allowed in recipes (a run must not depend on the environment); only references to other "
                "keys like ${collector.total_frames} are"
            )
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_strings(v, _join_path(path, str(k)), where)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _check_strings(v, f"{path}[{i}]", where)


# --------------------------------------------------------------------------------------- merging and extends


def _to_omegaconf(data: dict, where: str):
    from omegaconf import OmegaConf

    try:
        return OmegaConf.create(data)
    except Exception as err:
        raise RecipeError(f"{where}: unsupported value: {_one_line(err)}") from None


def _default_name(path: Path) -> str:
    name = re.sub(r"[^A-Za-z0-9_.+-]", "_", path.stem)[:100]
    return name if name and name[0] not in ".+-" else f"r{name}"[:100]


def _resolve_extends(ext: Any, child: Path, where: str) -> Path:
    if not isinstance(ext, str) or not ext.strip():
        raise RecipeError(f"{where}: extends = {_show(ext)}: must be a recipe name or a path to a .yaml file")
    me = child.resolve()
    if _is_path_like(ext):
        p = Path(ext).expanduser()
        if not p.is_absolute():
            p = child.parent / p
        if not p.is_file():
            raise RecipeError(f"{where}: extends = {ext!r}: file {str(p)!r} not found")
        return p
    found = _find_by_name(ext, first=child.parent, exclude=me)
    if found is None:
        names = _available_names()
        raise RecipeError(
            f"{where}: extends = {ext!r}: no recipe of that name next to this file or in "
            f"{', '.join(str(d) for d in recipes_dir())}; available: {', '.join(names) or '(none)'}{_suggest(ext, names)}"
        )
    return found


def _load_chain(path: Path, stack: tuple[Path, ...] = ()):
    """The merged (unresolved) OmegaConf config of ``path`` and everything it extends."""
    from omegaconf import OmegaConf

    where = str(path)
    real = path.resolve()
    if real in stack:
        chain = " -> ".join(str(p) for p in (*stack, real))
        raise RecipeError(f"extends cycle: {chain}")
    if len(stack) >= _MAX_EXTENDS_DEPTH:
        raise RecipeError(f"{where}: extends chain deeper than {_MAX_EXTENDS_DEPTH} files")
    data = _read_file(path)
    _check_version(data, where)
    _check_strings(data, "", where)
    ext = data.pop("extends", None)
    # name and description describe this file; they are never inherited from the base
    data.setdefault("name", _default_name(path))
    data.setdefault("description", "")
    if ext is None:
        return _to_omegaconf(data, where)
    base = _load_chain(_resolve_extends(ext, path, where), (*stack, real))
    child = _to_omegaconf(data, where)
    if OmegaConf.select(child, _SCHEDULE_PATH, default=_NO_VALUE) is not _NO_VALUE and OmegaConf.select(
        base, _SCHEDULE_PATH, default=None
    ) is not None:
        # an explicit schedule replaces the base's whole schedule (a sinusoid's keys make no sense in a list)
        OmegaConf.update(base, _SCHEDULE_PATH, None, merge=False)
    try:
        return OmegaConf.merge(base, child)
    except Exception as err:
        raise RecipeError(f"{where}: cannot merge onto its base {ext!r}: {_one_line(err)}") from None


# segments after the first may hold ':' and '-' (perturbation parameters such as mass_scale:torso)
_OVERRIDE_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z0-9_:-]+|\[[0-9]+\])*$")


def _split_key(key: str) -> list[str | int]:
    out: list[str | int] = []
    for tok in re.findall(r"\[([0-9]+)\]|\.?([A-Za-z0-9_:-]+)", key):
        idx, name = tok
        out.append(int(idx) if idx else int(name) if name.isdigit() else name)
    return out


def _check_override_key(key: str, parts: list[str | int], override: str) -> None:
    model: type[BaseModel] | None = Recipe
    tp: Any = None
    walked: list[str] = []
    for part in parts:
        if model is not None:
            if isinstance(part, int) or part not in model.model_fields:
                allowed = list(model.model_fields)
                path = ".".join(walked)
                full = _join_path(path, str(part))
                where = f" under {path!r}" if path else " at the top level"
                raise RecipeError(
                    f"override {override!r}: unknown key {full!r}; allowed keys{where}: {', '.join(allowed)}"
                    f"{_suggest(str(part), allowed)}"
                )
            tp = model.model_fields[part].annotation
            model = _model_of(tp)
            walked.append(part)
        elif _is_free_mapping(tp):
            return  # inside a free-form mapping (the schedule): its own validator checks the keys
        elif _list_item(tp) is not None and isinstance(part, int):
            tp = _list_item(tp)
            model = _model_of(tp)
            walked.append(f"[{part}]")
        else:
            path = ""
            for w in walked:
                path = _join_path(path, w)
            raise RecipeError(f"override {override!r}: {path!r} is a single value, it has no key {part!r}")


def _apply_overrides(cfg, overrides: Sequence[str]) -> None:
    from omegaconf import DictConfig, OmegaConf

    if isinstance(overrides, str):
        raise RecipeError(f"overrides must be a list of 'key=value' strings, got the single string {overrides!r}")
    try:
        items = list(overrides)
    except TypeError:
        raise RecipeError(f"overrides must be a list of 'key=value' strings, got {_show(overrides)}") from None
    for ov in items:
        if not isinstance(ov, str):
            raise RecipeError(f"override {_show(ov)}: must be a 'key=value' string")
        if ov.strip()[:1] in ("+", "~"):
            raise RecipeError(
                f"override {ov!r}: Hydra's +/~ prefixes are not supported; every key already exists in the schema, "
                "write key=value (key=null to clear an optional value)"
            )
        if "=" not in ov:
            raise RecipeError(f"override {ov!r}: expected key=value (e.g. rank.beta=0.95)")
        key, text = ov.split("=", 1)
        key = key.strip()
        if not _OVERRIDE_KEY.match(key):
            raise RecipeError(
                f"override {ov!r}: bad key {key!r}; expected a dotted path like rank.beta or network.actor.num_cells[0]"
            )
        parts = _split_key(key)
        _check_override_key(key, parts, ov)
        value = _parse_yaml(text, f"override {ov!r}") if text.strip() else None
        _check_strings(value, key, f"override {ov!r}")
        try:
            # give a null intermediate (an unset schedule) a mapping to write into
            node = cfg
            for part in parts[:-1]:
                nxt = node[part] if isinstance(node, DictConfig) and part in node else None
                if isinstance(node, DictConfig) and (part not in node or nxt is None):
                    node[part] = {}
                    nxt = node[part]
                node = nxt if nxt is not None else node[part]
            dotted = ".".join(f"[{p}]" if isinstance(p, int) else p for p in parts).replace(".[", "[")
            OmegaConf.update(cfg, dotted, value, merge=key != _SCHEDULE_PATH)
        except RecipeError:
            raise
        except Exception as err:
            raise RecipeError(f"override {ov!r}: cannot apply: {_one_line(err)}") from None


def _resolve(cfg, label: str) -> dict:
    from omegaconf import OmegaConf
    from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

    try:
        data = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    except MissingMandatoryValue as err:
        key = getattr(err, "full_key", "") or "?"
        raise RecipeError(f"invalid recipe {label}: {key}: required value not set ('???')") from None
    except OmegaConfBaseException as err:
        key = getattr(err, "full_key", "") or "?"
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise RecipeError(f"invalid recipe {label}: {key}: cannot resolve interpolation: {msg}") from None
    except RecursionError:
        raise RecipeError(f"invalid recipe {label}: interpolations nested too deeply") from None
    except Exception as err:
        raise RecipeError(f"invalid recipe {label}: cannot resolve: {_one_line(err)}") from None
    return data


# --------------------------------------------------------------------------------------------- public API


def load_recipe(name_or_path: str | os.PathLike, overrides: Sequence[str] = ()) -> Recipe:
    """Load, merge (``extends``), override and validate a recipe.

    ``name_or_path`` is a recipe name (``recipes/<name>.yaml``, searched in :func:`recipes_dir`) or a path to a
    ``.yaml`` file. ``overrides`` are OmegaConf dotlist strings (``rank.beta=0.9``,
    ``network.actor.num_cells=[32,32]``); each key must exist in the schema. Any problem raises
    :class:`~adarl.errors.RecipeError`."""
    path = _locate(name_or_path)
    label = f"{_default_name(path)!r} ({path})"
    if overrides:
        label += f" with overrides {list(overrides) if not isinstance(overrides, str) else overrides!r}"
    try:
        cfg = _load_chain(path)
        _apply_overrides(cfg, overrides or ())
        data = _resolve(cfg, label)
    except RecipeError:
        raise
    except RecursionError:
        raise RecipeError(f"invalid recipe {label}: nested too deeply") from None
    except Exception as err:  # nothing raw escapes (an OmegaConf corner we did not foresee)
        raise RecipeError(f"invalid recipe {label}: {type(err).__name__}: {_one_line(err)}") from None
    return validate_recipe(data, label=label)


def _scan_recipes(with_descriptions: bool = True) -> list[tuple[str, str]]:
    found: dict[str, str] = {}
    for d in recipes_dir():
        try:
            files = sorted(d.rglob("*.yaml")) if d.is_dir() else []
        except OSError:
            continue
        for p in files:
            rel = p.relative_to(d)
            if any(part.startswith(".") for part in rel.parts) or rel.parts[0] == EXPERIMENTS_DIR:
                continue  # hidden files; experiment specs (adarl.experiment) are not recipes
            name = rel.with_suffix("").as_posix()
            if name in found:
                continue  # shadowed by an earlier folder
            desc = ""
            if with_descriptions:
                try:
                    data = _read_file(p)
                    d_ = data.get("description", "")
                    desc = " ".join(str(d_).split()) if d_ is not None else ""
                except RecipeError as err:
                    desc = f"(unreadable: {err})"
            found[name] = desc
    return sorted(found.items())


def list_recipes() -> list[tuple[str, str]]:
    """``(name, description)`` of every recipe in :func:`recipes_dir` (subfolders give names like ``a/b``)."""
    return _scan_recipes(with_descriptions=True)


class _Dumper(yaml.SafeDumper):
    """Safe dumper that quotes every string the loader would read back as something else, and writes flat lists
    of scalars in flow style (``num_cells: [64, 64]``)."""


def _setup_dumper() -> None:
    loader = _yaml_loader()
    # OmegaConf's loader recognises more floats (1e-3) than YAML 1.1; quote such strings when dumping
    _Dumper.yaml_implicit_resolvers = {k: list(v) for k, v in loader.yaml_implicit_resolvers.items()}

    def represent_list(dumper, data):
        flat = all(isinstance(x, (int, float, bool, str)) or x is None for x in data)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat or None)

    _Dumper.add_representer(list, represent_list)

    def represent_str(dumper, data):
        # NEL, line/paragraph separators, BOM and control characters are line breaks or invisible to a YAML
        # reader unless escaped, and only the double-quoted style escapes them
        special = any(ch in "\x85\u2028\u2029\ufeff" or (ch < " " and ch not in "\n") or "\x7f" <= ch < "\xa0" for ch in data)
        return dumper.represent_scalar("tag:yaml.org,2002:str", data, style='"' if special else None)

    _Dumper.add_representer(str, represent_str)


_dumper_ready = False


def _escape_interpolations(obj: Any) -> Any:
    """Make strings read back literally by OmegaConf: ``${`` becomes ``\\${`` (with its preceding backslashes
    doubled, OmegaConf's escaping rule)."""
    if isinstance(obj, str):
        if obj == "???":
            raise RecipeError("a string value '???' cannot be saved: OmegaConf reads it back as 'missing'")
        if "${" not in obj:
            return obj
        return re.sub(r"(\\*)\$\{", lambda m: "\\" * (2 * len(m.group(1)) + 1) + "${", obj)
    if isinstance(obj, dict):
        return {k: _escape_interpolations(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_escape_interpolations(v) for v in obj]
    return obj


def recipe_to_yaml(recipe: Recipe) -> str:
    """The fully resolved recipe as YAML (no ``extends``, every default spelled out); it loads back equal."""
    global _dumper_ready
    if not isinstance(recipe, Recipe):
        raise RecipeError(f"recipe_to_yaml needs a Recipe, got {type(recipe).__name__}")
    if not _dumper_ready:
        _setup_dumper()
        _dumper_ready = True
    data = _escape_interpolations(recipe.model_dump(mode="python"))
    body = yaml.dump(data, Dumper=_Dumper, sort_keys=False, allow_unicode=True, width=120)
    header = f"# adarl resolved recipe (schema version {SCHEMA_VERSION}): every key explicit, no extends\n"
    return header + body


def save_resolved(recipe: Recipe, path: str | os.PathLike) -> Path:
    """Write :func:`recipe_to_yaml` to ``path`` (atomically); ``load_recipe(path)`` gives back an equal recipe."""
    text = recipe_to_yaml(recipe)
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise RecipeError(f"cannot write the resolved recipe to {str(p)!r}: {err.strerror or err}") from None
    return p
