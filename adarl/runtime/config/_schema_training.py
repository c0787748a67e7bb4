"""The recipe's training sections: learning-rate schedule, replay and its warm start, collector, evaluation,
logging, checkpoints, guards, output and callbacks."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from adarl import plugins
from adarl.errors import AdaRLValueError, UnknownNameError, did_you_mean, one_of
from adarl.runtime.config._schema_base import Float, NonNegInt, PosInt, _Problems, _Section, _validated_options


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
