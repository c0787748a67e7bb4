"""A recipe's ``plugins``: a local module (beside the recipe, not packaged) registers an algorithm the recipe runs;
its entries resolve where the recipe is and bad ones are named (issue 29.5). The end-to-end part (a run killed and
resumed, a two-seed experiment, resume and eval refused once the module changed or went missing) is in
tests/test_plugin_e2e.py, on the same run as the pip-installed plugin."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from adarl import plugins
from adarl.errors import RecipeError
from adarl.runtime.config import load_recipe, local_plugins, validate_recipe

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


@pytest.fixture(autouse=True)
def _undone(monkeypatch):
    """Each test's plugin imports and registrations are undone after it: another test on the same worker (the
    doctests of adarl.plugins list the registered algorithms) must not see ``local_sac``."""
    monkeypatch.setattr(plugins._algorithm, "_algorithms", dict(plugins._algorithm._algorithms))
    monkeypatch.setattr(local_plugins, "_IMPORTED", {})
    monkeypatch.setattr(sys, "path", list(sys.path))
    yield
    sys.modules.pop("my_algo", None)


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


@pytest.mark.parametrize("entry", [0, "", "my module", "0"])
def test_a_recipe_validated_from_a_mapping_refuses_an_entry_its_file_could_not_load(entry):
    """Found by tests/test_recipes_fuzz.py: ``plugins: [0]`` validated from a mapping (the number made a string),
    and the recipe.yaml it wrote was refused on loading. The schema checks an entry's form as the loader does."""
    data = load_recipe("quickstart").model_dump()
    data["plugins"] = [entry]
    with pytest.raises(RecipeError, match=r"plugins = .*(module name|\.py)"):
        validate_recipe(data)


