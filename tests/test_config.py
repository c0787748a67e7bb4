"""Recipe schema and loader: shipped recipes, extends, overrides, interpolation policy, error messages, round trip.

Every failure must be a RecipeError whose message names the key path, the offending value and what is allowed.
The env checks go through ``adarl.envs`` (SUPPORTED_ENVS, env_parameters, schedule_from_dict, ...); when that
module does not provide them (yet), a small stand-in with the same names and the paper's parameters is used.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

import adarl.envs as envs
from adarl.errors import RecipeError
from adarl.runtime.config import (
    SCHEMA_VERSION,
    Recipe,
    describe_schema,
    list_recipes,
    load_recipe,
    recipe_to_yaml,
    recipes_dir,
    save_resolved,
    validate_recipe,
)

REPO = Path(__file__).resolve().parent.parent
SHIPPED = sorted(p.stem for p in (REPO / "recipes").glob("*.yaml"))
PAPER_RECIPES = ["hopper_adarl", "walker2d_adarl", "ant_adarl", "humanoid_adarl"]


@pytest.fixture(scope="module", autouse=True)
def env_api():
    """The real adarl.envs registry (recipes are validated against it)."""
    real = envs
    assert real is not None and hasattr(real, "SUPPORTED_ENVS")
    yield real


def _err(name="quickstart", overrides=()) -> str:
    with pytest.raises(RecipeError) as info:
        load_recipe(name, list(overrides))
    return str(info.value)


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


# ------------------------------------------------------------------------------------------- shipped recipes


def test_expected_recipes_are_shipped():
    assert set(SHIPPED) >= {"base", "quickstart", *PAPER_RECIPES, "cartpole_adarl"}


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_recipe_loads_validates_and_describes_itself(name):
    r = load_recipe(name)
    assert isinstance(r, Recipe)
    assert r.name == name
    assert r.description and "\n" not in r.description
    assert r.version == SCHEMA_VERSION
    text = (REPO / "recipes" / f"{name}.yaml").read_text()
    if name != "base":
        assert yaml.safe_load(text)["extends"] == "base"


def test_list_recipes_names_and_descriptions():
    rows = dict(list_recipes())
    for name in SHIPPED:
        assert rows[name] == load_recipe(name).description
    assert "extend" in rows["base"].lower()  # marked as a base


def test_base_holds_the_paper_hyperparameters():
    r = load_recipe("base")
    for net in (r.network.actor, r.network.critic):
        assert net.num_cells == [64, 64] and net.activation == "relu" and net.low_rank_layers == [0, 1]
    a = r.algorithm
    # App. D.1: spinningup's SAC with lr 3e-3; spinningup's defaults where the paper is silent
    assert (a.name, a.lr, a.batch_size, a.gamma, a.tau) == ("sac", 3e-3, 100, 0.99, 0.005)
    assert (a.fixed_alpha, a.init_alpha, a.update_after, a.utd_ratio) == (True, 0.2, 1000, 1.0)
    assert (r.collector.frames_per_batch, r.collector.init_random_frames) == (50, 10_000)
    assert (r.rank.rule, r.rank.beta, r.rank.scope, r.rank.accept.mode) == ("energy", 0.98, "both", "projection")
    assert (r.lr_schedule.warmup_steps, r.lr_schedule.cosine) == (2000, True)
    assert r.replay.warm_start.mode == "refill"


@pytest.mark.parametrize("env", ["hopper", "walker2d", "ant", "humanoid"])
@pytest.mark.parametrize("baseline", ["sac_full", "sac_fixed", "parseval", "sparse"])
def test_sac_baselines_share_the_paper_sac_with_a_constant_learning_rate(env, baseline):
    r, adarl = load_recipe(f"baselines/{env}_{baseline}"), load_recipe(f"{env}_adarl")
    assert r.algorithm.model_dump(exclude={"parseval"}) == adarl.algorithm.model_dump(exclude={"parseval"})
    assert r.collector == adarl.collector and not r.rank.enabled
    assert (r.lr_schedule.warmup_steps, r.lr_schedule.cosine) == (0, False)  # spinningup: constant


@pytest.mark.parametrize("name", PAPER_RECIPES)
def test_paper_recipes_use_the_full_budget(name):
    r = load_recipe(name)
    assert r.collector.total_frames == 3_500_000
    assert r.replay.size == 1_000_000
    assert r.rank.interval == (700_000 if name.startswith("walker") else 1_000_000)
    assert r.env.perturbation.preset == "paper" and r.env.perturbation.schedule is None
    assert r.algorithm.lr == 3e-3 and r.rank.beta == 0.98
    assert r.env.id.lower().startswith(name.split("_")[0])


def _planned_updates(r: Recipe) -> int:
    c = r.collector
    return int((c.total_frames - min(c.init_random_frames, c.total_frames)) * r.algorithm.utd_ratio)


@pytest.mark.parametrize("name", ["quickstart", "cartpole_adarl"])
def test_small_recipes_have_two_rank_events(name):
    r = load_recipe(name)
    assert r.rank.enabled
    assert (_planned_updates(r) - 1) // r.rank.interval == 2


def test_quickstart_is_sized_for_ten_minutes():
    r = load_recipe("quickstart")
    assert r.env.id == "Hopper-v5" and r.env.perturbation.preset == "paper"
    assert 20_000 <= r.collector.total_frames <= 40_000 and r.algorithm.utd_ratio == 1.0
    assert r.eval.episodes == 3 and r.eval.interval == 10_000 and r.checkpoint.interval == 10_000
    assert r.collector.frames_per_batch == 250 and r.collector.init_random_frames == 5000
    assert r.replay.warm_start.frames == 2000


def test_cartpole_recipe():
    r = load_recipe("cartpole_adarl")
    assert r.env.id == "CartPole-v1" and r.env.perturbation.preset == "paper"
    assert r.collector.total_frames <= 20_000


# ------------------------------------------------------------------------------------------------ overrides


def test_overrides_apply():
    r = load_recipe(
        "quickstart",
        [
            "rank.beta=0.9",
            "network.actor.num_cells=[32,32]",
            "network.critic.num_cells[1]=48",
            "seed=7",
            "rank.rule=fixed",
            "rank.target_rank=8",
            "output.dir=/tmp/somewhere",
            "algorithm.target_entropy=-3",
            "algorithm.lr=1e-4",
        ],
    )
    assert r.rank.beta == 0.9 and r.network.actor.num_cells == [32, 32] and r.network.critic.num_cells == [64, 48]
    assert r.seed == 7 and r.rank.target_rank == 8 and r.output.dir == "/tmp/somewhere"
    assert r.algorithm.target_entropy == -3.0 and r.algorithm.lr == 1e-4


def test_override_mapping_merges_into_a_section():
    r = load_recipe("quickstart", ["rank={beta: 0.9, scope: actor}"])
    assert (r.rank.beta, r.rank.scope, r.rank.interval) == (0.9, "actor", 10_000)


def test_override_null_clears_an_optional_value():
    r = load_recipe("quickstart", ["network.actor.rank=8", "network.actor.rank=null"])
    assert r.network.actor.rank is None


def test_schedule_override_replaces_and_subkeys_merge():
    sched = "{kind: uniform, low: {torso_length: 0.3}, high: {torso_length: 0.5}}"
    r = load_recipe(
        "quickstart", [f"env.perturbation.schedule={sched}", "env.perturbation.schedule.high.torso_length=0.45"]
    )
    assert r.env.perturbation.schedule == {
        "kind": "uniform",
        "low": {"torso_length": 0.3},
        "high": {"torso_length": 0.45},
    }
    # a whole new schedule replaces the old one (no sinusoid keys left over in a fixed schedule)
    r = load_recipe(
        "quickstart",
        [
            "env.perturbation.schedule={kind: sinusoid, center: {torso_length: 0.4}, "
            "amplitude: {torso_length: 0.1}, frequency: 0.2}",
            "env.perturbation.schedule={kind: fixed, values: {torso_length: 0.3}}",
        ],
    )
    assert r.env.perturbation.schedule == {"kind": "fixed", "values": {"torso_length": 0.3}}
    # and keys can be set one by one into an unset schedule
    r = load_recipe(
        "quickstart", ["env.perturbation.schedule.kind=fixed", "env.perturbation.schedule.values.foot_length=0.3"]
    )
    assert r.env.perturbation.schedule == {"kind": "fixed", "values": {"foot_length": 0.3}}


@pytest.mark.parametrize(
    "override, expected",
    [
        ("rank.betta=0.9", ["rank.betta", "did you mean 'beta'", "interval"]),
        ("rnak.beta=0.9", ["rnak", "did you mean 'rank'"]),
        ("eval.intervl=5", ["eval.intervl", "did you mean 'interval'"]),
        ("network.actor.num_cels=[1]", ["network.actor.num_cels", "did you mean 'num_cells'"]),
    ],
)
def test_override_of_unknown_key_is_rejected_with_suggestion(override, expected):
    msg = _err(overrides=[override])
    for part in expected:
        assert part in msg


@pytest.mark.parametrize(
    "override, expected",
    [
        ("rank.beta", "key=value"),
        ("=3", "bad key"),
        ("rank..beta=1", "bad key"),
        ("+rank.foo=1", "not supported"),
        ("~rank.beta", "not supported"),
        ("rank.beta=[0.9", "YAML syntax error"),
        ("rank.beta.x=1", "single value"),
        ("network.actor.num_cells[0].x=1", "single value"),
        ("network.actor.num_cells[9]=1", "cannot apply"),
    ],
)
def test_bad_override_syntax(override, expected):
    msg = _err(overrides=[override])
    assert override in msg and expected in msg


def test_overrides_must_be_a_list_of_strings():
    with pytest.raises(RecipeError, match="list of 'key=value'"):
        load_recipe("quickstart", "rank.beta=0.9")
    with pytest.raises(RecipeError, match="key=value"):
        load_recipe("quickstart", [3])


# ---------------------------------------------------------------------------- bad values: key, value, allowed


@pytest.mark.parametrize(
    "override, parts",
    [
        ("rank.beta=1.5", ["rank.beta", "1.5", "must be a number in (0, 1)"]),
        ("rank.beta=0", ["rank.beta", "0", "(0, 1)"]),
        ("algorithm.gamma=1.01", ["algorithm.gamma", "1.01", "(0, 1]"]),
        ("algorithm.lr=-1", ["algorithm.lr", "-1", "> 0"]),
        ("algorithm.lr=.nan", ["algorithm.lr", "nan", "> 0"]),
        ("algorithm.batch_size=0", ["algorithm.batch_size", "0", ">= 1"]),
        ("seed=-1", ["seed", "-1", "[0, 4294967295]"]),
        ("seed=1.5", ["seed", "1.5", "an integer"]),
        ("env.num_envs=true", ["env.num_envs", "true", "an integer >= 1"]),
        ("env.parallel=maybe", ["env.parallel", "maybe", "true or false"]),
        ("rank.rule=enrgy", ["rank.rule", "'enrgy'", "'energy_inclusive'", "did you mean 'energy'"]),
        ("algorithm.loss_function=mse", ["algorithm.loss_function", "'mse'", "'smooth_l1'"]),
        ("algorithm.target_entropy=high", ["algorithm.target_entropy", "'high'", "'auto' or a number"]),
        ("device=gpu", ["device", "'gpu'", "'cuda:N'"]),
        ("network.actor.num_cells=[]", ["network.actor.num_cells", "[]", "non-empty list of integers >= 1"]),
        ("network.actor.num_cells=[64,0]", ["network.actor.num_cells[1]", "0", ">= 1"]),
        ("network.actor.activation=swish", ["network.actor.activation", "'swish'", "'softplus'"]),
        ("logging.backends=[csv,mlflow]", ["logging.backends[1]", "'mlflow'", "'tensorboard'"]),
        ("logging.backends=[csv,csv]", ["logging.backends", "distinct"]),
        ("collector=5", ["collector", "5", "a mapping with keys total_frames"]),
        ("name=a/b", ["name", "'a/b'", "letters, digits"]),
        ("lr_schedule.min_factor=2", ["lr_schedule.min_factor", "2", "[0, 1]"]),
        ("replay.warm_start.mode=flush", ["replay.warm_start.mode", "'flush'", "'refill'"]),
        ("env.perturbation.preset=extreme", ["env.perturbation.preset", "'extreme'", "'nominal'"]),
        ("output.dir=''", ["output.dir", "''", "non-empty string or null"]),
        ("version=0", ["version", "0", "1 (the only schema version so far)" if SCHEMA_VERSION == 1 else "from 1 to"]),
    ],
)
def test_bad_values_name_key_value_and_allowed(override, parts):
    msg = _err(overrides=[override])
    for part in parts:
        assert part in msg, (part, msg)


def test_several_problems_are_listed_together():
    msg = _err(overrides=["rank.beta=2", "seed=-3", "device=tpu"])
    assert "3 problems" in msg and "rank.beta" in msg and "seed" in msg and "device" in msg


def test_rank_larger_than_the_layer():
    msg = _err(overrides=["network.actor.rank=65"])
    assert "network.actor.rank" in msg and "65" in msg and "<= 64" in msg
    msg = _err(overrides=["network.critic.num_cells=[64,16]", "network.critic.rank=32"])
    assert "network.critic.rank" in msg and "<= 16" in msg and "64 -> 16" in msg
    assert load_recipe("quickstart", ["network.actor.rank=64"]).network.actor.rank == 64


def test_low_rank_layers_must_index_hidden_layers():
    msg = _err(overrides=["network.actor.low_rank_layers=[0,2]"])
    assert "network.actor.low_rank_layers" in msg and "0 .. 1" in msg and "[2]" in msg
    msg = _err(overrides=["network.actor.low_rank_layers=[1,1]"])
    assert "distinct" in msg
    msg = _err(overrides=["network.actor.low_rank_layers=[-1]"])
    assert "network.actor.low_rank_layers[0]" in msg and ">= 0" in msg


def test_rank_cross_checks():
    msg = _err(overrides=["rank.rule=fixed"])
    assert "rank.target_rank" in msg and "rule 'fixed' needs target_rank" in msg
    msg = _err(overrides=["rank.rule=fixed", "rank.target_rank=100"])
    assert "rank.target_rank" in msg and "100" in msg and "64" in msg
    msg = _err(overrides=["rank.min_rank=65"])
    assert "rank.min_rank" in msg and "65" in msg
    msg = _err(overrides=["network.actor.low_rank_layers=[]"])
    assert "network.actor.low_rank_layers" in msg and "rank.enabled=false" in msg
    # fine when the controller does not touch the actor
    load_recipe("quickstart", ["network.actor.low_rank_layers=[]", "rank.scope=critic"])
    load_recipe("quickstart", ["network.actor.low_rank_layers=[]", "rank.enabled=false"])


def test_budget_cross_checks():
    msg = _err(overrides=["algorithm.batch_size=200000"])
    assert "algorithm.batch_size" in msg and "200000" in msg and "replay.size (100000)" in msg
    msg = _err(overrides=["replay.warm_start.frames=200000"])
    assert "replay.warm_start.frames" in msg and "replay.size" in msg
    msg = _err(overrides=["collector.init_random_frames=40000"])
    assert "collector.init_random_frames" in msg and "collector.total_frames (30000)" in msg
    msg = _err(overrides=["collector.frames_per_batch=40000"])
    assert "collector.frames_per_batch" in msg


def test_unknown_env_is_rejected_with_suggestion():
    msg = _err(overrides=["env.id=Hoper-v5"])
    assert "env.id" in msg and "'Hoper-v5'" in msg and "'Hopper-v5'" in msg and "did you mean 'Hopper-v5'" in msg
    msg = _err(overrides=["env.id=Pong-v5"])
    assert "env.id" in msg and "'CartPole-v1'" in msg


def test_unknown_perturbation_parameter_is_rejected():
    msg = _err(overrides=["env.perturbation.schedule={kind: fixed, values: {torso_lenght: 0.3}}"])
    assert "env.perturbation.schedule.values.torso_lenght" in msg
    assert "'torso_length'" in msg and "did you mean 'torso_length'" in msg and "Hopper-v5" in msg
    msg = _err(overrides=["env.id=Ant-v5", "env.perturbation.schedule={kind: fixed, values: {torso_length: 0.3}}"])
    assert "'gravity'" in msg and "'wind'" in msg


@pytest.mark.parametrize(
    "schedule, parts",
    [
        ("{values: {torso_length: 0.3}}", ["env.perturbation.schedule.kind", "is required", "'sinusoid'"]),
        ("{kind: sine, values: {}}", ["env.perturbation.schedule.kind", "'sine'", "'sinusoid'"]),
        ("{kind: fixed, value: {torso_length: 0.3}}", ["schedule.value", "did you mean 'values'", "schedule.values"]),
        (
            "{kind: uniform, low: {torso_length: 0.5}, high: {torso_length: 0.3}}",
            ["schedule.high.torso_length", ">= low"],
        ),
        ("{kind: uniform, low: {torso_length: 0.3}, high: {foot_length: 0.5}}", ["schedule.high", "same parameters"]),
        (
            "{kind: sinusoid, center: {torso_length: 0.4}, amplitude: {torso_length: x}, frequency: 0.2}",
            ["schedule.amplitude.torso_length", "'x'", "finite number"],
        ),
        ("{kind: list, values: [], cycle: true}", ["schedule.values", "non-empty list"]),
        ("{kind: list, values: [{torso_length: 0.3}], cycle: 2}", ["schedule.cycle", "true or false"]),
    ],
)
def test_bad_schedules(schedule, parts):
    msg = _err(overrides=[f"env.perturbation.schedule={schedule}"])
    for part in parts:
        assert part in msg, (part, msg)


def test_good_schedules(env_api):
    for sched in [
        "{kind: sinusoid, center: {torso_length: 0.4, foot_length: 0.39}, "
        "amplitude: {torso_length: 0.1, foot_length: 0.1}, frequency: 0.2}",
        "{kind: sinusoid, center: {torso_length: 0.4}, amplitude: {torso_length: 0.1}, "
        "frequency: {torso_length: 0.2}, phase: 1.0}",
        "{kind: uniform, low: {torso_length: 0.31}, high: {torso_length: 0.49}}",
        "{kind: fixed, values: {foot_length: 0.3}}",
        "{kind: list, values: [{torso_length: 0.3}, {torso_length: 0.5}], cycle: false}",
    ]:
        r = load_recipe("quickstart", [f"env.perturbation.schedule={sched}"])
        assert r.env.perturbation.schedule["kind"] in sched
        assert env_api.schedule_from_dict(r.env.perturbation.schedule) is not None


def test_top_level_typo_in_a_file(tmp_path):
    p = _write(tmp_path / "typo.yaml", "extends: quickstart\nrank:\n  betta: 0.9\n")
    with pytest.raises(RecipeError) as info:
        load_recipe(str(p))
    msg = str(info.value)
    assert "rank.betta" in msg and "0.9" in msg and "did you mean 'beta'" in msg and str(p) in msg
    p = _write(tmp_path / "typo2.yaml", "extends: quickstart\nrnak: {beta: 0.9}\n")
    assert "did you mean 'rank'" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)


def test_missing_required_keys(tmp_path):
    p = _write(tmp_path / "empty.yaml", "")
    msg = str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "env: required key is missing" in msg and "collector: required key is missing" in msg


# ---------------------------------------------------------------------------------------------- file errors


def test_missing_recipe_name_and_file(tmp_path):
    msg = _err("quikstart")
    assert "quikstart" in msg and "did you mean 'quickstart'" in msg and "base" in msg
    msg = str(pytest.raises(RecipeError, load_recipe, str(tmp_path / "nope.yaml")).value)
    assert "nope.yaml" in msg and "not found" in msg
    for bad in ["", "   ", None, 3, "../../etc/passwd"]:
        with pytest.raises(RecipeError):
            load_recipe(bad)


def test_yaml_syntax_error(tmp_path):
    p = _write(tmp_path / "bad.yaml", "rank: {beta: 0.9\nseed: 1\n")
    msg = str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "YAML syntax error" in msg and str(p) in msg


@pytest.mark.parametrize("text", ["- a\n- b\n", "42\n", "just a string\n"])
def test_non_mapping_top_level(tmp_path, text):
    p = _write(tmp_path / "list.yaml", text)
    msg = str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "top level must be a mapping" in msg


def test_duplicate_keys_are_an_error(tmp_path):
    p = _write(tmp_path / "dup.yaml", "extends: quickstart\nseed: 1\nseed: 2\n")
    assert "duplicate key" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)


def test_loader_is_safe(tmp_path):
    marker = tmp_path / "pwned"
    p = _write(
        tmp_path / "evil.yaml",
        f"extends: quickstart\ndescription: !!python/object/apply:os.system ['touch {marker}']\n",
    )
    with pytest.raises(RecipeError, match="YAML"):
        load_recipe(str(p))
    assert not marker.exists()
    p = _write(tmp_path / "evil2.yaml", "a: &a [*a]\n")
    with pytest.raises(RecipeError):
        load_recipe(str(p))
    bomb = "a: &a [x,x,x,x,x,x,x,x,x,x]\n" + "".join(
        f"{c}: &{c} [*{p_},*{p_},*{p_},*{p_},*{p_},*{p_},*{p_},*{p_},*{p_},*{p_}]\n"
        for p_, c in zip("abcdefgh", "bcdefghi")
    )
    p = _write(tmp_path / "bomb.yaml", bomb)
    with pytest.raises(RecipeError, match="YAML"):
        load_recipe(str(p))


def test_newer_version_is_refused(tmp_path):
    p = _write(tmp_path / "future.yaml", f"extends: quickstart\nversion: {SCHEMA_VERSION + 1}\n")
    msg = str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "version" in msg and str(SCHEMA_VERSION + 1) in msg and "upgrade adarl" in msg
    # also when only the base is from the future
    _write(tmp_path / "newbase.yaml", f"extends: quickstart\nversion: {SCHEMA_VERSION + 1}\n")
    p = _write(tmp_path / "child.yaml", f"extends: newbase\nversion: {SCHEMA_VERSION}\n")
    assert "upgrade adarl" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "upgrade adarl" in _err(overrides=[f"version={SCHEMA_VERSION + 1}"])


def test_non_utf8_file(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes("description: caf\xe9\n".encode("latin-1"))
    assert "UTF-8" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)


# -------------------------------------------------------------------------------------------------- extends


def test_extends_merges_dicts_and_replaces_lists(tmp_path):
    p = _write(
        tmp_path / "child.yaml",
        "extends: quickstart\nnetwork:\n  actor:\n    num_cells: [32]\n    low_rank_layers: [0]\nrank:\n  beta: 0.9\n",
    )
    r = load_recipe(str(p))
    assert r.network.actor.num_cells == [32] and r.network.actor.low_rank_layers == [0]
    assert r.rank.beta == 0.9 and r.rank.interval == 10_000  # merged with quickstart's rank section
    assert r.collector.total_frames == 30_000  # from quickstart
    assert r.algorithm.lr == 3e-3  # from base, through quickstart
    # name and description describe the file; they are not inherited
    assert r.name == "child" and r.description == ""


def test_extends_relative_path_and_nested_chain(tmp_path):
    _write(
        tmp_path / "a" / "base2.yaml",
        "extends: base\ncollector: {total_frames: 1234, init_random_frames: 0}\nseed: 3\n",
    )
    _write(tmp_path / "b" / "mid.yaml", "extends: ../a/base2.yaml\nseed: 4\n")
    p = _write(tmp_path / "b" / "leaf.yaml", "extends: mid\nname: leafy\n")
    r = load_recipe(str(p))
    assert (r.name, r.seed, r.collector.total_frames) == ("leafy", 4, 1234)


def test_extends_cycle_is_detected(tmp_path):
    _write(tmp_path / "x.yaml", "extends: y\n")
    _write(tmp_path / "y.yaml", "extends: z.yaml\n")
    _write(tmp_path / "z.yaml", "extends: x\n")
    msg = str(pytest.raises(RecipeError, load_recipe, str(tmp_path / "x.yaml")).value)
    assert "cycle" in msg and "x.yaml" in msg and "y.yaml" in msg and "z.yaml" in msg
    _write(tmp_path / "self.yaml", "extends: ./self.yaml\n")
    assert "cycle" in str(pytest.raises(RecipeError, load_recipe, str(tmp_path / "self.yaml")).value)


def test_a_file_may_extend_the_shipped_recipe_of_its_own_name(tmp_path):
    p = _write(tmp_path / "quickstart.yaml", "extends: quickstart\nseed: 9\n")
    r = load_recipe(str(p))
    assert r.seed == 9 and r.collector.total_frames == 30_000


def test_extends_errors(tmp_path):
    p = _write(tmp_path / "c.yaml", "extends: nosuch\n")
    assert "extends = 'nosuch'" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    p = _write(tmp_path / "d.yaml", "extends: [base]\n")
    assert "extends" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    p = _write(tmp_path / "e.yaml", "extends: missing.yaml\n")
    assert "not found" in str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    p = _write(tmp_path / "f.yaml", "extends: quickstart\nrank: 3\n")
    with pytest.raises(RecipeError, match="rank"):
        load_recipe(str(p))


def test_child_schedule_replaces_the_base_schedule(tmp_path):
    _write(
        tmp_path / "sbase.yaml",
        "extends: quickstart\nenv:\n  perturbation:\n    schedule: {kind: sinusoid, center: {torso_length: 0.4}, "
        "amplitude: {torso_length: 0.1}, frequency: 0.2}\n",
    )
    p = _write(
        tmp_path / "schild.yaml",
        "extends: sbase\nenv:\n  perturbation:\n"
        "    schedule: {kind: uniform, low: {torso_length: 0.3}, high: {torso_length: 0.5}}\n",
    )
    assert load_recipe(str(p)).env.perturbation.schedule == {
        "kind": "uniform",
        "low": {"torso_length": 0.3},
        "high": {"torso_length": 0.5},
    }
    # a child that does not mention the schedule keeps the base's
    p = _write(tmp_path / "skeep.yaml", "extends: sbase\nseed: 1\n")
    assert load_recipe(str(p)).env.perturbation.schedule["kind"] == "sinusoid"


def test_recipes_path_env_var(tmp_path, monkeypatch):
    _write(tmp_path / "mine.yaml", "extends: quickstart\ndescription: my own\n")
    _write(
        tmp_path / "baselines" / "plain_sac.yaml",
        "extends: quickstart\ndescription: no rank control\nrank: {enabled: false}\n",
    )
    _write(
        tmp_path / "quickstart.yaml",
        "extends: base\ndescription: shadowing quickstart\ncollector: {total_frames: 20000}\n",
    )
    other = tmp_path / "other"
    _write(other / "x.yaml", "extends: quickstart\ndescription: from the second folder\n")
    monkeypatch.setenv("ADARL_RECIPES_PATH", os.pathsep.join([str(tmp_path), str(other)]))
    assert recipes_dir()[:2] == [tmp_path, other] and recipes_dir()[-1] == REPO / "recipes"
    rows = dict(list_recipes())
    assert rows["mine"] == "my own" and rows["baselines/plain_sac"] == "no rank control"
    assert rows["x"] == "from the second folder" and rows["quickstart"] == "shadowing quickstart"
    assert rows["hopper_adarl"]  # shipped ones still listed
    assert load_recipe("baselines/plain_sac").rank.enabled is False
    assert load_recipe("mine").description == "my own"
    assert load_recipe("quickstart").collector.total_frames == 20_000  # the earlier folder wins


def test_list_recipes_reports_unreadable_files(tmp_path, monkeypatch):
    _write(tmp_path / "broken.yaml", "a: [\n")
    monkeypatch.setenv("ADARL_RECIPES_PATH", str(tmp_path))
    rows = dict(list_recipes())
    assert rows["broken"].startswith("(unreadable")


# ----------------------------------------------------------------------------------------- interpolations


def test_node_interpolation_is_resolved_late(tmp_path):
    p = _write(tmp_path / "interp.yaml", "extends: quickstart\ncheckpoint:\n  interval: ${collector.total_frames}\n")
    assert load_recipe(str(p)).checkpoint.interval == 30_000
    assert load_recipe(str(p), ["collector.total_frames=20000"]).checkpoint.interval == 20_000
    assert load_recipe("quickstart", ["eval.interval=${checkpoint.interval}"]).eval.interval == 10_000


@pytest.mark.parametrize("value", ["${oc.env:HOME}", "${oc.decode:1}", "x ${oc.env:USER,nobody} y", "${foo:bar}"])
def test_resolver_interpolations_are_rejected(tmp_path, value):
    p = _write(tmp_path / "res.yaml", f'extends: quickstart\ndescription: "{value}"\n')
    msg = str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "description" in msg and "resolver" in msg
    msg = _err(overrides=[f"description='{value}'"])
    assert "resolver" in msg
    msg = _err(overrides=[f"rank.interval={value}"])
    assert "rank.interval" in msg and "resolver" in msg


def test_bad_interpolations(tmp_path):
    assert "cannot resolve" in _err(overrides=["eval.interval=${nope.nothing}"])
    assert "malformed interpolation" in _err(overrides=["description='${'"])
    p = _write(tmp_path / "loop.yaml", "extends: quickstart\nseed: ${eval.interval}\neval: {interval: '${seed}'}\n")
    with pytest.raises(RecipeError):
        load_recipe(str(p))
    p = _write(tmp_path / "missing.yaml", "env:\n  id: ???\ncollector: {total_frames: 100, init_random_frames: 0}\n")
    msg = str(pytest.raises(RecipeError, load_recipe, str(p)).value)
    assert "env.id" in msg and "required value not set" in msg


def test_escaped_interpolation_is_literal_and_round_trips(tmp_path):
    p = _write(tmp_path / "esc.yaml", "extends: quickstart\ndescription: 'costs \\${5} and ${seed}'\n")
    r = load_recipe(str(p))
    assert r.description == "costs ${5} and 0"
    out = save_resolved(r, tmp_path / "out.yaml")
    assert load_recipe(str(out)) == r


# ------------------------------------------------------------------------------------------------ round trip


@pytest.mark.parametrize("name", SHIPPED)
def test_save_resolved_round_trip(tmp_path, name):
    r = load_recipe(name)
    path = save_resolved(r, tmp_path / "run" / "recipe.yaml")
    text = path.read_text()
    assert "extends" not in yaml.safe_load(text)
    back = load_recipe(str(path))
    assert back == r
    assert recipe_to_yaml(back) == text


def test_round_trip_with_overrides_and_odd_strings(tmp_path):
    r = load_recipe(
        "quickstart",
        [
            "env.perturbation.schedule={kind: list, values: [{torso_length: 0.3}, {torso_length: 0.5}], cycle: false}",
            "description='1e-3'",
            "name='3e5'",
            "logging.backends=[csv, tensorboard]",
            "output.dir='null'",
            "algorithm.target_entropy=-2.5",
        ],
    )
    assert r.description == "1e-3" and r.name == "3e5" and r.output.dir == "null"
    back = load_recipe(str(save_resolved(r, tmp_path / "r.yaml")))
    assert back == r


def test_recipe_to_yaml_refuses_unrepresentable_values():
    r = load_recipe("quickstart").model_copy(update={"description": "???"})
    with pytest.raises(RecipeError, match="missing"):
        recipe_to_yaml(r)
    with pytest.raises(RecipeError):
        recipe_to_yaml({"name": "x"})


def test_save_resolved_unwritable(tmp_path):
    blocker = _write(tmp_path / "file", "x")
    with pytest.raises(RecipeError, match="cannot write"):
        save_resolved(load_recipe("quickstart"), blocker / "recipe.yaml")


# --------------------------------------------------------------------------------------- validate_recipe, docs


def test_validate_recipe_on_mappings():
    r = validate_recipe(
        {"name": "m", "env": {"id": "Hopper-v5"}, "collector": {"total_frames": 5000, "init_random_frames": 0}}
    )
    assert r.network.actor.num_cells == [64, 64] and r.rank.beta == 0.98
    with pytest.raises(RecipeError, match="top level must be a mapping"):
        validate_recipe([1, 2])
    msg = str(pytest.raises(RecipeError, validate_recipe, {"name": "m", 1: 2, None: 3}).value)
    assert "unknown key" in msg


def test_validate_recipe_hints():
    base = {"name": "m", "env": {"id": "Hopper-v5"}, "collector": {"total_frames": 5000, "init_random_frames": 0}}
    msg = str(pytest.raises(RecipeError, validate_recipe, {**base, "rank.beta": 0.9}).value)
    assert "'rank.beta'" not in msg and "rank.beta: unknown key" in msg and "did you mean 'rank'" in msg
    assert "nest keys as mappings" in msg
    msg = str(pytest.raises(RecipeError, validate_recipe, {**base, "extends": "base"}).value)
    assert "load_recipe" in msg


def test_yaml_numbers_and_strings_coerce_sensibly():
    r = validate_recipe(
        {"name": 7, "env": {"id": "Hopper-v5"}, "collector": {"total_frames": 3.5e6}, "algorithm": {"lr": "3e-3"}}
    )
    assert r.name == "7" and r.collector.total_frames == 3_500_000 and isinstance(r.collector.total_frames, int)
    assert r.algorithm.lr == 3e-3


def test_docs_list_every_key():
    doc = (REPO / "docs" / "recipes.md").read_text()
    for path, _default, _allowed, why in describe_schema():
        assert f"`{path}`" in doc, path
        assert why, path


def test_errors_are_recipe_errors_and_value_errors():
    assert issubclass(RecipeError, ValueError)
    with pytest.raises(ValueError):
        load_recipe("quickstart", ["rank.beta=3"])
