"""Env ids and perturbation parameters registered by installed packages (adarl.register_env / register_parameter).

A parameter registered on Hopper-v5 (the thigh's half-length) is applied through ``make_env`` on the compiled
model in both physics modes; a new gymnasium id registered with its model file validates in a recipe and is
perturbed by ``make_env``; an env without MuJoCo gets its parameter applied to the live env; unknown names give
installed plugins (the ``adarl.plugins`` entry points) a chance before the error, which lists what is registered
and says how to register; a name registered twice is an error. Every test puts the registries back.
"""

from __future__ import annotations

import shutil

import gymnasium
import mujoco
import numpy as np
import pytest

import adarl
from adarl import plugins
from adarl.envs import (
    FixedSchedule,
    ListSchedule,
    ParameterInfo,
    env_parameters,
    find_gym_env,
    make_env,
    make_schedule,
    perturbation_transform,
    preset_names,
    register_env,
    register_parameter,
    registration,
    registry,
    supported_envs,
    validate_values,
)
from adarl.envs.registry import check_env_id, default_xml_path
from adarl.errors import AdaRLValueError, RecipeError
from adarl.runtime.config import load_recipe

THIGH = ParameterInfo("thigh_length", 0.225, low=0.0, low_open=True, unit="m", description="thigh half-length")
PLUGIN_HOPPER = "PluginHopper-v0"
PLUGIN_CARTPOLE = "PluginCartPole-v0"


def thigh_length(editor, value, defaults):
    """A longer thigh: its capsule scaled about the hip, the leg (and what hangs from it) moved down to its end."""
    editor.scale_along("thigh_geom", value / defaults["thigh_length"])
    editor.set_body_z("leg", -(0.25 + 2 * value))  # v5 Hopper: leg body at -0.7 = -(leg half 0.25 + thigh 0.45)


@pytest.fixture(autouse=True)
def registries():
    """Every registration made by a test is undone (adarl's registries and gymnasium's)."""
    state = registration._registry_state()
    gym_ids = set(gymnasium.registry)
    yield
    registration._restore_registry(state)
    for env_id in set(gymnasium.registry) - gym_ids:
        del gymnasium.registry[env_id]


def _raises(fragments, fn, *args, **kwargs) -> str:
    with pytest.raises(AdaRLValueError) as info:
        fn(*args, **kwargs)
    msg = str(info.value)
    for fragment in fragments:
        assert fragment in msg, (fragment, msg)
    return msg


def _model(env):
    return find_gym_env(env).model


# ------------------------------------------------------------------------------------------ a parameter
@pytest.mark.parametrize("mode", ["consistent", "ompo"])
def test_a_registered_parameter_edits_the_compiled_model_and_never_compounds(mode):
    assert adarl.register_parameter is register_parameter and adarl.register_env is register_env
    register_parameter("Hopper-v5", THIGH, thigh_length)
    assert env_parameters("Hopper-v5")["thigh_length"] == THIGH
    fresh = mujoco.MjModel.from_xml_path(default_xml_path("Hopper-v5"))
    env = make_env("Hopper-v5", schedule=ListSchedule([{"thigh_length": 0.3}, {"thigh_length": 0.225}]), mode=mode)
    m = _model(env)
    thigh, leg = m.geom("thigh_geom").id, m.body("leg").id

    td = env.reset()
    assert float(td["dynamics", "thigh_length"]) == pytest.approx(0.3)
    assert m.geom_size[thigh][1] == pytest.approx(0.3)
    assert m.geom_pos[thigh][2] == pytest.approx(-0.3)  # the hip end stays at the thigh body's origin
    assert m.body_pos[leg][2] == pytest.approx(-0.85)
    thigh_body = m.geom_bodyid[thigh]
    if mode == "consistent":  # mass and inertia follow the geometry: as a model compiled from the edited XML
        spec = mujoco.MjSpec.from_file(default_xml_path("Hopper-v5"))
        spec.geom("thigh_geom").size = [0.05, 0.3, 0]
        spec.geom("thigh_geom").pos = [0, 0, -0.3]
        spec.body("leg").pos = [0, 0, -0.85]
        edited = spec.compile()
        assert m.body_mass[thigh_body] > fresh.body_mass[thigh_body] * 1.2
        for field in ("body_pos", "body_mass", "body_inertia", "body_ipos", "geom_size", "geom_pos", "geom_rbound"):
            np.testing.assert_allclose(getattr(m, field), getattr(edited, field), atol=1e-9, err_msg=field)
    else:  # OMPO's way: geometry only
        assert m.body_mass[thigh_body] == fresh.body_mass[thigh_body]
        assert m.geom_rbound[thigh] == pytest.approx(0.3 + 0.05)  # mj_setConst refreshed the bounding radius
    steps = env.rollout(5, break_when_any_done=False, auto_reset=False, tensordict=td)
    assert steps["next", "observation"].isfinite().all()

    env.reset()  # back at the default: the compiled model exactly
    for field in ("body_pos", "body_mass", "body_inertia", "geom_size", "geom_pos", "geom_rbound"):
        np.testing.assert_array_equal(getattr(m, field), getattr(fresh, field), err_msg=field)
    env.close()


