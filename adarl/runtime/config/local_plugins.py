"""A recipe's ``plugins``: local Python modules imported before the recipe is validated, without packaging them.

As pytest's ``pytest_plugins`` or Hydra's ``_target_`` reach code by module name, a recipe lists modules whose
import registers what it names (``register_algorithm``, ``register_env``, ``register_rank_rule``,
``register_callback``)::

    plugins: [my_algo]             # my_algo.py beside this recipe, else a module on PYTHONPATH
    # or: plugins: [./lib/my_algo.py]   a path, relative to this recipe file
    algorithm: {name: my_sac}

Each entry is resolved where the recipe file that names it is (so ``extends`` keeps working), and the resolved recipe
(``adarl show``, a run folder's recipe.yaml) holds the absolute path of a local file, or the module name of one found
on ``PYTHONPATH``. The file's folder goes last on ``sys.path`` (process workers, which inherit it, import it by name
when they unpickle its classes): another file beside the recipe never shadows a module imported later, and a plugin
whose name an installed or standard module already has is refused by name. A run folder's plugins.json records each
module's file and sha256 (:func:`record`), and those of the modules it imports from its own folder (``helper.py``
beside it, a package there; :func:`helper_modules`: read from its ``import`` statements, so a module imported by a
computed name is not among them): ``adarl resume``, ``eval`` and ``report`` of a run whose module or helper is
missing or changed are refused by name (:func:`check_recorded`), as a run whose plugin package is gone is; a module
found by name on ``PYTHONPATH`` is checked where Python finds it now (another module of that name earlier on the path
would be the one imported).
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import os
import re
import site
import sys
import sysconfig
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from adarl import plugins
from adarl.errors import RecipeError

__all__ = [
    "resolve_entry",
    "entry_form_error",
    "import_plugins",
    "record",
    "located",
    "check_recorded",
    "helper_modules",
]

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


def _sha256(path: Path, *, code: bool = True) -> str:
    """The sha256 of a module's code, or of a package folder's (every .py file under it, by relative path).

    ``code``: of each file's parsed module (``ast.dump``), so that a comment or a layout change is not a change (a
    comment-only edit made ``adarl eval`` refuse the run: issue 48.6); a file that does not parse is hashed by its
    bytes. ``code=False``: the bytes, what adarl recorded before (:func:`check_recorded` accepts either)."""
    digest = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*.py") if "__pycache__" not in p.parts)
    for f in files:
        if f is not path:
            digest.update(f.relative_to(path).as_posix().encode() + b"\0")
        data = f.read_bytes()
        if code:
            try:
                data = ast.dump(ast.parse(data, filename=str(f))).encode()
            except (SyntaxError, ValueError):
                pass
        digest.update(data)
    return digest.hexdigest()


def _same(path: Path, recorded) -> bool:
    """Whether ``path`` holds what ``recorded`` hashed: its code now, or its bytes (a record made before code
    hashes)."""
    return recorded in (_sha256(path), _sha256(path, code=False))


def _imported_names(files: Iterable[Path]) -> set[str]:
    """The top-level names the files import absolutely (``import helper``, ``from helper import x``)."""
    names: set[str] = set()
    for f in files:
        try:
            tree = ast.parse(f.read_bytes(), filename=str(f))
        except (SyntaxError, ValueError, OSError):
            continue  # its import fails and says so; nothing to follow here
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names


def _py_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    return sorted(p for p in path.rglob("*.py") if "__pycache__" not in p.parts)


def _installed_folders() -> set[Path]:
    """The standard library's and the installed packages' folders."""
    paths = sysconfig.get_paths()
    folders = [paths.get(k) for k in ("stdlib", "platstdlib", "purelib", "platlib")]
    folders += [*getattr(site, "getsitepackages", list)(), site.getusersitepackages()]
    return {Path(f).resolve() for f in folders if f}


def helper_modules(path: str | os.PathLike) -> dict[str, str]:
    """The modules a plugin (a ``.py`` file or a package folder) imports from its own folder, and those they import
    from it in turn: ``{"helper.py": sha256, "pkg/": sha256 of the package}``, by path relative to that folder. Read
    from the ``import`` statements (a module imported by a computed name, ``importlib.import_module(name)``, is not
    found); a name that is no file there (an installed or standard module) is not one."""
    plugin = Path(path)
    root = plugin.parent
    if root.resolve() in _installed_folders():  # a module on the path beside installed packages: those are versioned
        return {}
    out: dict[str, str] = {}
    todo, seen = _py_files(plugin), {plugin.resolve()}
    while todo:
        names = _imported_names(todo)
        todo = []
        for name in sorted(names):
            for candidate, key in ((root / f"{name}.py", f"{name}.py"), (root / name, f"{name}/")):
                if candidate.resolve() in seen or not (
                    candidate.is_file() if key.endswith(".py") else (candidate / "__init__.py").is_file()
                ):
                    continue
                if any(root.glob(f"{name}-*.dist-info")) or any(root.glob(f"{name}-*.egg-info")):
                    break  # a package pip installed there (`pip install --target`): versioned, not a helper
                seen.add(candidate.resolve())
                out[key] = _sha256(candidate)
                todo += _py_files(candidate)
                break
    return dict(sorted(out.items()))


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
        except (Exception, SystemExit) as err:  # noqa: BLE001 - any failure of the user's module, named with it
            # (SystemExit too: a module calling sys.exit() at import would end the run with its status, silently)
            sys.modules.pop(name, None)
            raise RecipeError(
                f"plugins: {entry!r}: importing {name!r} ({path}) failed: {type(err).__name__}: {err}"
            ) from err
        found = getattr(module, "__file__", None)
        if found is None or Path(found).resolve() not in (path.resolve(), path.resolve() / "__init__.py"):
            raise RecipeError(  # the name is an installed or standard module's, found before the recipe's folder
                f"plugins: {entry!r}: the module name {name!r} is taken by {found or 'a built-in module'}, which "
                f"Python finds first; rename the file"
            )
        _IMPORTED[entry] = {
            "entry": entry,
            "module": name,
            "path": str(path),
            "sha256": _sha256(path),
            "imports": helper_modules(path),
        }


def record(entries: Iterable[str]) -> list[dict]:
    """What plugins.json records of a recipe's ``plugins``: each module's name, file and sha256 (at import)."""
    out = []
    for entry in entries:
        if entry not in _IMPORTED:
            import_plugins([entry])
        out.append(dict(_IMPORTED[entry]))
    return out


def located(entries: Iterable[str], modules: Iterable[Mapping]) -> list[dict]:
    """Records :func:`check_recorded` takes, from a run's resolved ``plugins`` entries (where the modules are) and a
    fingerprint's modules (their content, no path): what a run folder whose plugins.json was lost still proves."""
    by_name = {m.get("module"): m for m in modules if isinstance(m, Mapping)}
    out = []
    for entry in entries:
        name, path = _locate(str(entry))
        rec = by_name.pop(name, None)
        if rec is None:
            raise RecipeError(f"plugins: {entry!r}: the run's fingerprint.json records no module {name!r}")
        out.append(
            {
                "entry": str(entry),
                "module": name,
                "path": str(path),
                "sha256": rec.get("sha256"),
                "imports": rec.get("imports"),
            }
        )
    if by_name:
        raise RecipeError(
            "the run's fingerprint.json records plugin modules its recipe.yaml does not name: "
            f"{sorted(map(str, by_name))}"
        )
    return out


