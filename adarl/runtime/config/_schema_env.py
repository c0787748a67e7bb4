"""The recipe's ``env`` section: the environment, its perturbation (preset, schedule, declared parameters) and
its cross-checks against :mod:`adarl.envs`' registry."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, field_validator, model_validator

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
from adarl.runtime.config._schema_base import Float, PosInt, _plain_copy, _Problems, _Section


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