def test_a_registered_parameter_combines_with_built_in_ones_and_is_checked_against_its_range():
    register_parameter("Hopper-v5", THIGH, thigh_length)
    env = make_env("Hopper-v5", schedule=FixedSchedule({"thigh_length": 0.3, "torso_length": 0.4}))
    env.reset()
    m = _model(env)
    assert m.geom("thigh_geom").size[1] == pytest.approx(0.3) and m.geom("torso_geom").size[1] == pytest.approx(0.4)
    assert m.body("thigh").pos[2] == pytest.approx(-0.4)  # the torso edit moves the thigh body, ours the leg
    env.close()
    _raises(["thigh_length", "-0.1", "> 0"], make_env, "Hopper-v5", schedule=FixedSchedule({"thigh_length": -0.1}))
    _raises(["thigh_length", "nan"], validate_values, "Hopper-v5", {"thigh_length": float("nan")})
    # a registered default must itself be valid
    bad = ParameterInfo("stub_length", -1.0, low=0.0, low_open=True)
    _raises(["default of stub_length", "> 0"], register_parameter, "Hopper-v5", bad, thigh_length)


def test_a_registered_parameter_validates_in_a_recipe():
    override = "env.perturbation.schedule={kind: uniform, low: {thigh_length: 0.2}, high: {thigh_length: 0.3}}"
    with pytest.raises(RecipeError, match="thigh_length"):
        load_recipe("quickstart", [override])
    register_parameter("Hopper-v5", THIGH, thigh_length)
    recipe = load_recipe("quickstart", [override])
    assert recipe.env.perturbation.schedule["high"] == {"thigh_length": 0.3}
    with pytest.raises(RecipeError, match=r"thigh_length.*> 0"):
        load_recipe("quickstart", ["env.perturbation.schedule={kind: fixed, values: {thigh_length: 0.0}}"])


def test_a_registered_edit_that_fails_is_named():
    register_parameter("Hopper-v5", ParameterInfo("shin_length", 1.0, low=0.0, low_open=True), _no_such_geom)
    for mode in ("consistent", "ompo"):
        env = make_env("Hopper-v5", schedule=FixedSchedule({"shin_length": 2.0}), mode=mode)
        _raises(["Hopper-v5", "shin_length", "no geom named 'shin_geom'"], env.reset)
        env.close()


def _no_such_geom(editor, value, defaults):
    editor.scale_along("shin_geom", value)


# ------------------------------------------------------------------------------------------ a new env id
def _register_plugin_hopper(tmp_path, **kwargs):
    xml = tmp_path / "plugin_hopper.xml"
    shutil.copy(default_xml_path("Hopper-v5"), xml)
    gymnasium.register(
        PLUGIN_HOPPER,
        entry_point="gymnasium.envs.mujoco.hopper_v5:HopperEnv",
        max_episode_steps=1000,
        kwargs={"xml_file": str(xml)},
    )
    register_env(PLUGIN_HOPPER, xml=xml, parameters=[(THIGH, thigh_length)], description="a test hopper", **kwargs)
    return xml