def _found_now(rec: Mapping) -> Path:
    """Where the recorded module is now: its recorded file for a path entry; for a module found by name on
    ``PYTHONPATH``, the file Python imports under that name now (imported already, or found first on the path)."""
    recorded = Path(str(rec.get("path")))
    entry, name = str(rec.get("entry") or ""), rec.get("module")
    if not entry or Path(entry).is_absolute() or not isinstance(name, str):
        return recorded
    loaded = getattr(sys.modules.get(name), "__file__", None)
    if loaded is None:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        loaded = spec.origin if spec is not None and spec.origin else None
    if loaded is None:
        return recorded
    found = Path(loaded)
    return found.parent if found.name == "__init__.py" else found


def check_recorded(recorded: Iterable[Mapping], run: str) -> None:
    """Refuse a run whose local plugin module (recorded by :func:`record`), or a module it imports from its folder,
    is missing or changed, by name; a module found by name is checked at the file Python imports now."""
    for rec in recorded:
        name, path = rec.get("module"), Path(str(rec.get("path")))
        how = "restore it (e.g. from version control) to resume, evaluate or report this run, or start a new run"
        now_at = _found_now(rec)
        if now_at.resolve() != path.resolve() and path.exists():
            raise RecipeError(
                f"run folder {run!r} was trained with the local plugin module {name!r} from {path}, but Python now "
                f"imports {name!r} from {now_at} (another module of that name comes first on sys.path): remove it "
                f"from the path or rename it, to resume, evaluate or report this run"
            )
        if not path.exists():
            raise RecipeError(
                f"run folder {run!r} was trained with the local plugin module {name!r} ({path}), which is missing: "
                f"{how}"
            )
        now = _sha256(path)
        if not _same(path, rec.get("sha256")):
            raise RecipeError(
                f"run folder {run!r} was trained with the local plugin module {name!r} ({path}), which has changed "
                f"since (sha256 {str(rec.get('sha256'))[:12]}... then, {now[:12]}... now): {how}"
            )
        helpers = rec.get("imports")
        if not isinstance(helpers, Mapping):  # recorded before helpers were: the module itself only
            continue
        for rel, sha in helpers.items():
            helper = path.parent / rel.rstrip("/")
            if not helper.exists():
                raise RecipeError(
                    f"run folder {run!r} was trained with the local plugin module {name!r}, which imports {rel} "
                    f"({helper}), now missing: {how}"
                )
            now = _sha256(helper)
            if not _same(helper, sha):
                raise RecipeError(
                    f"run folder {run!r} was trained with the local plugin module {name!r}, which imports {rel} "
                    f"({helper}), changed since (sha256 {str(sha)[:12]}... then, {now[:12]}... now): {how}"
                )
