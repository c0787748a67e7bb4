"""Reading recipe files safely: a size cap, UTF-8, and OmegaConf's safe YAML loader (PyYAML's safe loader with
alias-expansion limits and duplicate-key detection); a file must hold a mapping.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from omegaconf._yaml import get_yaml_loader  # OmegaConf's safe loader (yaml.SafeLoader/CSafeLoader based)

from adarl.errors import RecipeError
from adarl.runtime.config._schema_base import SCHEMA_VERSION, _newer_version_message, _show

_MAX_FILE_BYTES = 1 << 20  # a recipe is a few KB; refuse anything absurd before parsing it
_MAX_YAML_NODES = 10_000  # OmegaConf's alias-expansion cap, pinned (its env var could lift it)


def _yaml_loader():
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
