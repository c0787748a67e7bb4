"""Loading a recipe: its file and the chain it ``extends`` merged (dicts merge, lists replace; an explicit
schedule replaces the base's), dotlist overrides checked against the schema and applied, node interpolations
resolved, then validated. Resolver calls (``${oc.env:HOME}``) are refused: a run never depends on the process
environment, and the resolved copy saved in a run folder is exactly what ran.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException
from omegaconf.grammar_parser import OmegaConfGrammarParser, parse
from pydantic import BaseModel

from adarl import plugins
from adarl.errors import NO_VALUE, RecipeError, did_you_mean
from adarl.runtime.config._schema_base import _show
from adarl.runtime.config.discovery import _available_names, _find_by_name, _is_path_like, _locate, recipes_dir
from adarl.runtime.config.files import _check_version, _one_line, _parse_yaml, _read_file
from adarl.runtime.config.local_plugins import import_plugins, resolve_entry
from adarl.runtime.config.schema import Recipe
from adarl.runtime.config.validation import _is_free_mapping, _join_path, _list_item, _model_of, validate_recipe

__all__ = ["load_recipe"]

_MAX_EXTENDS_DEPTH = 32
_SCHEDULE_PATH = "env.perturbation.schedule"


# ----------------------------------------------------------------------------------------- interpolations


def _resolver_calls(s: str) -> list[str] | None:
    """Resolver names called in string ``s`` (``[]`` for plain text or node interpolations); None if ``s`` is
    not a valid OmegaConf string."""
    if "${" not in s:
        return []
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
                f"{where}: {path or '<value>'} = {_show(obj)}: resolver interpolations "
                f"({', '.join(sorted(set(calls)))}) are not allowed in recipes (a run must not depend on the "
                "environment); only references to other "
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
            f"{', '.join(str(d) for d in recipes_dir())}; available: {', '.join(names) or '(none)'}"
            f"{did_you_mean(ext, names)}"
        )
    return found


def _load_chain(path: Path, stack: tuple[Path, ...] = ()):
    """The merged (unresolved) OmegaConf config of ``path`` and everything it extends."""
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
    if isinstance(data.get("plugins"), list):  # local modules, found where this file is (plugins beside it)
        data["plugins"] = [resolve_entry(entry, path.parent, where) for entry in data["plugins"]]
    ext = data.pop("extends", None)
    # name and description describe this file; they are never inherited from the base
    data.setdefault("name", _default_name(path))
    data.setdefault("description", "")
    if ext is None:
        return _to_omegaconf(data, where)
    base = _load_chain(_resolve_extends(ext, path, where), (*stack, real))
    child = _to_omegaconf(data, where)
    if (
        OmegaConf.select(child, _SCHEDULE_PATH, default=NO_VALUE) is not NO_VALUE
        and OmegaConf.select(base, _SCHEDULE_PATH, default=None) is not None
    ):
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


# keys of older recipes, with where they went (recipe files with them are still read: schema.py converts them)
_MOVED_KEYS = {
    "algorithm.rnac": " (RNAC is now a registered algorithm: algorithm.name=rnac_ipm with algorithm.options.kappa, "
    "or algorithm.name=rnac_ds with algorithm.options.num_candidates / noise)",
}


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
                moved = _MOVED_KEYS.get(full, "")
                raise RecipeError(
                    f"override {override!r}: unknown key {full!r}{moved}; allowed keys{where}: {', '.join(allowed)}"
                    f"{did_you_mean(str(part), allowed)}"
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
        if isinstance(data.get("plugins"), list):  # an override's entries are relative to the working folder
            data["plugins"] = [resolve_entry(entry, Path.cwd(), f"invalid recipe {label}") for entry in data["plugins"]]
            try:  # before validation: their registrations are what the recipe names
                import_plugins(data["plugins"])
            except RecipeError as err:  # its errors name the entry, not the recipe
                raise RecipeError(f"invalid recipe {label}: {err}") from None
    except RecipeError:
        raise
    except RecursionError:
        raise RecipeError(f"invalid recipe {label}: nested too deeply") from None
    except Exception as err:  # nothing raw escapes (an OmegaConf corner we did not foresee)
        raise RecipeError(f"invalid recipe {label}: {type(err).__name__}: {_one_line(err)}") from None
    follow_option_overrides(data, overrides or ())
    return validate_recipe(data, label=label)


def follow_option_overrides(data: dict, overrides: Sequence[str]) -> None:
    """An override of an algorithm option that sets an ``algorithm`` key (CrossQ's ``options.lr`` sets
    ``algorithm.lr``) carries that key with it, unless an override sets the key too (then the two are checked against
    each other): a resolved recipe spells both out, and the key's old value would otherwise refuse the new option."""
    alg = data.get("algorithm")
    if not isinstance(alg, dict) or not isinstance(alg.get("options"), dict):
        return
    try:
        sets = plugins.algorithm(alg.get("name")).sets
    except Exception:  # an unknown name: validation says so
        return
    given = {ov.split("=", 1)[0].strip() for ov in overrides if isinstance(ov, str)}
    for key, option in sets.items():
        if f"algorithm.options.{option}" in given and f"algorithm.{key}" not in given and option in alg["options"]:
            alg[key] = alg["options"][option]