def test_a_file_beside_the_recipe_never_shadows_a_module_imported_later(recipe, tmp_path):
    """The recipe's folder goes last on sys.path: a ``wave.py`` beside it (any script that shares a standard or an
    installed module's name) must not replace that module for the code that imports it after the plugin loaded;
    a plugin that has such a name is refused by name rather than silently not imported."""
    import subprocess

    (tmp_path / "wave.py").write_text("raise RuntimeError('the wave.py beside the recipe was imported')\n")
    probe = (
        "import sys\n"
        "from adarl.runtime.config import load_recipe\n"
        f"load_recipe({str(recipe)!r})\n"
        "before = 'wave' in sys.modules\n"
        "import wave\n"
        "print(before, wave.__file__)\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    before, where = out.stdout.split()
    assert before == "False" and Path(where).parent != tmp_path, out.stdout  # (a module not imported yet: it could)
    (tmp_path / "json.py").write_text("VALUE = 1\n")
    with pytest.raises(RecipeError, match=r"plugins: .*json.py.*'json'"):
        load_recipe(recipe, [f"plugins=[{tmp_path / 'json.py'}]"])


HELPED = '''
"""A SAC whose loss takes a constant from a helper module beside it."""
from torchrl.objectives import SACLoss

from adarl import register_algorithm
from helper_of_algo import SCALE


@register_algorithm("helped_sac", description="SACLoss with a helper beside it")
class HelpedSACLoss(SACLoss):
    scale = SCALE
'''


def test_a_helper_module_the_plugin_imports_is_fingerprinted_and_a_change_refused_by_resume_eval_and_report(
    tmp_path, monkeypatch
):
    """Issue 46.6: a helper module the plugin imports could change between run and resume unhashed; and
    `adarl report` did not refuse a run whose plugin changed, though the docs said it did."""
    import json

    from adarl.experiments.report import collect_runs
    from adarl.runtime.fingerprint import differences
    from adarl.runtime.report import write_report
    from adarl.runtime.run_folder.run_dir import RunDir

    monkeypatch.delitem(sys.modules, "helper_of_algo", raising=False)
    monkeypatch.delitem(sys.modules, "helped_algo", raising=False)
    (tmp_path / "helped_algo.py").write_text(HELPED)
    (tmp_path / "helper_of_algo.py").write_text("SCALE = 1.0\n")
    (tmp_path / "r.yaml").write_text("extends: quickstart\nplugins: [helped_algo]\nalgorithm: {name: helped_sac}\n")
    loaded = load_recipe(tmp_path / "r.yaml", ["collector.total_frames=500", "collector.init_random_frames=100"])
    [recorded] = local_plugins.record(loaded.plugins)
    assert list(recorded["imports"]) == ["helper_of_algo.py"]
    run = RunDir.create(tmp_path / "run")
    try:
        run.save_recipe(loaded)
    finally:
        run.unlock()
    (run.path / "summary.json").write_text(json.dumps({"frames": 500}))
    [module] = json.loads((run.path / "fingerprint.json").read_text())["plugins"]
    assert module["module"] == "helped_algo" and list(module["imports"]) == ["helper_of_algo.py"]
    assert differences(run.path, loaded) == []
    RunDir(run.path).load_recipe()  # unchanged: resumes, evaluates

    (tmp_path / "helper_of_algo.py").write_text("SCALE = 2.0\n")
    with pytest.raises(RecipeError, match=r"'helped_algo', which imports helper_of_algo.py .* changed since"):
        RunDir(run.path).load_recipe()  # what resume and eval read the run with
    with pytest.raises(RecipeError, match=r"helper_of_algo.py .* changed since"):
        write_report(run.path)
    with pytest.raises(RecipeError, match=r"helper_of_algo.py .* changed since"):
        collect_runs([run.path])  # the aggregate report
    assert not (run.path / "report.md").exists()

    # with plugins.json deleted, eval imported the changed code silently: fingerprint.json still records the modules,
    # and with both records gone a recipe that names plugins is refused (its code cannot be checked)
    (run.path / "plugins.json").unlink()
    with pytest.raises(RecipeError, match=r"helper_of_algo.py .* changed since"):
        RunDir(run.path).load_recipe()
    (run.path / "fingerprint.json").write_text("{not json")
    for reader in (
        lambda: RunDir(run.path).load_recipe(),
        lambda: write_report(run.path),
        lambda: collect_runs([run.path]),
    ):
        with pytest.raises(RecipeError, match=r"local plugin modules \[.*helped_algo.py'\] but holds no record"):
            reader()
    assert not (run.path / "report.md").exists()


def test_a_module_plugin_found_on_the_path_is_checked_where_python_finds_it_now(tmp_path, monkeypatch):
    """Issue 46.6: a module plugin found on PYTHONPATH was shadowed at resume by another of the same name (the
    recorded path was hashed, not the one imported)."""
    from adarl.runtime.run_folder.run_dir import RunDir

    name = "shadowed_sac_plugin"
    monkeypatch.delitem(sys.modules, name, raising=False)
    first, second = tmp_path / "first", tmp_path / "second"
    for folder in (first, second):
        folder.mkdir()
        (folder / f"{name}.py").write_text(MODULE.replace("local_sac", "shadowed_sac") + f"\nWHERE = {folder.name!r}\n")
    monkeypatch.syspath_prepend(str(first))
    (tmp_path / "r.yaml").write_text(f"extends: quickstart\nplugins: [{name}]\nalgorithm: {{name: shadowed_sac}}\n")
    loaded = load_recipe(tmp_path / "r.yaml")
    run = RunDir.create(tmp_path / "run")
    try:
        run.save_recipe(loaded)
    finally:
        run.unlock()
    RunDir(run.path).load_recipe()
    # a later process: another module of that name comes first on the path
    sys.modules.pop(name, None)
    monkeypatch.setattr(local_plugins, "_IMPORTED", {})
    monkeypatch.syspath_prepend(str(second))
    with pytest.raises(RecipeError, match=rf"{name}.* from {first}.*now imports '{name}' from {second}"):
        RunDir(run.path).load_recipe()
    sys.modules.pop(name, None)


def test_a_plugin_calling_sys_exit_at_import_is_an_error_naming_it_with_no_folder(recipe, tmp_path, monkeypatch):
    """Issue 46.6: a module plugin calling ``sys.exit(0)`` at import made run, experiment and tune end with status 0,
    no output and no folder. It is an error naming the module (in process), and the CLI exits non-zero with one line
    and writes nothing; an entry-point plugin that exits while loading is named the same way."""
    import subprocess
    from importlib.metadata import EntryPoint

    (tmp_path / "quitter.py").write_text("import sys\nsys.exit(0)\n")
    with pytest.raises(RecipeError, match=r"plugins: .*quitter.py.*failed: SystemExit: 0"):
        load_recipe(recipe, [f"plugins=[{tmp_path / 'quitter.py'}]"])
    assert "quitter" not in sys.modules  # a retry imports it again rather than finding a half-run module
    out = tmp_path / "out"
    cli = [
        sys.executable,
        "-m",
        "adarl.cli",
        "run",
        str(recipe),
        f"plugins=[{tmp_path / 'quitter.py'}]",
        "-o",
        str(out),
    ]
    done = subprocess.run(cli, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "SystemExit" in done.stderr and "quitter" in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and not out.exists()

    (tmp_path / "quitter_ep.py").write_text("import sys\nsys.exit(3)\n")
    sys.path.insert(0, str(tmp_path))  # (into the fixture's copy of sys.path: monkeypatch's own restore would keep it)
    quitter = EntryPoint("quitter", "quitter_ep", plugins.ENTRY_POINT_GROUP)
    monkeypatch.setattr(plugins._registry, "entry_points", lambda group: [quitter])
    monkeypatch.setattr(plugins._registry, "_loaded", set())
    try:
        with pytest.raises(RecipeError, match=r"plugin 'quitter' \(quitter_ep.*SystemExit: 3"):
            load_recipe("quickstart", ["algorithm.name=anything"])
    finally:
        sys.modules.pop("quitter_ep", None)


def test_a_comment_or_layout_edit_of_a_plugin_is_not_a_change_but_code_is(recipe, tmp_path):
    """Issue 48.6: a comment-only edit of a local plugin module made `adarl eval` refuse the run. The recorded sha256
    is of the parsed code (comments and layout left out); a record of the file's bytes (older runs) still checks."""
    import json

    from adarl.runtime.run_folder.run_dir import RunDir

    loaded = load_recipe(recipe)
    run = RunDir.create(tmp_path / "run")
    try:
        run.save_recipe(loaded)
    finally:
        run.unlock()
    module = tmp_path / "my_algo.py"
    module.write_text("# a comment added after the run\n" + MODULE.replace("    pass", "\n\n    pass  # nothing"))
    RunDir(run.path).load_recipe()  # comments and blank lines: the same code
    record = json.loads((run.path / "plugins.json").read_text())
    record["modules"][0]["sha256"] = local_plugins._sha256(module, code=False)  # as an older adarl recorded it
    (run.path / "plugins.json").write_text(json.dumps(record))
    RunDir(run.path).load_recipe()
    module.write_text(MODULE.replace("    pass", "    gamma_scale = 2"))
    with pytest.raises(RecipeError, match=r"'my_algo' .* which has changed since"):
        RunDir(run.path).load_recipe()
