"""A recipe's ``plugins``: a local module (beside the recipe, not packaged) registers an algorithm the recipe runs;
its entries resolve where the recipe is and bad ones are named (issue 29.5). The end-to-end part (a run killed and
resumed, a two-seed experiment, resume and eval refused once the module changed or went missing) is in
tests/test_plugin_e2e.py, on the same run as the pip-installed plugin."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

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