def test_a_registered_env_validates_in_a_recipe_and_is_perturbed_by_make_env(tmp_path):
    with pytest.raises(RecipeError, match="register_env"):
        load_recipe("quickstart", [f"env.id={PLUGIN_HOPPER}", "env.perturbation.preset=low"])
    low = {"kind": "uniform", "low": {"thigh_length": 0.2}, "high": {"thigh_length": 0.26}}
    _register_plugin_hopper(tmp_path, presets={"low": low})

    assert check_env_id(PLUGIN_HOPPER) == PLUGIN_HOPPER and PLUGIN_HOPPER in supported_envs(load=False)
    params = env_parameters(PLUGIN_HOPPER)
    assert {"thigh_length", "mass_scale", "friction_scale", "mass_scale:thigh"} <= set(params)
    assert "torso_length" not in params  # Hopper-v5's own parameters belong to Hopper-v5
    assert preset_names(PLUGIN_HOPPER) == ["low", "nominal", "none"]
    assert make_schedule(PLUGIN_HOPPER, "nominal").nominal() == {"thigh_length": 0.225}  # from the defaults

    recipe = load_recipe("quickstart", [f"env.id={PLUGIN_HOPPER}", "env.perturbation.preset=low"])
    assert recipe.env.id == PLUGIN_HOPPER
    with pytest.raises(RecipeError, match=r"preset.*not available.*'low', 'nominal', 'none'"):
        load_recipe("quickstart", [f"env.id={PLUGIN_HOPPER}"])  # the paper has no schedule for it

    env = make_env(PLUGIN_HOPPER, preset="low", seed=0)
    data = env.rollout(3, break_when_any_done=False)
    drawn = float(data["dynamics", "thigh_length"][0])
    assert 0.2 <= drawn <= 0.26
    assert _model(env).geom("thigh_geom").size[1] == pytest.approx(drawn)
    env.close()

    env = make_env(PLUGIN_HOPPER, schedule=FixedSchedule({"thigh_length": 0.3, "mass_scale:torso": 2.0}))
    env.reset()
    fresh = mujoco.MjModel.from_xml_path(default_xml_path("Hopper-v5"))
    m = _model(env)
    assert m.body("torso").mass[0] == pytest.approx(2 * fresh.body("torso").mass[0])
    assert m.geom("thigh_geom").size[1] == pytest.approx(0.3)
    env.close()


def test_a_registered_env_without_presets_gets_the_generic_boxes_and_a_nominal_from_its_defaults(tmp_path):
    _register_plugin_hopper(tmp_path)
    assert preset_names(PLUGIN_HOPPER) == ["low", "high", "nominal", "none"]
    assert set(make_schedule(PLUGIN_HOPPER, "high").params) == {"mass_scale", "friction_scale"}
    foot = ParameterInfo("foot_length", 0.195, low=0.0, low_open=True)
    register_parameter(PLUGIN_HOPPER, foot, lambda editor, value, defaults: editor.set_half_length("foot_geom", value))
    assert make_schedule(PLUGIN_HOPPER, "nominal").nominal() == {"thigh_length": 0.225, "foot_length": 0.195}
    _raises(["preset 'paper'", "'low', 'high', 'nominal', 'none'"], make_schedule, PLUGIN_HOPPER, "paper")


def _pole_mass(env, value, defaults):
    env.masspole = value
    env.total_mass = env.masspole + env.masscart
    env.polemass_length = env.masspole * env.length


def test_an_env_without_mujoco_gets_its_parameters_applied_to_the_live_env():
    gymnasium.register(PLUGIN_CARTPOLE, entry_point="gymnasium.envs.classic_control:CartPoleEnv", max_episode_steps=50)
    register_env(PLUGIN_CARTPOLE, parameters=[(ParameterInfo("pole_mass", 0.1, low=0.0, low_open=True), _pole_mass)])
    assert set(env_parameters(PLUGIN_CARTPOLE)) == {"pole_mass"}  # no MuJoCo model: no mass or friction scales
    assert preset_names(PLUGIN_CARTPOLE) == ["nominal", "none"]
    env = make_env(PLUGIN_CARTPOLE, schedule=ListSchedule([{"pole_mass": 0.3}, {"pole_mass": 0.2}]))
    live = find_gym_env(env)
    env.reset()
    assert live.masspole == 0.3 and live.polemass_length == pytest.approx(0.15)
    env.reset()
    assert live.masspole == 0.2 and live.total_mass == pytest.approx(1.2)
    perturbation_transform(env).applier.restore()  # every parameter back at its default
    assert live.masspole == 0.1 and live.polemass_length == pytest.approx(0.05)
    env.close()


# ------------------------------------------------------------------------------------------ unknown names
def test_unknown_names_load_the_installed_plugins_first(monkeypatch, tmp_path):
    calls = []

    def fake_load_entry_points():  # what an installed plugin's entry point does when it is loaded
        calls.append(1)
        if PLUGIN_HOPPER not in supported_envs(load=False):
            _register_plugin_hopper(tmp_path)
            register_parameter("Hopper-v5", THIGH, thigh_length)

    monkeypatch.setattr(plugins._registry, "load_entry_points", fake_load_entry_points)
    assert check_env_id("Hopper-v5") == "Hopper-v5" and calls == []  # known names never load plugins
    assert validate_values("Hopper-v5", {"torso_length": 0.3}) == {"torso_length": 0.3} and calls == []
    assert validate_values("Hopper-v5", {"thigh_length": 0.3}) == {"thigh_length": 0.3} and calls == [1]
    assert check_env_id(PLUGIN_HOPPER) == PLUGIN_HOPPER and len(calls) == 1  # registered by the first load


