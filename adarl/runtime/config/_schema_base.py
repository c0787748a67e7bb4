"""The schema's building blocks: the section base (unknown keys and NaN refused), number types that refuse
booleans, the validators' problem list, and the helpers the loader shares."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from adarl.errors import NO_VALUE, did_you_mean, one_of

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
