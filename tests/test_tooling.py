"""The test command is one command: the README's `make test`, which CI (.ci/run) runs, checks the formatting and lint
with ruff (configured in pyproject.toml, pinned in constraints.txt) before the test suite."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python 3.11+
REPO = Path(__file__).resolve().parents[1]


def _make_recipe(target: str) -> list[str]:
    """The commands of a Makefile target, in order."""
    lines = (REPO / "Makefile").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if re.match(rf"{target}\s*:", line))
    out = []
    for line in lines[start + 1 :]:
        if not line.startswith("\t"):
            break
        out.append(line.strip())
    return out


def test_ci_runs_the_readme_test_command():
    commands = [line.strip() for line in (REPO / ".ci/run").read_text().splitlines() if line.strip() and line[0] != "#"]
    assert commands[-1] == "make test"
    tests_section = (REPO / "README.md").read_text().split("## Tests", 1)[1]
    assert "`make test`" in tests_section and "`.ci/run`" in tests_section


def test_make_test_checks_format_and_lint_then_runs_the_suite():
    assert _make_recipe("test") == [
        "$(BIN)/ruff format --check .",
        "$(BIN)/ruff check .",
        "$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --dist worksteal tests",
    ]


def test_ruff_is_configured_and_pinned():
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    ruff = pyproject["tool"]["ruff"]
    assert ruff["line-length"] == 120 and ruff["lint"]["select"]
    pins = dict(re.findall(r"^([A-Za-z0-9_.-]+)==([^\s#]+)", (REPO / "constraints.txt").read_text(), re.MULTILINE))
    dev = pyproject["project"]["optional-dependencies"]["dev"]
    assert f"ruff=={pins['ruff']}" in dev  # the dev extra installs the very version constraints.txt pins
