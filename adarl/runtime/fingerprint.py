"""What made a run: the fingerprint of its resolved recipe (its content, not its path) and of its plugin modules.

A run folder's ``fingerprint.json`` (written with its recipe.yaml, before training starts; rewritten when
``adarl resume --total-frames`` changes the recipe) holds::

    {"format": "adarl.fingerprint", "version": 1,
     "sha256": "<of the two below>",
     "recipe": {"sha256": "<of the fingerprinted keys>", "excluded": ["description", "logging", ...]},
     "plugins": [{"module": "my_sac", "sha256": "...", "imports": {"helper.py": "..."}}]}

What counts is every key of the resolved recipe (``rank.beta``, ``collector.total_frames``, ``algorithm.fused``,
``device``, the thread counts, ``checkpoint.*``: a rollback on divergence reloads checkpoints) except those in
:data:`EXCLUDED`, which name, place or log a run and change nothing it learns or reports; plus the content of each
plugin module the recipe lists and of the modules it imports from its own folder
(:func:`adarl.runtime.config.local_plugins.helper_modules`), by module name (a path differs between machines).

Whether a run folder is what a recipe makes now (:func:`differences`, which ``adarl experiment`` and ``adarl tune``
ask before they reuse a finished or resumable run) is decided on its recipe.yaml *re-validated with today's schema*:
a key added since the run (``algorithm.polyak``, ``algorithm.factor_lr_scale``) takes its default there, as it does
in the plan, so a run made by an older adarl still matches while nothing that matters changed; and run folders made
before ``fingerprint.json`` existed (the committed reproduction runs) are read so too. The recorded sha256 is the
run's own record of what made it (for tools and people reading the folder), not what the comparison reads: a schema
that gains a key changes it without changing the run.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from adarl.errors import AdaRLError, RecipeError, describe_os_error
from adarl.runtime.config import load_recipe, local_plugins, validate_recipe
from adarl.runtime.run_folder._file_safety import atomic_write_text
from adarl.runtime.run_folder.results import is_url, join, read_text

__all__ = [
    "FINGERPRINT_FILE",
    "EXCLUDED",
    "NOT_TRAINING",
    "training_values",
    "recipe_values",
    "revalidated",
    "fingerprint",
    "write_fingerprint",
    "read_fingerprint",
    "run_recipe",
    "differences",
]

FINGERPRINT_FILE = "fingerprint.json"
FORMAT = "adarl.fingerprint"
VERSION = 1

#: top-level recipe keys left out of a run's fingerprint, and why: each names, places or logs a run, and changes
#: nothing it learns, evaluates or reports
EXCLUDED = {
    "name": "the recipe's label (a copy under another name trains the same)",
    "description": "one line for `adarl recipes`",
    "version": "the recipe file's format version (older files are converted when read)",
    "plugins": "where the plugin modules are (a path per machine): their content is fingerprinted instead",
    "output": "where the run folder goes (`-o`; the experiment and tune drivers give each run its own)",
    "logging": "which loggers get the metrics beside the CSV files, the wandb project, how often losses are averaged "
    "into the log",
}

#: flat recipe keys a fingerprint keeps (a run is resumed or reused only with the same values) that change neither
#: what the run learns nor what its evaluations measure, and why; with :data:`EXCLUDED` they are the keys in which
#: seeds of one setting may differ (:func:`training_values`: ``adarl report`` pools loose run folders so)
NOT_TRAINING = {
    "checkpoint.interval": "where a run can resume from (it changes training only through a rollback: counted "
    "under guards.on_nonfinite: rollback)",
    "checkpoint.keep_last": "how many checkpoints stay on disk",
    "checkpoint.replay_buffer": "whether a checkpoint holds the replay buffer (an exact resume needs it)",
    "checkpoint.keep_best": "whether the best evaluation's policy is kept",
    "eval.interval": "how often the policy is evaluated, on an env of its own (counted when a callback, which may "
    "stop the run on an evaluation, is listed)",
    "eval.episodes": "how many episodes an evaluation averages: its precision, not what it measures (counted with a "
    "callback, as eval.interval)",
}


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def recipe_values(recipe) -> dict[str, Any]:
    """The fingerprinted keys of a validated recipe, flat (``rank.beta``), as JSON values."""
    data = recipe.model_dump(mode="json")
    return {k: v for k, v in _flat(data).items() if k.split(".")[0] not in EXCLUDED}


def training_values(recipe: dict) -> dict[str, Any]:
    """The keys of a recipe mapping (a run folder's recipe.yaml as read) that make its setting, flat
    (``rank.beta``): all but :data:`EXCLUDED`'s sections and :data:`NOT_TRAINING`'s keys, each of the latter kept
    where the recipe makes it matter (``checkpoint.interval`` with ``guards.on_nonfinite: rollback``, the
    evaluation keys with ``callbacks``). The seed is among them (it changes what a run learns)."""
    flat = _flat(recipe)
    counted = set()
    if (recipe.get("guards") or {}).get("on_nonfinite") == "rollback":
        counted.add("checkpoint.interval")
    if recipe.get("callbacks"):
        counted |= {"eval.interval", "eval.episodes"}
    return {
        k: v for k, v in flat.items() if k.split(".")[0] not in EXCLUDED and (k not in NOT_TRAINING or k in counted)
    }


def revalidated(values: dict[str, Any]) -> dict[str, Any] | None:
    """Recorded :func:`recipe_values` validated again by today's schema (keys added since take their defaults),
    as :func:`recipe_values`; None when they no longer validate."""
    nested: dict = {"name": "recorded"}  # a label the schema requires; not fingerprinted
    for key, value in values.items():
        node = nested
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                return None
        node[leaf] = value
    try:
        return recipe_values(validate_recipe(nested, label="a recorded recipe"))
    except RecipeError:
        return None


def _sha(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _plugin_records(recipe) -> list[dict]:
    """The recipe's plugin modules as a fingerprint holds them: name, sha256, helpers (no path)."""
    return [
        {"module": m["module"], "sha256": m["sha256"], "imports": dict(m.get("imports") or {})}
        for m in local_plugins.record(recipe.plugins)
    ]


def fingerprint(recipe) -> dict:
    """The fingerprint of a run of ``recipe`` (a validated :class:`~adarl.runtime.config.Recipe`) here, now."""
    recipe_sha = _sha(recipe_values(recipe))
    plugins = _plugin_records(recipe)
    return {
        "format": FORMAT,
        "version": VERSION,
        "sha256": _sha({"recipe": recipe_sha, "plugins": plugins}),
        "recipe": {"sha256": recipe_sha, "excluded": sorted(EXCLUDED)},
        "plugins": plugins,
    }


def write_fingerprint(folder: str | os.PathLike, recipe) -> None:
    """Write ``fingerprint.json`` into a run folder (atomically)."""
    path = Path(folder) / FINGERPRINT_FILE
    try:
        atomic_write_text(path, json.dumps(fingerprint(recipe), indent=2) + "\n")
    except OSError as err:
        raise AdaRLError(f"cannot write {str(path)!r}: {describe_os_error(err)}") from None


def _read_json(folder: str | os.PathLike, name: str) -> dict | None:
    text = read_text(join(str(folder), name)) if is_url(folder) else None
    if not is_url(folder):
        try:
            text = (Path(folder) / name).read_text()
        except OSError:
            return None
    try:
        out = json.loads(text) if text is not None else None
    except ValueError:
        return None
    return out if isinstance(out, dict) else None


def read_fingerprint(folder: str | os.PathLike) -> dict | None:
    """A run folder's ``fingerprint.json`` (None: made before it existed, or unreadable)."""
    out = _read_json(folder, FINGERPRINT_FILE)
    return out if out is not None and out.get("format") == FORMAT else None


def run_recipe(folder: str | os.PathLike):
    """A run folder's recipe.yaml (a local folder or a URL), validated by today's schema: keys added since the run
    take their defaults. :class:`RecipeError` when it does not load here."""
    if not is_url(folder):
        return load_recipe(str(Path(folder) / "recipe.yaml"))
    text = read_text(join(str(folder), "recipe.yaml"))
    if text is None:
        raise RecipeError(f"{folder}: no recipe.yaml")
    with tempfile.TemporaryDirectory(prefix="adarl-fingerprint-") as tmp:
        path = Path(tmp) / "recipe.yaml"
        path.write_text(text)
        return load_recipe(str(path))


def _show(value) -> str:
    if value is _ABSENT:
        return "(absent)"
    return repr(value) if isinstance(value, str) else json.dumps(value)


_ABSENT = object()


def _recorded_plugins(folder: str | os.PathLike) -> list[dict] | None:
    """The plugin modules a run recorded (fingerprint.json, else plugins.json); None when it recorded none."""
    fp = read_fingerprint(folder)
    if fp is not None and isinstance(fp.get("plugins"), list):
        return fp["plugins"]
    provenance = _read_json(folder, "plugins.json")
    modules = (provenance or {}).get("modules")
    return modules if isinstance(modules, list) else None


def differences(
    folder: str | os.PathLike, recipe, *, theirs: str = "the run", ours: str = "the spec", ignore: tuple = ()
) -> list[str]:
    """What differs between the run folder ``folder`` and a run of ``recipe`` (validated now), one line each:
    ``rank.beta: 0.9 in the run, 0.95 in the spec``, a plugin module whose content differs, or a recipe.yaml that
    does not load here. ``[]``: the run is what ``recipe`` makes. Keys in ``ignore`` (or under them) are not
    compared (``adarl tune``: the search space's keys, compared per trial)."""
    try:
        made = run_recipe(folder)
    except RecipeError as err:
        return [f"its recipe.yaml does not load here: {str(err).splitlines()[0]}"]
    a, b = recipe_values(made), recipe_values(recipe)
    lines = []
    for key in sorted(set(a) | set(b)):
        if any(key == k or key.startswith(k + ".") for k in ignore):
            continue
        va, vb = a.get(key, _ABSENT), b.get(key, _ABSENT)
        if va != vb:
            lines.append(f"{key}: {_show(va)} in {theirs}, {_show(vb)} in {ours}")
    recorded = _recorded_plugins(folder)
    now = {m["module"]: m for m in _plugin_records(recipe)}
    if recorded is None:  # a run made before plugins were recorded: its recipe's modules are not known
        return lines
    then = {m.get("module"): m for m in recorded if isinstance(m, dict)}
    for name in sorted(set(then) | set(now), key=str):
        if name not in now:
            lines.append(f"plugin module {name!r}: in {theirs}, not in {ours}")
        elif name not in then:
            lines.append(f"plugin module {name!r}: in {ours}, not in {theirs}")
        elif then[name].get("sha256") != now[name]["sha256"]:
            lines.append(
                f"plugin module {name!r}: sha256 {str(then[name].get('sha256'))[:12]}... in {theirs}, "
                f"{now[name]['sha256'][:12]}... in {ours}"
            )
        elif isinstance(then[name].get("imports"), dict) and then[name]["imports"] != now[name]["imports"]:
            changed = sorted(
                k
                for k in set(then[name]["imports"]) | set(now[name]["imports"])
                if then[name]["imports"].get(k) != now[name]["imports"].get(k)
            )
            lines.append(f"plugin module {name!r}: the module(s) it imports {', '.join(changed)} differ")
    return lines
