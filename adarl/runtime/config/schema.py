"""The recipe schema: pydantic models of every section of a recipe, with their defaults, ranges and cross-checks.

Every model forbids unknown keys and NaN/inf. A validator that finds problems raises ``_Problems`` (key path
relative to the model, value, message), which :mod:`adarl.runtime.config.validation` turns into
:class:`~adarl.errors.RecipeError` lines. Env ids, presets, parameter names and schedules are checked against
:mod:`adarl.envs` (its registry and schedule grammar), never against a copy.

The hub of the schema (as TorchRL's transforms: private modules behind it): each section's models live in their
own module, ``_schema_env``, ``_schema_network``, ``_schema_algorithm``, ``_schema_rank`` and
``_schema_training``, on ``_schema_base``'s building blocks; here is :class:`Recipe`, the sections put together,
with the checks that relate keys of several sections (each loop family's: :func:`ppo_problems`,
:func:`td3_problems`, :func:`sac_problems`). Import the models from here (or
:mod:`adarl.runtime.config`); ``adarl show`` and docs/recipes.md are read from them.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import Field, field_validator, model_validator

from adarl import plugins
from adarl.envs.registry import is_mujoco
from adarl.errors import AdaRLValueError
from adarl.runtime.config._schema_algorithm import (
    AlgorithmConfig,
    ParsevalConfig,
    PPOConfig,
    TD3Config,
)
from adarl.runtime.config._schema_base import SCHEMA_VERSION, Int, _newer_version_message, _Problems, _Section
from adarl.runtime.config._schema_env import DeclaredParameterConfig, EnvConfig, PerturbationConfig
from adarl.runtime.config._schema_network import InitConfig, MLPConfig, NetworkConfig, SparseLayerConfig
from adarl.runtime.config._schema_rank import AcceptConfig, RankConfig
from adarl.runtime.config._schema_training import (
    CallbackConfig,
    CheckpointConfig,
    CollectorConfig,
    EvalConfig,
    GuardsConfig,
    LoggingConfig,
    LRScheduleConfig,
    OutputConfig,
    ReplayConfig,
    WarmStartConfig,
)
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
    "TD3Config",
    "ppo_problems",
    "td3_problems",
    "sac_problems",
]

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
