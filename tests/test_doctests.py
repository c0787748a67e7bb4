"""The docstring examples (``>>>``) of adarl's modules run and print what they show: one test per module with
examples. The public components each carry one (a test below lists them, so that an example cannot silently go).

They run here rather than through ``--doctest-modules`` so that ``pytest tests`` (``make test``) runs them. As
``doctest.testmod`` does, each docstring runs in a fresh copy of its module's namespace (an example uses the
module's names and imports what else it needs), in a temporary working directory (the Trainer's writes a run).
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "adarl"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = sorted(_module_name(p) for p in ROOT.rglob("*.py") if ">>>" in p.read_text())

#: the public components (``from adarl import ...``) and where their example lives: (module, object), ``None``
#: for the module's own docstring
EXAMPLES = [
    ("adarl.core.lowrank", "LowRankLinear"),
    ("adarl.core.lowrank", "low_rank_mlp"),
    ("adarl.core.rank", "EnergyRule"),
    ("adarl.core.acceptance", "ProjectionAcceptance"),
    ("adarl.core.adapter", "RankAdapter"),
    ("adarl.core.lr_schedule", "WarmupCosine"),
    ("adarl.core.warmstart", "ReplayWarmStart"),
    ("adarl.core.collector_rebuild", "CollectorRebuild"),
    ("adarl.envs.schedules", "SinusoidSchedule"),
    ("adarl.envs.perturbation", "PerturbedDynamicsEnvTransform"),
    ("adarl.envs.factory", "make_env"),
    ("adarl.runtime.config", None),
    ("adarl.runtime.builders.sac", None),
    ("adarl.runtime.trainers.off_policy", "OffPolicyTrainer"),
    ("adarl.fast.sac", "FusedSACUpdate"),
    ("adarl.baselines.parseval", "ParsevalRegularizer"),
    ("adarl.baselines.registry", None),
]


def test_the_examples_are_found():
    assert {m for m, _ in EXAMPLES} <= set(MODULES)


@pytest.mark.parametrize("module", MODULES)
def test_docstring_examples_run(module, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    mod = importlib.import_module(module)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    # the examples of this module only (not those of names it imports), each with a copy of the module's globals
    tests = [t for t in finder.find(mod, module) if t.examples]
    assert tests, f"{module} has '>>>' but no example was found"
    for test in sorted(tests, key=lambda t: t.lineno or 0):
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {module} (output above)"


@pytest.mark.parametrize("module, name", EXAMPLES)
def test_public_components_have_examples(module, name):
    obj = importlib.import_module(module)
    if name is not None:
        obj = getattr(obj, name)
    assert ">>>" in (obj.__doc__ or ""), f"{module}.{name or ''} has no docstring example"
