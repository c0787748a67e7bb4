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

The package, one job per module:

* :mod:`~adarl.runtime.config.schema` - the pydantic models (:class:`Recipe` and its sections);
* :mod:`~adarl.runtime.config.validation` - :func:`validate_recipe`, error messages, :func:`describe_schema`;
* :mod:`~adarl.runtime.config.discovery` - :func:`recipes_dir`, :func:`list_recipes`, names to files;
* :mod:`~adarl.runtime.config.files` - reading a recipe file safely;
* :mod:`~adarl.runtime.config.loader` - :func:`load_recipe`: extends, overrides, interpolation;
* :mod:`~adarl.runtime.config.dump` - :func:`recipe_to_yaml`, :func:`save_resolved`.

Public API: :func:`load_recipe`, :func:`validate_recipe`, :func:`list_recipes`, :func:`recipes_dir`,
:func:`recipe_to_yaml`, :func:`save_resolved`, :func:`describe_schema`, :class:`Recipe` and its sections.

>>> from adarl.runtime.config import load_recipe
>>> recipe = load_recipe("quickstart", ["rank.beta=0.9"])
>>> recipe.rank.beta, recipe.env.id
(0.9, 'Hopper-v5')
"""

from adarl.runtime.config.discovery import EXPERIMENTS_DIR, RECIPES_PATH_ENV, TUNE_DIR, list_recipes, recipes_dir
from adarl.runtime.config.dump import recipe_to_yaml, save_resolved
from adarl.runtime.config.loader import load_recipe
from adarl.runtime.config.schema import (
    SCHEMA_VERSION,
    AcceptConfig,
    AlgorithmConfig,
    CheckpointConfig,
    CollectorConfig,
    EnvConfig,
    EvalConfig,
    GuardsConfig,
    InitConfig,
    LoggingConfig,
    LRScheduleConfig,
    MLPConfig,
    NetworkConfig,
    OutputConfig,
    ParsevalConfig,
    PerturbationConfig,
    PPOConfig,
    RankConfig,
    Recipe,
    ReplayConfig,
    SparseLayerConfig,
    WarmStartConfig,
)
from adarl.runtime.config.validation import describe_schema, validate_recipe

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
    "EXPERIMENTS_DIR",
    "TUNE_DIR",
]
