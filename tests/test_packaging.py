"""What `pip install adarl` (not editable) gives a user: every module and every shipped recipe, found from any
folder (issue 20). The slow test builds the wheel from a copy of the source tree, installs it into a fresh venv
and runs `adarl recipes` and a tiny `adarl run` from another directory."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from _helpers import tiny

REPO = Path(__file__).resolve().parents[1]
RECIPES = sorted(p.relative_to(REPO / "recipes").as_posix() for p in (REPO / "recipes").rglob("*.yaml"))
TINY = tiny("rank.interval=200", "eval.interval=600", "eval.episodes=1", "eval.max_steps=30", "checkpoint.interval=600")


def _subpackages() -> list[str]:
    return sorted(".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "adarl").rglob("__init__.py"))


def test_pyproject_lists_every_subpackage_and_maps_the_recipes():
    tomllib = pytest.importorskip("tomllib")
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    recipes = {p for p in cfg["packages"] if p == "adarl.recipes" or p.startswith("adarl.recipes.")}
    assert sorted(set(cfg["packages"]) - recipes) == _subpackages()
    assert cfg["package-dir"] == {"adarl.recipes": "recipes"}
    assert "**/*.yaml" in cfg["package-data"]["adarl.recipes"]
    # every recipe folder is declared a package (else setuptools warns once per folder on every install)
    folders = {"adarl.recipes." + d.name for d in (REPO / "recipes").iterdir() if d.is_dir()}
    assert folders <= recipes and all(cfg["package-data"][f] == ["*.yaml"] for f in folders)


def test_source_checkout_finds_the_top_level_recipes():
    from adarl.runtime.config import list_recipes, recipes_dir

    assert recipes_dir()[-1] == REPO / "recipes"
    names = {n for n, _ in list_recipes()}
    assert {"quickstart", "hopper_adarl", "baselines/hopper_sac_full", "ablations/hopper_softplus"} <= names


def _copy_source(dst: Path) -> Path:
    dst.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (REPO / name).is_file():
            shutil.copy2(REPO / name, dst / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    shutil.copytree(REPO / "adarl", dst / "adarl", ignore=ignore)
    shutil.copytree(REPO / "recipes", dst / "recipes", ignore=ignore)
    return dst


@pytest.mark.slow
def test_wheel_ships_recipes_and_runs_from_another_folder(tmp_path: Path):
    import zipfile

    src = _copy_source(tmp_path / "src")
    dist = tmp_path / "dist"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    try:  # the build backend pyproject.toml asks for is here: build with it, fetching nothing
        import setuptools

        isolation = ["--no-build-isolation"] if int(setuptools.__version__.split(".")[0]) >= 77 else []
    except (ImportError, ValueError):
        isolation = []
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-w", str(dist), str(src)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    wheel = next(dist.glob("adarl-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {f"adarl/recipes/{r}" for r in RECIPES} <= names, "recipes missing from the wheel"
    modules = {p.relative_to(REPO).as_posix() for p in (REPO / "adarl").rglob("*.py")}
    assert modules <= names, f"modules missing from the wheel: {sorted(modules - names)}"

    # A fresh venv with the wheel; its dependencies come from this test's environment (a .pth line), so nothing is
    # downloaded. The source tree is nowhere on its path.
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300, env=env)
    py = venv / "bin" / "python"
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    ).stdout.strip()
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(site) / "adarl_test_deps.pth").write_text("".join(f"{d}\n" for d in sorted(deps)))
    proc = subprocess.run(
        [str(py), "-m", "pip", "install", "--no-deps", "--no-index", str(wheel)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    adarl = str(venv / "bin" / "adarl")
    proc = subprocess.run(
        [str(py), "-c", "import adarl, adarl.runtime.config as c; print(adarl.__file__); print(c.recipes_dir()[-1])"],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    module_file, recipes = proc.stdout.split()
    assert Path(module_file).is_relative_to(venv), module_file
    assert Path(recipes) == Path(module_file).parent / "recipes"  # adarl/recipes in the installed package
    proc = subprocess.run([adarl, "recipes"], cwd=elsewhere, capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    recipes_part, _, specs_part = proc.stdout.partition("\n\n")  # the recipes, then the spec sections (headed)
    listed = {line.split()[0] for line in recipes_part.splitlines() if line.strip()}
    specs = ("experiments/", "tune/")  # experiment and tune specs, not recipes
    assert {r[: -len(".yaml")] for r in RECIPES if not r.startswith(specs)} == listed
    for kind in specs:  # listed under their sections, and found by name from the installed package (issue 48.3)
        names = {r[len(kind) : -len(".yaml")] for r in RECIPES if r.startswith(kind)}
        assert names and all(f"\n{n} " in specs_part for n in names), (kind, specs_part)
    proc = subprocess.run(
        [
            str(py),
            "-c",
            "from adarl.experiments.tune import load_tune_spec; print(load_tune_spec('hopper_tune').recipe)",
        ],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert (proc.returncode, proc.stdout.strip()) == (0, "hopper_adarl"), proc.stderr[-2000:]

    run_env = {**env, "OMP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run(
        [adarl, "run", "quickstart", "-o", "out", *TINY, "--quiet"],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        env=run_env,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (elsewhere / "out" / "summary.json").is_file()
    assert "run finished" in proc.stdout
