"""Every result is tied to what made it (issue 46, point 2; bullet 2 of "What to build").

A run folder records the fingerprint of its resolved recipe (content, not path) and of its plugin modules
(``fingerprint.json``, :mod:`adarl.runtime.fingerprint`); ``adarl experiment`` reuses a finished (or resumable) run
only while its recipe, re-validated with today's schema, is what the spec plans now, and otherwise refuses by name,
listing the keys that changed, with the folder untouched; ``--rerun-changed`` runs those again into new folders beside
the old ones. Run folders made before the fingerprint (the committed reproduction runs:
``test_committed_reports.py``) are compared through their recipe.yaml.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import yaml
from _helpers import adarl, tiny

REPO = Path(__file__).resolve().parents[1]
TINY = tiny()


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _spec(path: Path, beta: float, frames: int) -> Path:
    spec = {
        "kind": "experiment",
        "name": "edits",
        "recipe": "linear_cartpole_sac",
        "overrides": [*TINY[1:], f"collector.total_frames={frames}"],
        "axes": {"algo": [{"name": "ok"}, {"name": "ok2", "overrides": [f"rank.beta={beta}"]}]},
        "seeds": [0],
        "workers": 2,
    }
    path.write_text(yaml.safe_dump(spec))
    return path


def _finished(path: Path, recipe: str, overrides: list[str]) -> Path:
    """A finished run folder as training leaves it, without the training: its resolved recipe and a summary."""
    from adarl.runtime.config import load_recipe, save_resolved

    resolved = load_recipe(recipe, overrides)
    path.mkdir(parents=True)
    save_resolved(resolved, path / "recipe.yaml")
    (path / "summary.json").write_text(json.dumps({"frames": resolved.collector.total_frames}))
    return path


@pytest.mark.slow
def test_an_edited_spec_refuses_its_finished_runs_by_name_and_reruns_them_into_new_folders(tmp_path):
    """Issue 46.2: arms ok: [], ok2: [rank.beta=0.9] run; the spec then says rank.beta=0.95 and more frames. The
    next `adarl experiment` used to skip both as finished and report the old runs as the new arms."""
    spec = _spec(tmp_path / "edits.yaml", 0.9, 600)
    out = tmp_path / "exp"
    first = adarl("experiment", str(spec), "-o", str(out), "--no-report", timeout=900)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-3000:]
    before = _snapshot(out)

    _spec(spec, 0.95, 700)
    again = adarl("experiment", str(spec), "-o", str(out), timeout=900)
    said = again.stderr
    assert again.returncode == 1, again.stdout[-2000:] + said
    assert "Traceback" not in said
    assert "algo=ok__seed=0" in said and "algo=ok2__seed=0" in said, said
    assert "collector.total_frames: 600 in the run, 700 in the spec" in said, said
    assert "rank.beta: 0.9 in the run, 0.95 in the spec" in said, said
    assert "--rerun-changed" in said
    assert _snapshot(out) == before  # refused before anything was written: no report, experiment.json as it was

    dry = adarl("experiment", str(spec), "-o", str(out), "--dry-run", timeout=900)
    assert dry.returncode == 0, dry.stderr
    assert dry.stdout.count("changed") >= 2 and "rank.beta: 0.9 in the run, 0.95 in the spec" in dry.stdout

    rerun = adarl("experiment", str(spec), "-o", str(out), "--rerun-changed", timeout=900)
    assert rerun.returncode == 0, rerun.stdout[-2000:] + rerun.stderr[-3000:]
    for rel, data in before.items():  # the old runs are kept byte for byte
        if not rel.startswith(("experiment.json", "attempts", ".adarl-experiment.lock")):
            assert (out / rel).read_bytes() == data, rel
    state = json.loads((out / "experiment.json").read_text())
    paths = {r["run_id"]: Path(r["path"]) for r in state["runs"]}
    assert paths == {
        "algo=ok__seed=0": out / "algo=ok__seed=0.rerun1",
        "algo=ok2__seed=0": out / "algo=ok2__seed=0.rerun1",
    }
    assert all(r["status"] == "finished" for r in state["runs"])
    made = yaml.safe_load((paths["algo=ok2__seed=0"] / "recipe.yaml").read_text())
    assert made["rank"]["beta"] == 0.95 and made["collector"]["total_frames"] == 700
    with (out / "report" / "runs.csv").open() as fh:
        reported = {row["algo"]: row["path"] for row in csv.DictReader(fh)}
    assert {k: Path(v).name for k, v in reported.items()} == {
        "ok": "algo=ok__seed=0.rerun1",
        "ok2": "algo=ok2__seed=0.rerun1",
    }
    fingerprint = json.loads((paths["algo=ok2__seed=0"] / "fingerprint.json").read_text())
    assert len(fingerprint["recipe"]["sha256"]) == 64

    from adarl.experiments.orchestrate import run_experiment

    lines: list[str] = []
    runs = run_experiment(spec, output=out, report=False, log=lines.append)  # the new folders match: reused
    assert [r.status for r in runs] == ["skipped-finished"] * 2
    assert {Path(r.path).name for r in runs} == {"algo=ok__seed=0.rerun1", "algo=ok2__seed=0.rerun1"}
    _spec(spec, 0.9, 600)  # the spec as it was: the first runs are its runs again
    runs = run_experiment(spec, output=out, report=False, log=lines.append)
    assert [r.status for r in runs] == ["skipped-finished"] * 2
    assert {Path(r.path).name for r in runs} == {"algo=ok__seed=0", "algo=ok2__seed=0"}


def test_a_run_made_from_another_recipe_is_named_with_the_keys_that_differ(tmp_path):
    """In process, with finished run folders written without training: only training keys count (the run's name,
    its logging and its output place do not), and a recipe.yaml written before keys existed (they take their
    defaults) still matches."""
    from adarl.errors import AdaRLError
    from adarl.experiments.orchestrate import run_experiment

    spec = _spec(tmp_path / "edits.yaml", 0.9, 600)
    out = tmp_path / "exp"
    base = [*TINY[1:], "collector.total_frames=600"]
    _finished(out / "algo=ok__seed=0", "linear_cartpole_sac", [*base, "seed=0", "logging.log_interval=300"])
    old = _finished(out / "algo=ok2__seed=0", "linear_cartpole_sac", [*base, "rank.beta=0.9", "seed=0"])
    recipe = yaml.safe_load((old / "recipe.yaml").read_text())
    del recipe["algorithm"]["polyak"], recipe["algorithm"]["factor_lr_scale"]  # as an older adarl wrote it
    recipe["name"], recipe["output"]["root"] = "renamed", "elsewhere"
    (old / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
    lines: list[str] = []
    runs = run_experiment(spec, output=out, dry_run=True, log=lines.append)
    assert [r.status for r in runs] == ["skipped-finished"] * 2, lines

    _spec(spec, 0.95, 600)
    lines.clear()
    runs = run_experiment(spec, output=out, dry_run=True, log=lines.append)
    assert [r.status for r in runs] == ["skipped-finished", "changed"], lines
    assert any("algo=ok2__seed=0" in line and "rank.beta: 0.9 in the run, 0.95 in the spec" in line for line in lines)
    before = _snapshot(out)
    with pytest.raises(AdaRLError, match=r"(?s)made from another recipe.*algo=ok2__seed=0.*rank\.beta") as err:
        run_experiment(spec, output=out, report=False, log=lines.append)
    assert "algo=ok__seed=0:" not in str(err.value)  # the unchanged run is not named
    assert _snapshot(out) == before
    (old / "summary.json").unlink()  # an unfinished run with a checkpoint would resume with its own recipe
    (old / "checkpoints").mkdir()
    (old / "checkpoints" / "ckpt-000000000300.pt").write_bytes(b"")
    lines.clear()
    runs = run_experiment(spec, output=out, dry_run=True, log=lines.append)
    assert [r.status for r in runs] == ["skipped-finished", "changed"], lines

    # what every launcher's worker executes checks again, before it skips or resumes (a worker's files may not be
    # the driver's): the planned run of the edited spec, pointed at the old folder, is refused and left untouched
    from adarl.experiments.execute import execute_run
    from adarl.experiments.spec import load_experiment, plan_runs

    planned = {r.run_id: r for r in plan_runs(load_experiment(spec), out)}
    before = _snapshot(out)
    done = execute_run(planned["algo=ok2__seed=0"], 1)
    assert done.status == "changed" and "rank.beta: 0.9 in the run, 0.95 in the spec" in done.message
    assert execute_run(planned["algo=ok__seed=0"], 1).status == "skipped-finished"
    assert _snapshot(out) == before


@pytest.mark.parametrize("name", ["..", ".", "..."])
def test_spec_names_must_be_folder_names(tmp_path, name):
    """Issue 46.5: a spec named `..` wrote its study into runs/ (the default output is runs/<kind>/<name>)."""
    from adarl.errors import RecipeError
    from adarl.experiments.spec import load_experiment

    spec = _spec(tmp_path / "s.yaml", 0.9, 600)
    data = yaml.safe_load(spec.read_text())
    data["name"] = name
    spec.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError, match="name"):
        load_experiment(spec)


@pytest.mark.parametrize(
    "where",
    ["overrides", "value", "budget"],
)
@pytest.mark.parametrize("override", ["seed=5", " seed = 5", "+seed=5", "output=elsewhere", "output.dir=x"])
def test_an_experiment_override_of_a_key_each_run_sets_itself_is_refused_by_name(tmp_path, where, override):
    """Issue 46: an experiment override `seed=5` was recorded in the spec and silently overridden by each run's own
    seed (appended last), as tune's search space did; it is refused by name, wherever the spec holds overrides."""
    from adarl.errors import RecipeError
    from adarl.experiments.spec import load_experiment

    spec = _spec(tmp_path / "s.yaml", 0.9, 600)
    data = yaml.safe_load(spec.read_text())
    if where == "overrides":
        data["overrides"] = [*data.get("overrides", []), override]
    elif where == "value":
        axis = next(iter(data["axes"]))
        data["axes"][axis][0] = {"name": "with_seed", "overrides": [override]}
    else:
        data["budgets"] = {"small": {"overrides": [override]}}
    spec.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError, match=r"sets '(seed|output(\.dir)?)', which each run sets itself"):
        load_experiment(spec)