def test_a_recipe_naming_a_plugin_env_loads_it(monkeypatch, tmp_path):
    def fake_load_entry_points():
        if PLUGIN_HOPPER not in supported_envs(load=False):
            _register_plugin_hopper(tmp_path)

    monkeypatch.setattr(plugins._registry, "load_entry_points", fake_load_entry_points)
    recipe = load_recipe("quickstart", [f"env.id={PLUGIN_HOPPER}", "env.perturbation.preset=nominal"])
    assert recipe.env.id == PLUGIN_HOPPER


def test_unknown_env_ids_and_parameters_list_what_is_registered_and_say_how_to_register(tmp_path):
    msg = _raises(
        ["unknown env id 'Hoppr-v5'", "'Hopper-v5'", "did you mean 'Hopper-v5'", "register_env"],
        check_env_id,
        "Hoppr-v5",
    )
    assert "docs/adding-a-component.md" in msg and "'adarl.plugins' entry point" in msg
    _raises(["'Hopper-v4'", "use 'Hopper-v5'"], check_env_id, "Hopper-v4")  # other versions: still pointed at v5
    with pytest.raises(RecipeError, match=r"env\.id.*'Hopper-v5'.*register_env.*adding-a-component"):
        load_recipe("quickstart", ["env.id=Hoppr-v5"])

    _register_plugin_hopper(tmp_path)
    _raises([f"'{PLUGIN_HOPPER}'", "register_env"], check_env_id, "Pong-v5")  # registered ids are listed
    _raises([f"use '{PLUGIN_HOPPER}'"], check_env_id, "PluginHopper-v1")
    _raises(
        ["unknown parameter 'thigh_lenght'", "did you mean 'thigh_length'", "register_parameter"],
        validate_values,
        PLUGIN_HOPPER,
        {"thigh_lenght": 0.3},
    )
    _raises(["'thigh_length'", "torso_length"], make_env, "Hopper-v5", schedule=FixedSchedule({"thigh_length": 0.3}))


# ------------------------------------------------------------------------------------------ registration errors
def test_registering_a_name_twice_is_an_error_unless_replace(tmp_path):
    register_parameter("Hopper-v5", THIGH, thigh_length)
    _raises(
        ["'thigh_length' of Hopper-v5 is already registered", "replace=True"],
        register_parameter,
        "Hopper-v5",
        THIGH,
        thigh_length,
    )
    wider = ParameterInfo("thigh_length", 0.225, low=0.1, high=0.5)
    register_parameter("Hopper-v5", wider, thigh_length, replace=True)
    assert env_parameters("Hopper-v5")["thigh_length"] == wider
    assert [p.name for p in registry._SPECIFIC["Hopper-v5"]].count("thigh_length") == 1
    _raises(
        ["torso_length", "already registered (from adarl)"],
        register_parameter,
        "Hopper-v5",
        ParameterInfo("torso_length", 0.2),
        thigh_length,
    )

    _register_plugin_hopper(tmp_path)
    _raises([f"env {PLUGIN_HOPPER!r} is already registered", "replace=True"], register_env, PLUGIN_HOPPER)
    register_env(PLUGIN_HOPPER, replace=True)  # replaced as a whole: no model file, no parameters any more
    assert env_parameters(PLUGIN_HOPPER) == {} and preset_names(PLUGIN_HOPPER) == ["nominal", "none"]
    _raises(["one of adarl's own envs", "register_parameter"], register_env, "Hopper-v5")


