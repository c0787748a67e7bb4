"""Finding recipes: the folders searched for a recipe name (``$ADARL_RECIPES_PATH``, then the shipped
``recipes/``), a name or path resolved to a file, and the lists ``adarl recipes`` prints: the recipes, and the
experiment and tune specs of the same folders (their ``experiments/`` and ``tune/`` subfolders, found by name by
``adarl experiment`` and ``adarl tune``, in a source checkout and in an installed wheel alike).
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath
from typing import Any

from adarl.errors import RecipeError, did_you_mean
from adarl.runtime.config._schema_base import _show
from adarl.runtime.config.files import _read_file

__all__ = ["RECIPES_PATH_ENV", "EXPERIMENTS_DIR", "TUNE_DIR", "recipes_dir", "list_recipes", "list_specs"]

#: Extra recipe folders, searched before the shipped ``recipes/`` (``os.pathsep``-separated).
RECIPES_PATH_ENV = "ADARL_RECIPES_PATH"


#: Subfolder of a recipes folder holding experiment specs (``adarl experiment``), not recipes.
EXPERIMENTS_DIR = "experiments"
#: Subfolder of a recipes folder holding hyperparameter-search specs (``adarl tune``), not recipes.
TUNE_DIR = "tune"


def _package_recipes_dir() -> Path:
    """The shipped recipes: ``adarl/recipes/`` in an installed wheel (package data mapped from the source tree's
    top-level ``recipes/``, see pyproject.toml), else that top-level folder (a source checkout, an editable install)."""
    package = Path(__file__).resolve().parents[2]  # adarl/runtime/config/discovery.py -> adarl/
    installed = package / "recipes"
    return installed if installed.is_dir() else package.parent / "recipes"


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
    top = [n for n in names if "/" not in n]  # the shipped recipes' first level; `adarl recipes` lists them all
    shown = ", ".join(top[:12]) + (
        f", ... ({len(names)} in all: `adarl recipes` lists them)" if len(names) > 12 else ""
    )
    raise RecipeError(  # the did-you-mean first: a long list before it hid it (issue 48.6)
        f"no recipe named {s!r} in {', '.join(str(d) for d in recipes_dir())}{did_you_mean(s, names)}; available: "
        f"{shown or '(none)'} (or pass a path to a .yaml file)"
    )


def _scan_recipes(with_descriptions: bool = True) -> list[tuple[str, str]]:
    found: dict[str, str] = {}
    for d in recipes_dir():
        try:
            files = sorted(d.rglob("*.yaml")) if d.is_dir() else []
        except OSError:
            continue
        for p in files:
            rel = p.relative_to(d)
            if any(part.startswith(".") for part in rel.parts) or rel.parts[0] in (EXPERIMENTS_DIR, TUNE_DIR):
                continue  # hidden files; experiment and tune specs (adarl.experiments) are not recipes
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


def list_specs(kind: str) -> list[tuple[str, str]]:
    """``(name, description)`` of every spec in the ``kind`` subfolder (:data:`EXPERIMENTS_DIR` or :data:`TUNE_DIR`)
    of :func:`recipes_dir`, by the name ``adarl experiment`` / ``adarl tune`` finds it by (earlier folders shadow)."""
    if kind not in (EXPERIMENTS_DIR, TUNE_DIR):
        raise RecipeError(f"spec kind must be {EXPERIMENTS_DIR!r} or {TUNE_DIR!r}, got {kind!r}")
    found: dict[str, str] = {}
    for d in recipes_dir():
        try:
            files = sorted((d / kind).glob("*.yaml")) if (d / kind).is_dir() else []
        except OSError:
            continue
        for p in files:
            if p.name.startswith(".") or p.stem in found:
                continue
            try:
                d_ = _read_file(p).get("description", "")
                found[p.stem] = " ".join(str(d_).split()) if d_ is not None else ""
            except RecipeError as err:
                found[p.stem] = f"(unreadable: {err})"
    return sorted(found.items())
