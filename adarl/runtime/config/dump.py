"""Writing a recipe back: the fully resolved YAML (every default spelled out, no ``extends``) that loads back equal;
``save_resolved`` writes it atomically into a run folder.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml

from adarl.errors import RecipeError
from adarl.runtime.config.files import _yaml_loader
from adarl.runtime.config.schema import SCHEMA_VERSION, Recipe

__all__ = ["recipe_to_yaml", "save_resolved"]


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
        special = any(
            ch in "\x85\u2028\u2029\ufeff" or (ch < " " and ch not in "\n") or "\x7f" <= ch < "\xa0" for ch in data
        )
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
