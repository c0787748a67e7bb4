"""A recipe's ``plugins``: a local module (beside the recipe, not packaged) registers an algorithm the recipe runs;
the run is killed (-9) and resumed, a two-seed experiment runs it; resume and eval refuse once the module changed
or went missing (issue 29.5)."""

from __future__ import annotations

import json
import signal
import textwrap
from pathlib import Path

import pytest
from test_cli_e2e import adarl
from test_faults import FAST, _start, _wait_for

from adarl.errors import RecipeError
from adarl.runtime.config import load_recipe

MODULE = '''
"""A SAC whose loss is a subclass of TorchRL's, registered at import."""
from torchrl.objectives import SACLoss

from adarl import register_algorithm


@register_algorithm("local_sac", description="SACLoss from a module beside the recipe")
class LocalSACLoss(SACLoss):
    pass
'''

RECIPE = """
extends: quickstart
plugins: [my_algo]
algorithm: {name: local_sac}
"""

pytestmark = pytest.mark.slow


def _error_line(proc) -> str:
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    (line,) = [line for line in proc.stderr.splitlines() if line.startswith("adarl: error:")]
    return line


@pytest.fixture
def recipe(tmp_path: Path) -> Path:
    (tmp_path / "my_algo.py").write_text(MODULE)
    (tmp_path / "local.yaml").write_text(textwrap.dedent(RECIPE))
    return tmp_path / "local.yaml"


def test_entries_resolve_where_the_recipe_is_and_bad_ones_are_named(recipe, tmp_path):
    loaded = load_recipe(recipe, ["collector.total_frames=500", "collector.init_random_frames=100"])
    assert loaded.plugins == [str(tmp_path / "my_algo.py")] and loaded.algorithm.name == "local_sac"
    with pytest.raises(RecipeError, match=r"plugins: 'no_such_module_xyz': no module of that name"):
        load_recipe(recipe, ["plugins=[no_such_module_xyz]"])
    (tmp_path / "broken.py").write_text("raise ValueError('half written')\n")
    with pytest.raises(RecipeError, match=r"plugins: .*broken.py.*failed: ValueError: half written"):
        load_recipe(recipe, [f"plugins=[{tmp_path / 'broken.py'}]"])


def test_a_local_module_algorithm_runs_resumes_after_kill_9_and_is_refused_once_changed(recipe, tmp_path):
    run = tmp_path / "run"
    proc = _start("run", str(recipe), *FAST, "-o", str(run), "--quiet")
    try:
        assert _wait_for(lambda: any(run.glob("checkpoints/ckpt-*.pt")), proc), proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGSTOP)  # mid-run, after its first checkpoint
        assert not (run / "summary.json").exists(), "the run finished first: nothing to test"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    [module] = json.loads((run / "plugins.json").read_text())["modules"]
    assert module["module"] == "my_algo" and module["path"] == str(tmp_path / "my_algo.py")
    assert json.loads((run / "plugins.json").read_text())["algorithm"]["package"] == "my_algo"

    proc = adarl("resume", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (run / "summary.json").is_file()

    # a two-seed experiment of the same recipe: each run imports the module (a worker process each) and records it
    spec = tmp_path / "seeds.yaml"
    spec.write_text(
        f"kind: experiment\nname: local_seeds\nrecipe: {recipe}\noverrides: [{', '.join(FAST)}]\nseeds: [0, 1]\n"
    )
    proc = adarl("experiment", str(spec), "-o", str(tmp_path / "experiment"), "--workers", "2", "--no-live")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    runs = sorted(p.parent for p in (tmp_path / "experiment").rglob("summary.json"))
    assert len(runs) == 2, runs
    for r in runs:
        assert (
            json.loads((r / "summary.json").read_text())["frames"]
            == json.loads((run / "summary.json").read_text())["frames"]
        )
        [recorded] = json.loads((r / "plugins.json").read_text())["modules"]
        assert recorded["sha256"] == module["sha256"] and recorded["path"] == module["path"]

    (tmp_path / "my_algo.py").write_text(MODULE + "\n# changed\n")
    for command in (("resume", str(run)), ("eval", str(run))):
        line = _error_line(adarl(*command))
        assert "local plugin module 'my_algo'" in line and "has changed" in line, line
    (tmp_path / "my_algo.py").unlink()
    line = _error_line(adarl("resume", str(run), "--quiet"))
    assert "local plugin module 'my_algo'" in line and "missing" in line, line