def test_bad_registrations_are_refused_and_leave_nothing_behind(tmp_path):
    for name in ("mass_scale", "gravity", "episode", "mass_scale:torso", "not a name"):
        _raises(["register_parameter"], register_parameter, "Hopper-v5", ParameterInfo(name, 1.0), thigh_length)
    _raises(["applier of its own"], register_parameter, "CartPole-v1", THIGH, thigh_length)
    _raises(["must be a function"], register_parameter, "Hopper-v5", THIGH, None)
    _raises(["ParameterInfo"], register_parameter, "Hopper-v5", {"name": "x"}, thigh_length)
    _raises(["unknown env id 'Nope-v0'"], register_parameter, "Nope-v0", THIGH, thigh_length)
    _raises(["no MuJoCo model file", "hopper.xm"], register_env, "X-v0", xml="hopper.xm")
    _raises(["unknown preset name(s) ['extreme']"], register_env, "X-v0", presets={"extreme": {}})
    bad_preset = {"low": {"kind": "fixed", "values": {"thigh_length": 0.3}}}
    _raises(
        ["preset 'low'", "unknown parameter 'thigh_length'"], register_env, "X-v0", xml="hopper.xml", presets=bad_preset
    )
    assert (
        "X-v0" not in supported_envs(load=False)
        and "X-v0" not in registry._MUJOCO_XML
        and "X-v0" not in registry._PRESET_TABLE
    )
    assert "thigh_length" not in env_parameters("Hopper-v5")


def test_every_builtin_parameter_has_physical_bounds_and_a_plugin_may_declare_its_own():
    """Issue 30.7: no built-in parameter accepts 1e308 or 1e-300 (a length within 10x of nominal, a scale within
    100x of 1); a plugin parameter states its bounds with ParameterInfo (within_factor), refused in a recipe by name."""
    for env_id in ("Hopper-v5", "Walker2d-v5", "Ant-v5", "CartPole-v1", "InvertedPendulum-v5"):
        for name, info in env_parameters(env_id).items():
            assert info.contains(info.default), (env_id, name)
            assert not info.contains(1e308) and not info.contains(-1e308), (env_id, name, info.allowed())
            if info.low > 0 or info.low_open:  # a mass, a length (gravity 0 is physical)
                assert not info.contains(1e-300), (env_id, name, info.allowed())
    shin = ParameterInfo.within_factor("shin_length", 0.25, 4, unit="m", description="shin half-length")
    assert (shin.low, shin.high) == (0.0625, 1.0)
    register_parameter("Hopper-v5", shin, lambda editor, value, defaults: None)
    _raises(["shin_length", "1.5", ">= 0.0625 and <= 1"], validate_values, "Hopper-v5", {"shin_length": 1.5})
    with pytest.raises(RecipeError, match=r"shin_length.*1e\+308.*>= 0.0625 and <= 1"):
        load_recipe("quickstart", ["env.perturbation.schedule={kind: fixed, values: {shin_length: 1e308}}"])
    _raises(["factor"], ParameterInfo.within_factor, "x", 1.0, 0.5)


@pytest.mark.parametrize("kind", ["env", "rank_rule"])
def test_a_run_whose_env_or_rank_rule_package_is_gone_is_refused_by_package(tmp_path, monkeypatch, kind):
    """Issue 29.6: plugins.json records the env's and the rank rule's package (as the algorithm's); resume/eval of a
    run whose plugin package is gone names that package, not an unknown env or rule with a did-you-mean."""
    from adarl.core.rank import EnergyRule
    from adarl.runtime.run_folder.run_dir import RunDir

    monkeypatch.setattr(plugins._rank_rule, "_rank_rules", dict(plugins._rank_rule._rank_rules))
    state = registration._registry_state()
    with plugins.providing("adarl-gone-plugin"):
        gymnasium.register(PLUGIN_HOPPER, entry_point="gymnasium.envs.mujoco.hopper_v5:HopperEnv")
        register_env(PLUGIN_HOPPER, xml="hopper.xml")
        plugins.register_rank_rule("gone_rule", EnergyRule)
    recipe = load_recipe(
        "quickstart", [f"env.id={PLUGIN_HOPPER}", "env.perturbation.preset=nominal", "rank.rule=gone_rule"]
    )
    run = RunDir.create(tmp_path / "run")
    run.save_recipe(recipe)
    record = run.recorded_plugins()
    assert record["env"] == {"name": PLUGIN_HOPPER, "package": "adarl-gone-plugin", "version": None}
    assert record["rank_rule"] == {"name": "gone_rule", "package": "adarl-gone-plugin", "version": None}
    assert record["algorithm"]["package"] == "adarl" and record["modules"] == []
    if kind == "env":
        registration._restore_registry(state)  # the package is uninstalled: its env is gone
    else:
        del plugins._rank_rule._rank_rules["gone_rule"]
    with pytest.raises(RecipeError) as err:
        RunDir(tmp_path / "run").load_recipe()
    what = {"env": f"env {PLUGIN_HOPPER!r}", "rank_rule": "rank rule 'gone_rule'"}[kind]
    assert f"trained with {what} from the package 'adarl-gone-plugin'" in str(err.value)
    assert "pip install adarl-gone-plugin" in str(err.value)
