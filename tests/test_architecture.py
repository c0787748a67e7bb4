"""The package reads as its architecture: no import cycles, no upward imports, imports at module top.

The import graph is read from the source (``ast``), so the test needs nothing installed and sees every import,
including those inside functions. Wings, bottom to top (a module may import its own wing and those listed for it):

* ``errors`` - nothing of adarl; ``plugins`` (algorithm names and the entry-point group) - ``errors``;
* ``core`` (the paper's components) - ``errors``, ``plugins`` (rank rules by name; torch, TorchRL, tensordict
  the only third-party packages); ``envs`` - ``errors``,
  ``plugins`` (the entry-point group, loaded when an env id or a perturbation parameter is not registered yet);
* ``baselines`` - ``core``; ``fast`` (the speed engine) - ``core``, ``envs``;
* ``runtime`` - all of the above; ``experiments`` - ``runtime`` and below; ``cli`` - everything.

``adarl/__init__.py`` and ``adarl/envs/__init__.py`` load their public names on first use (PEP 562, by name),
so they hold no static import; modules may read ``adarl.__version__``.

Splits stay split: no module is over :data:`MAX_LINES` lines unless its docstring says why on a line of its own
starting with ``Long because:`` (or it is in :data:`SPLIT_PENDING`), and the parts recipes are validated with (the
plugin registry, the env registry) import neither torch, TorchRL nor MuJoCo at module top.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "adarl"

#: wing -> the wings its modules may import (besides their own)
ALLOWED = {
    "errors": set(),
    "plugins": {"errors"},
    "core": {"errors", "plugins"},
    "envs": {"errors", "plugins"},
    "baselines": {"errors", "plugins", "core"},
    "fast": {"errors", "core", "envs"},
    "runtime": {"errors", "plugins", "core", "envs", "baselines", "fast"},
    "experiments": {"errors", "plugins", "core", "envs", "baselines", "fast", "runtime"},
    "cli": {"errors", "plugins", "core", "envs", "baselines", "fast", "runtime", "experiments"},
}
#: third-party packages the paper's components may use
CORE_THIRD_PARTY = {"torch", "torchrl", "tensordict"}
#: modules that import adarl modules inside functions, and why (every other adarl import is at module top)
LAZY_ADARL_IMPORTS = {
    "adarl.cli": "each command imports the wing it runs: `adarl --help` answers without torch",
    "adarl.experiments.bench": "the bench hub: `--whole-run`'s driver (the recipe runtime) loads when it runs",
    "adarl.experiments.bench._update": "the benchmark driver never imports torch; each measurement's worker does",
    "adarl.experiments.tune": "the tune hub, in the parser: the spec, the study (Optuna, torch) load on first use",
    "adarl.experiments.tune._cli": "`adarl tune`'s arguments, in the parser: Optuna and torch load when it runs",
    # what a command checks before it trains (the run folder, a pack folder, an experiment's plan) needs no torch:
    # bad input is refused before torch's seconds of import (tests/test_cli_usability.py), and an experiment's
    # driver, which trains nothing itself, never imports it to plan
    "adarl.experiments.packing": "the packed trainer (torch) only once an experiment packs its runs",
    "adarl.experiments.sweep": "the policy's evaluation (torch, MuJoCo) once a sweep runs; reading one needs neither",
    "adarl.runtime.run_folder._file_safety": "torch where a checkpoint is saved or loaded",
    "adarl.runtime.run_folder._loggers": "TorchRL's loggers where a run first logs",
    "adarl.runtime.run_folder._records": "TorchRL's loggers where a run first logs",
    "adarl.runtime.trainers.pack_folder": "the packed trainer where a pack is built; reading a pack folder needs none",
}
#: third-party packages a module may import inside a function: optional extras (ray, submitit, stable-baselines3,
#: tensorboard), MuJoCo (the env registry validates recipes without it), matplotlib (its backend is chosen first),
#: onnx (``adarl export --format onnx`` only, when it is installed)
LAZY_THIRD_PARTY = {
    "onnx",
    "pandas",  # heavy; the run folder's progress.csv alone needs it in a training process
    "mujoco",
    "gymnasium",
    "matplotlib",
    "stable_baselines3",
    "ray",
    "submitit",
    "torch.utils.tensorboard",
}


#: the longest a module may be without a ``Long because:`` line in its docstring
MAX_LINES = 600
#: modules over MAX_LINES whose split is pending, and why they are not split yet (keep this short: it is a to-do list)
SPLIT_PENDING: dict[str, str] = {}
#: what recipe validation and ``import adarl`` reach, which must not load torch, TorchRL or MuJoCo at module top
LIGHT_MODULES = ("adarl.plugins", "adarl.envs.registry", "adarl.envs.registration", "adarl.envs.presets")
#: and what a command checks its input with before it trains, and an experiment's driver (it trains nothing itself)
LIGHT_MODULES += ("adarl.runtime.run_folder.run_dir", "adarl.runtime.continuing", "adarl.experiments.orchestrate")
HEAVY_THIRD_PARTY = {"torch", "torchrl", "tensordict", "mujoco", "gymnasium"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _target(name: str) -> str:
    """The adarl module an imported name refers to (``adarl.core.lowrank.LowRankLinear`` -> its module)."""
    while name not in MODULES and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def _imports(path: Path, module: str) -> list[tuple[str, bool, int]]:
    """``(imported name, at module top, line)`` of every import in a file (relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = []

    def visit(node, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                out.extend((a.name, top, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    base = ".".join(
                        package.split(".")[: len(package.split(".")) - child.level + 1] + ([base] if base else [])
                    )
                out.extend(
                    (f"{base}.{a.name}" if base.startswith("adarl") else base, top, child.lineno) for a in child.names
                )
            visit(child, top and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, True)
    return out


def _wing(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "root"


GRAPH = {
    m: sorted({_target(n) for n, _, _ in _imports(p, m) if n.startswith("adarl.") or n == "adarl"} - {m})
    for m, p in MODULES.items()
}


def _cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))

    def strong(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            strong(v)
    return out


def test_every_wing_is_known():
    assert {_wing(m) for m in MODULES} - {"root"} == set(ALLOWED)


def test_the_import_graph_has_no_cycles():
    assert _cycles(GRAPH) == []


def test_no_upward_imports():
    bad = []
    for m, targets in GRAPH.items():
        wing = _wing(m)
        for t in targets:
            if t == "adarl":  # adarl.__version__: the root holds no static import
                continue
            if wing == "root" or (_wing(t) != wing and _wing(t) not in ALLOWED[wing]):
                bad.append(f"{m} -> {t}")
    assert bad == []


def test_the_lazy_front_doors_import_nothing_statically():
    for module in ("adarl", "adarl.envs"):
        assert GRAPH[module] == [], module


def test_core_depends_on_torch_torchrl_errors_and_the_plugin_registry_only():
    stdlib = set(sys.stdlib_module_names)
    bad = [
        f"{m}: {n}"
        for m, p in MODULES.items()
        if _wing(m) == "core"
        for n, _, _ in _imports(p, m)
        if n.split(".")[0] not in stdlib | CORE_THIRD_PARTY | {"__future__"}
        and not n.startswith(("adarl.core", "adarl.errors", "adarl.plugins"))
    ]
    assert bad == []


def test_imports_are_at_module_top():
    """adarl modules are imported at the top of a module (except in the CLI's and the bench driver's lazy doors);
    the standard library and third-party packages too, except optional or heavy ones a function alone needs."""
    bad = []
    for m, p in MODULES.items():
        for name, top, line in _imports(p, m):
            if top:
                continue
            if name.startswith("adarl"):
                if m not in LAZY_ADARL_IMPORTS:
                    bad.append(f"{p.relative_to(ROOT.parent)}:{line}: {name}")
            elif (
                name.split(".")[0] not in LAZY_THIRD_PARTY
                and name not in LAZY_THIRD_PARTY
                and m not in LAZY_ADARL_IMPORTS
            ):
                bad.append(f"{p.relative_to(ROOT.parent)}:{line}: {name}")
    assert bad == []


@pytest.mark.parametrize(
    "module", sorted(f"adarl.fast.{p.stem}" for p in (ROOT / "fast").glob("*.py") if p.stem != "__init__")
)
def test_each_fast_module_names_what_it_mirrors_and_the_test_that_proves_it(module):
    doc = ast.get_docstring(ast.parse(MODULES[module].read_text())) or ""
    assert "Mirrors:" in doc and "Equality:" in doc and "tests/test_" in doc, module
    for ref in (w for w in doc.replace("``", " ").split() if w.startswith("tests/test_")):
        file, _, name = ref.rstrip(",.;)").partition("::")
        text = (ROOT.parent / file).read_text()
        assert not name or f"def {name}(" in text, ref


def test_core_imports_nothing_of_runtime_or_experiments():
    """The paper's components stand on torch and TorchRL: nothing of the machinery that runs recipes."""
    above = {"envs", "baselines", "fast", "runtime", "experiments", "cli"}
    assert [f"{m} -> {t}" for m, ts in GRAPH.items() if _wing(m) == "core" for t in ts if _wing(t) in above] == []


def test_no_module_is_over_the_line_limit_without_saying_why():
    bad = []
    for m, p in MODULES.items():
        lines = len(p.read_text().splitlines())
        if lines <= MAX_LINES or m in SPLIT_PENDING:
            continue
        doc = ast.get_docstring(ast.parse(p.read_text())) or ""
        if not any(line.strip().startswith("Long because:") for line in doc.splitlines()):
            bad.append(f"{p.relative_to(ROOT.parent)}: {lines} lines, and no 'Long because:' line in its docstring")
    assert bad == []


def test_split_pending_lists_only_long_modules():
    """An entry is removed once its module is split (the list must not hide a module that grows back)."""
    assert all(m in MODULES and len(MODULES[m].read_text().splitlines()) > MAX_LINES for m in SPLIT_PENDING)


def _closure(module: str) -> set[str]:
    """The adarl modules ``module`` imports at module top, transitively (itself included)."""
    seen, todo = set(), [module]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(_target(n) for n, top, _ in _imports(MODULES[m], m) if top and n.startswith("adarl."))
    return seen


@pytest.mark.parametrize("module", LIGHT_MODULES)
def test_what_recipes_are_validated_with_imports_no_torch_or_mujoco(module):
    heavy = sorted(
        f"{m}: {n}"
        for m in _closure(module)
        for n, top, _ in _imports(MODULES[m], m)
        if top and n.split(".")[0] in HEAVY_THIRD_PARTY
    )
    assert heavy == []
