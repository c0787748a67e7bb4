"""Recipe validation and its messages: pydantic's errors as :class:`~adarl.errors.RecipeError` lines that name
the key path, the offending value and what is allowed (with a "did you mean"); :func:`describe_schema` lists every
key with its default, allowed values and why (``docs/recipes.md`` shows the same rows).
"""

from __future__ import annotations

import types
from collections.abc import Iterable, Mapping, Sequence
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticUndefined

from adarl.errors import NO_VALUE, RecipeError, did_you_mean, one_of
from adarl.runtime.config._schema_base import _Problems, _show, _WrongType
from adarl.runtime.config.schema import Recipe

__all__ = ["validate_recipe", "describe_schema"]


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
        vals = one_of(get_args(tp))
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
        inp = e.get("input", NO_VALUE)
        ctx = e.get("ctx") or {}
        path, target, parent, used = _walk_loc(loc)
        if etype == "value_error" and isinstance(ctx.get("error"), _Problems):
            for rel, value, msg in ctx["error"].problems:
                full = _join_path(path, rel)
                shown = "" if value is NO_VALUE else f" = {_show(value)}"
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
                f"{did_you_mean(str(bad).split('.')[0], allowed)}"
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
                else _describe_type(target)
                if target is not None
                else "a mapping with keys " + ", ".join(Recipe.model_fields)
            )
            if etype == "missing":
                line = f"{key}: required key is missing; expected {allowed}"
            elif etype == "value_error" and not isinstance(ctx.get("error"), _WrongType):
                line = f"{key} = {_show(inp)}: {ctx.get('error', e.get('msg'))}"
            else:
                line = f"{key} = {_show(inp)}: must be {allowed}"
                lits = _literal_options(getattr(target, "annotation", target))
                if lits and isinstance(inp, str):
                    line += did_you_mean(inp, lits)
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


def validate_recipe(data: Mapping[str, Any], *, label: str = "<mapping>") -> Recipe:
    """Validate a plain mapping (already merged and resolved) into a :class:`Recipe`.

    Raises :class:`RecipeError` listing every problem with its key path, value and allowed values."""
    if not isinstance(data, Mapping):
        raise RecipeError(
            f"invalid recipe {label}: the top level must be a mapping of keys to values, got {_show(data)}"
        )
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
