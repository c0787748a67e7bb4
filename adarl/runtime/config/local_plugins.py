"""A recipe's ``plugins``: local Python modules imported before the recipe is validated, without packaging them.

As pytest's ``pytest_plugins`` or Hydra's ``_target_`` reach code by module name, a recipe lists modules whose
import registers what it names (``register_algorithm``, ``register_env``, ``register_rank_rule``)::

    plugins: [my_algo]             # my_algo.py beside this recipe, else a module on PYTHONPATH
    # or: plugins: [./lib/my_algo.py]   a path, relative to this recipe file
    algorithm: {name: my_sac}

Each entry is resolved where the recipe file that names it is (so ``extends`` keeps working), and the resolved recipe
(``adarl show``, a run folder's recipe.yaml) holds the absolute path of a local file, or the module name of one found
on ``PYTHONPATH``. The file's folder goes last on ``sys.path`` (process workers, which inherit it, import it by name
when they unpickle its classes): another file beside the recipe never shadows a module imported later, and a plugin
whose name an installed or standard module already has is refused by name. A run folder's plugins.json records each
module's file and sha256 (:func:`record`): ``adarl resume``, ``eval`` and ``report`` of a run whose module is missing
or changed are refused by name (:func:`check_recorded`), as a run whose plugin package is gone is.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import re
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from adarl import plugins
from adarl.errors import RecipeError

__all__ = ["resolve_entry", "entry_form_error", "import_plugins", "record", "check_recorded"]

_MODULE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
# entry (as resolved) -> what plugins.json records of it, for the modules this process imported
_IMPORTED: dict[str, dict] = {}


def _is_path(entry: str) -> bool:
    return entry.endswith(".py") or "/" in entry or "\\" in entry or entry.startswith(("~", "."))


def entry_form_error(entry: Any) -> str | None:
    """What is wrong with the form of a ``plugins`` entry (None: a module name or a path), before any file is
    looked for: the recipe schema checks it, so that a recipe validated from a mapping writes a file that loads."""
    if not isinstance(entry, str) or not entry.strip():
        return "expected a module name or a path to a .py file"
    if not _is_path(entry) and not _MODULE_NAME.match(entry):
        return "not a module name (my_module, pkg.module) nor a .py path"
    return None


def resolve_entry(entry: Any, base: Path, where: str) -> str:
    """``entry`` of the ``plugins`` list of the recipe file in folder ``base``, as the resolved recipe keeps it."""
    if (problem := entry_form_error(entry)) is not None:
        raise RecipeError(f"{where}: plugins: {entry!r}: {problem}")
    if Path(entry).is_absolute() and Path(entry).exists():
        return entry
    if _is_path(entry):
        path = Path(entry).expanduser()
        path = path if path.is_absolute() else base / path
        if not (path.is_file() and path.suffix == ".py") and not (path / "__init__.py").is_file():
            raise RecipeError(
                f"{where}: plugins: {entry!r}: no Python file {str(path)!r} (a path is relative to the recipe file)"
            )
        return str(path.resolve())
    for beside in (base / f"{entry}.py", base / entry / "__init__.py"):
        if "." not in entry and beside.is_file():
            return str((beside if beside.name != "__init__.py" else beside.parent).resolve())
    return entry  # a module on PYTHONPATH: found when imported


def _locate(entry: str) -> tuple[str, Path]:
    """``(module name, file or package folder)`` of a resolved entry; a path's folder goes first on sys.path."""
    if Path(entry).is_absolute():
        path = Path(entry)
        if not path.exists():
            raise RecipeError(f"plugins: {entry!r}: the module is missing")
        folder = str(path.parent)
        if folder not in sys.path:  # last: a sibling file must not shadow a module imported later (csv.py, wave.py)
            sys.path.append(folder)
        return path.stem if path.is_file() else path.name, path
    try:
        spec = importlib.util.find_spec(entry)
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin:
        raise RecipeError(
            f"plugins: {entry!r}: no module of that name beside the recipe nor on PYTHONPATH (sys.path: "
            f"{sys.path[:4]}...); give a path to the .py file, or add its folder to PYTHONPATH"
        )
    origin = Path(spec.origin)
    return entry, origin.parent if origin.name == "__init__.py" else origin


def _sha256(path: Path) -> str:
    """The file's sha256, or a package folder's (every .py file under it, by relative path)."""
    digest = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*.py") if "__pycache__" not in p.parts)
    for f in files:
        if f is not path:
            digest.update(f.relative_to(path).as_posix().encode() + b"\0")
        digest.update(f.read_bytes())
    return digest.hexdigest()


def import_plugins(entries: Iterable[str]) -> None:
    """Import each resolved entry (once per process); registrations record the module name as their provider. A
    module that fails to import, or whose name another module already took, is a :class:`RecipeError` naming it."""
    for entry in entries:
        if entry in _IMPORTED:
            continue
        name, path = _locate(entry)
        loaded = sys.modules.get(name)
        where = getattr(loaded, "__file__", None)
        if (
            loaded is not None
            and where
            and Path(where).resolve() not in (path.resolve(), path.resolve() / "__init__.py")
        ):
            raise RecipeError(
                f"plugins: {entry!r}: another module named {name!r} is already imported (from {where}); rename the file"
            )
        try:
            with plugins.providing(name):
                module = importlib.import_module(name)
        except RecipeError:
            raise
        except Exception as err:  # noqa: BLE001 - any failure of the user's module, named with it
            raise RecipeError(
                f"plugins: {entry!r}: importing {name!r} ({path}) failed: {type(err).__name__}: {err}"
            ) from err
        found = getattr(module, "__file__", None)
        if found is None or Path(found).resolve() not in (path.resolve(), path.resolve() / "__init__.py"):
            raise RecipeError(  # the name is an installed or standard module's, found before the recipe's folder
                f"plugins: {entry!r}: the module name {name!r} is taken by {found or 'a built-in module'}, which "
                f"Python finds first; rename the file"
            )
        _IMPORTED[entry] = {"entry": entry, "module": name, "path": str(path), "sha256": _sha256(path)}


def record(entries: Iterable[str]) -> list[dict]:
    """What plugins.json records of a recipe's ``plugins``: each module's name, file and sha256 (at import)."""
    out = []
    for entry in entries:
        if entry not in _IMPORTED:
            import_plugins([entry])
        out.append(dict(_IMPORTED[entry]))
    return out


def check_recorded(recorded: Iterable[Mapping], run: str) -> None:
    """Refuse a run whose local plugin module (recorded by :func:`record`) is missing or changed, by name."""
    for rec in recorded:
        name, path = rec.get("module"), Path(str(rec.get("path")))
        how = "restore it (e.g. from version control) to resume, evaluate or report this run, or start a new run"
        if not path.exists():
            raise RecipeError(
                f"run folder {run!r} was trained with the local plugin module {name!r} ({path}), which is missing: "
                f"{how}"
            )
        now = _sha256(path)
        if now != rec.get("sha256"):
            raise RecipeError(
                f"run folder {run!r} was trained with the local plugin module {name!r} ({path}), which has changed "
                f"since (sha256 {str(rec.get('sha256'))[:12]}... then, {now[:12]}... now): {how}"
            )
