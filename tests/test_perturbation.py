"""PerturbedDynamicsEnvTransform and make_env: the physics really changes, values are reported, runs reproduce."""

from __future__ import annotations

import io
import json
import math

import mujoco
import numpy as np
import pytest
import torch
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.libs.gym import GymEnv
from torchrl.envs.utils import check_env_specs

from adarl.envs import (
    SUPPORTED_ENVS,
    FixedSchedule,
    ListSchedule,
    PerturbedDynamicsEnvTransform,
    SinusoidSchedule,
    UniformSchedule,
    dynamics_state_dict,
    env_parameters,
    find_gym_env,
    load_dynamics_state_dict,
    make_env,
    make_eval_env,
    make_schedule,
    perturbation_transform,
)
from adarl.envs.mujoco_appliers import MujocoDynamics
from adarl.envs.registry import default_xml_path
from adarl.errors import AdaRLValueError

HOPPER_TORSO_MASS = 3.66519143  # compiled v5 default
HOPPER_TORSO_MASS_T04 = 6.80678408  # NOTES.md: torso half-length 0.4 with mass following geometry


def _model(env):
    return find_gym_env(env).model


def _draws(env, n, key="torso_length"):
    """Values of ``key`` for the next ``n`` episodes (each reset draws one)."""
    return [float(env.reset()["dynamics", key]) for _ in range(n)]


# ------------------------------------------------------------------------------------------------- physics
@pytest.mark.parametrize("mode, torso_mass", [("consistent", HOPPER_TORSO_MASS_T04), ("ompo", HOPPER_TORSO_MASS)])
def test_longer_torso_weighs_more_only_in_consistent_mode(mode, torso_mass):
    env = make_env("Hopper-v5", schedule=FixedSchedule({"torso_length": 0.4}), mode=mode)
    env.reset()
    m = _model(env)
    assert m.body("torso").mass[0] == pytest.approx(torso_mass, rel=1e-6)
    # the geometry is the same in both modes (OMPO's edits): torso z = 1.05 + T, thigh at -T, capsule half T
    assert m.body("torso").pos[2] == pytest.approx(1.45)
    assert m.body("thigh").pos[2] == pytest.approx(-0.4)
    assert m.geom("torso_geom").size[1] == pytest.approx(0.4)


def test_consistent_mode_matches_a_model_compiled_from_the_edited_xml():
    env = make_env("Walker2d-v5", schedule=FixedSchedule({"torso_length": 0.3, "foot_length": 0.15}))
    env.reset()
    live = _model(env)
    spec = mujoco.MjSpec.from_file(default_xml_path("Walker2d-v5"))
    spec.body("torso").pos = [0, 0, 1.05 + 0.3]
    for thigh in ("thigh", "thigh_left"):
        spec.body(thigh).pos = [0, 0, -0.3]
    spec.geom("torso_geom").size = [0.05, 0.3, 0]
    for foot in ("foot_geom", "foot_left_geom"):
        spec.geom(foot).size = [0.06, 0.15, 0]
    fresh = spec.compile()
    for field in (
        "body_pos",
        "body_mass",
        "body_inertia",
        "body_ipos",
        "geom_size",
        "geom_rbound",
        "body_subtreemass",
        "dof_invweight0",
        "body_invweight0",
    ):
        np.testing.assert_allclose(getattr(live, field), getattr(fresh, field), atol=1e-9, err_msg=field)


@pytest.mark.parametrize("mode", ["consistent", "ompo"])
def test_long_foot_still_touches_the_floor(mode):
    env = make_env("Hopper-v5", schedule=FixedSchedule({"foot_length": 0.545}), mode=mode)
    env.reset()
    unwrapped = find_gym_env(env)
    m, d = unwrapped.model, unwrapped.data
    foot, floor = m.geom("foot_geom").id, m.geom("floor").id
    # the bounding radius follows the longer capsule (OMPO leaves it stale): half-length + radius
    assert m.geom_rbound[foot] == pytest.approx(0.545 + 0.06)
    touching = 0
    for _ in range(300):
        mujoco.mj_step(m, d)
        touching += any({int(c.geom1), int(c.geom2)} == {foot, floor} for c in d.contact[: d.ncon])
    assert touching > 100


def test_nominal_episode_restores_the_compiled_model_exactly():
    env = make_env(
        "Hopper-v5",
        schedule=ListSchedule(
            [
                {
                    "torso_length": 0.5,
                    "foot_length": 0.3,
                    "mass_scale": 1.5,
                    "friction_scale": 0.5,
                    "mass_scale:foot": 2.0,
                },
                {
                    "torso_length": 0.2,
                    "foot_length": 0.195,
                    "mass_scale": 1.0,
                    "friction_scale": 1.0,
                    "mass_scale:foot": 1.0,
                },
            ]
        ),
    )
    fresh = mujoco.MjModel.from_xml_path(default_xml_path("Hopper-v5"))
    m = _model(env)
    env.reset()
    assert m.body("foot").mass[0] > 2 * fresh.body("foot").mass[0]
    env.reset()  # back at the defaults: no drift, nothing compounded
    for name in dir(fresh):
        value = getattr(fresh, name)
        if not name.startswith("_") and isinstance(value, np.ndarray) and value.dtype.kind == "f":
            np.testing.assert_array_equal(getattr(m, name), value, err_msg=name)
    for name in ("gravity", "wind", "density", "viscosity"):
        np.testing.assert_array_equal(getattr(m.opt, name), getattr(fresh.opt, name))


def test_mass_and_friction_scales_are_relative_to_the_defaults_and_do_not_compound():
    sched = FixedSchedule({"mass_scale": 2.0, "mass_scale:torso": 3.0, "friction_scale": 0.5})
    env = make_env("Hopper-v5", schedule=sched)
    fresh = mujoco.MjModel.from_xml_path(default_xml_path("Hopper-v5"))
    m = _model(env)
    for _ in range(3):
        env.reset()
        np.testing.assert_allclose(m.body_mass[2:], 2.0 * fresh.body_mass[2:])
        assert m.body("torso").mass[0] == pytest.approx(6.0 * fresh.body("torso").mass[0])
        np.testing.assert_allclose(m.body_inertia[1], 6.0 * fresh.body_inertia[1])
        np.testing.assert_allclose(m.geom_friction, 0.5 * fresh.geom_friction)


def test_ant_gravity_and_wind_are_set_and_act():
    env = make_env("Ant-v5", schedule=FixedSchedule({"gravity": 12.0, "wind": 1.5}))
    env.reset()
    unwrapped = find_gym_env(env)
    m, d = unwrapped.model, unwrapped.data
    np.testing.assert_array_equal(m.opt.gravity, [0.0, 0.0, -12.0])
    np.testing.assert_array_equal(m.opt.wind, [-1.5, 0.0, 0.0])
    assert m.opt.density == 1.2 and m.opt.viscosity == 2e-5
    # the wind pushes the free-floating torso along -x (zero wind, same state: no push)
    mujoco.mj_forward(m, d)
    qacc_wind = d.qacc[0]
    m.opt.wind[:] = 0.0
    mujoco.mj_forward(m, d)
    assert qacc_wind < d.qacc[0] - 1e-6
    assert make_schedule("Ant-v5", "paper").sample(1, None)["gravity"] == pytest.approx(14.715 + 4.905 * math.sin(0.5))


def test_cartpole_pole_length():
    env = make_env("CartPole-v1", schedule=FixedSchedule({"pole_length": 0.6}))
    td = env.reset()
    unwrapped = find_gym_env(env)
    assert unwrapped.length == 0.6
    assert unwrapped.polemass_length == pytest.approx(unwrapped.masspole * 0.6)
    assert float(td["dynamics", "pole_length"]) == pytest.approx(0.6)
    paper = make_env("CartPole-v1", seed=0)
    lengths = _draws(paper, 5, "pole_length")
    assert all(0.475 <= v <= 0.525 for v in lengths) and len(set(lengths)) == 5


def test_inverted_pendulum_pole_scales_about_the_hinge():
    consistent = make_env("InvertedPendulum-v5", schedule=FixedSchedule({"pole_length": 0.36}))
    ompo = make_env("InvertedPendulum-v5", schedule=FixedSchedule({"pole_length": 0.36}), mode="ompo")
    fresh = mujoco.MjModel.from_xml_path(default_xml_path("InvertedPendulum-v5"))
    consistent.reset(), ompo.reset()
    a, b = _model(consistent), _model(ompo)
    np.testing.assert_allclose(a.geom("cpole").size, b.geom("cpole").size)
    np.testing.assert_allclose(a.geom("cpole").pos, 1.2 * fresh.geom("cpole").pos, atol=1e-12)
    assert a.body("pole").mass[0] > 1.15 * fresh.body("pole").mass[0]
    assert b.body("pole").mass[0] == fresh.body("pole").mass[0]


# ------------------------------------------------------------------------------------------------- output
def test_values_at_reset_and_every_step_declared_and_not_in_the_observation():
    check_env_specs(make_env("Hopper-v5", seed=0))
    env = make_env("Hopper-v5", seed=0, max_episode_steps=20)
    assert ("dynamics", "torso_length") in env.observation_spec.keys(True)
    assert env.observation_spec["observation"].shape == (11,)
    td = env.reset()
    assert td["dynamics", "torso_length"].dtype == torch.float32 and td["dynamics", "torso_length"].shape == ()
    assert float(td["dynamics", "torso_length"]) == pytest.approx(0.4)  # paper: 0.4 + 0.2 sin(0)
    assert int(td["dynamics", "episode"]) == 0
    # several episodes (termination or the 20-step limit), starting from this reset
    roll = env.rollout(45, break_when_any_done=False, auto_reset=False, tensordict=td)
    assert roll["observation"].shape == (45, 11)
    done = roll["next", "done"].squeeze(-1).long()
    expected_episode = torch.cumsum(done, 0) - done  # episodes finished before each step
    eps = roll["next", "dynamics", "episode"]
    assert torch.equal(eps, expected_episode) and eps[-1] >= 2
    torso = roll["next", "dynamics", "torso_length"]
    for k in range(int(eps[-1]) + 1):
        expected = 0.4 + 0.2 * math.sin(0.2 * k)
        assert torch.allclose(torso[eps == k], torch.tensor(expected, dtype=torch.float32))
    # the root entries (what the policy saw) carry the same episode's values
    assert torch.equal(roll["dynamics", "episode"], eps)
    assert torch.equal(roll["dynamics", "torso_length"], torso)
    assert "episode_reward" in roll["next"].keys()


def test_custom_out_key():
    env = TransformedEnv(
        GymEnv("Hopper-v5"), PerturbedDynamicsEnvTransform("Hopper-v5", "nominal", out_key=("info", "dyn"))
    )
    td = env.rollout(3)
    assert float(td["next", "info", "dyn", "foot_length"][-1]) == pytest.approx(0.39)
    assert ("info", "dyn", "episode") in env.observation_spec.keys(True)


def test_full_episode_under_rollout():
    env = make_env("Walker2d-v5", preset="high", seed=1)
    roll = env.rollout(1000, break_when_any_done=True)
    done = roll["next", "done"].squeeze(-1)
    assert done[-1] and not done[:-1].any()
    assert roll["next", "episode_reward"][-1].item() == pytest.approx(roll["next", "reward"].sum().item(), rel=1e-4)


# ------------------------------------------------------------------------------------------------- seeding
def test_same_seed_same_sequence_different_seed_different():
    a = _draws(make_env("Hopper-v5", preset="high", seed=7), 4)
    b = _draws(make_env("Hopper-v5", preset="high", seed=7), 4)
    c = _draws(make_env("Hopper-v5", preset="high", seed=8), 4)
    assert a == b and a != c and len(set(a)) == 4
    # reseeding the same env restarts the stream
    env = make_env("Hopper-v5", preset="high", seed=7)
    first = _draws(env, 2)
    env.set_seed(7)
    assert _draws(env, 2) == first == a[:2]


def test_explicit_transform_seed_and_independence_from_gymnasium_stream():
    t1 = PerturbedDynamicsEnvTransform("Hopper-v5", "low", seed=3)
    t2 = PerturbedDynamicsEnvTransform("Hopper-v5", "low", seed=3)
    e1, e2 = TransformedEnv(GymEnv("Hopper-v5"), t1), TransformedEnv(GymEnv("Hopper-v5"), t2)
    assert _draws(e1, 3) == _draws(e2, 3)
    # seeded by the env: the dynamics draws are not the env's own reset-noise draws
    env = TransformedEnv(GymEnv("Hopper-v5"), PerturbedDynamicsEnvTransform("Hopper-v5", "low"))
    env.set_seed(0)
    low, high = 0.31, 0.49
    drawn = _draws(env, 1)[0]
    gym_first = np.random.Generator(np.random.PCG64(np.random.SeedSequence(0))).uniform(low, high)
    assert drawn != pytest.approx(gym_first)


def test_serial_env_two_workers_draw_their_own_sequences():
    env = make_env("Hopper-v5", preset="high", num_envs=2, seed=0, max_episode_steps=5)
    roll = env.rollout(12, break_when_any_done=False)
    assert roll.batch_size == (2, 12)
    episodes = roll["next", "dynamics", "episode"]
    assert episodes[:, -1].tolist() == [2, 2]  # per-worker episode index
    torso = roll["dynamics", "torso_length"]
    assert not torch.equal(torso[0], torso[1])
    again = make_env("Hopper-v5", preset="high", num_envs=2, seed=0, max_episode_steps=5).rollout(
        12, break_when_any_done=False
    )
    assert torch.equal(again["dynamics", "torso_length"], torso)
    # the paper's sinusoid is interleaved across workers: worker w plays episodes w, w + 2, ...
    sine = make_env("Hopper-v5", num_envs=2, max_episode_steps=5).rollout(6, break_when_any_done=False)
    first = sine["dynamics", "torso_length"][:, 0]
    assert first.tolist() == pytest.approx([0.4, 0.4 + 0.2 * math.sin(0.2)])
    assert float(sine["dynamics", "torso_length"][0, -1]) == pytest.approx(0.4 + 0.2 * math.sin(0.4))


def test_state_dict_round_trip_continues_the_same_sequence():
    env = make_env("Hopper-v5", preset="high", seed=11)
    _draws(env, 3)
    state = perturbation_transform(env).state_dict()
    buffer = io.BytesIO()
    torch.save(state, buffer)
    expected = _draws(env, 3)
    other = make_env("Hopper-v5", preset="high", seed=99)
    buffer.seek(0)
    other_t = perturbation_transform(other)
    other_t.load_state_dict(torch.load(buffer, weights_only=True))
    assert _draws(other, 3) == expected
    assert other_t.episode == 5
    # the whole env's state dict carries it too, and so does a batched env's
    serial = make_env("Hopper-v5", preset="high", num_envs=2, seed=5)
    serial.reset()
    saved = dynamics_state_dict(serial)
    assert sorted(saved) == ["worker0", "worker1"]
    nxt = serial.reset()["dynamics", "torso_length"].clone()
    fresh = make_env("Hopper-v5", preset="high", num_envs=2, seed=6)
    load_dynamics_state_dict(fresh, saved)
    assert torch.equal(fresh.reset()["dynamics", "torso_length"], nxt)


# ------------------------------------------------------------------------------------------------- eval / misc
def test_make_eval_env_fixes_the_nominal_dynamics():
    env = make_eval_env("Hopper-v5", "high")
    assert _draws(env, 3) == pytest.approx([0.4] * 3)
    env = make_eval_env("Hopper-v5", {"torso_length": 0.3})
    assert _draws(env, 2) == pytest.approx([0.3] * 2)
    env = make_eval_env("Ant-v5", SinusoidSchedule({"gravity": 12.0}, {"gravity": 2.0}, 0.5))
    assert _draws(env, 2, "gravity") == pytest.approx([12.0] * 2)
    plain = make_eval_env("Hopper-v5", "none")
    assert "dynamics" not in plain.reset().keys()
    assert "dynamics" not in make_env("Hopper-v5", perturb=False).reset().keys()


def test_registry_and_presets():
    assert {"Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "CartPole-v1", "InvertedPendulum-v5"} <= set(
        SUPPORTED_ENVS
    )
    hopper = env_parameters("Hopper-v5")
    assert hopper["torso_length"].default == 0.2 and hopper["foot_length"].default == 0.195
    assert {"mass_scale", "friction_scale", "mass_scale:torso", "mass_scale:foot"} <= set(hopper)
    assert set(env_parameters("CartPole-v1")) == {"pole_length"}
    assert make_schedule("Hopper-v5", "low").to_dict() == {
        "kind": "uniform",
        "low": {"foot_length": 0.305, "torso_length": 0.31},
        "high": {"foot_length": 0.485, "torso_length": 0.49},
    }
    assert make_schedule("Walker2d-v5", "high").bounds() == {"foot_length": (0.03, 0.17), "torso_length": (0.06, 0.34)}
    assert make_schedule("Humanoid-v5", "paper").bounds()["wind"] == pytest.approx((0.5, 1.5))
    assert make_schedule("Hopper-v5", "nominal").nominal() == {"torso_length": 0.4, "foot_length": 0.39}
    for env_id in SUPPORTED_ENVS:
        for preset in ("low", "high", "nominal"):
            s = make_schedule(env_id, preset)
            assert json.loads(json.dumps(s.to_dict())) == s.to_dict()


def test_halfcheetah_leaves_no_mujoco_log(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    env = make_env("HalfCheetah-v5", preset="low", seed=0)
    env.rollout(3)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------- errors
def _raises(match_all, fn, *args, **kwargs):
    with pytest.raises(AdaRLValueError) as info:
        fn(*args, **kwargs)
    for text in match_all:
        assert text in str(info.value), str(info.value)
    return str(info.value)


def test_error_paths_name_the_allowed_values():
    _raises(["'Foo-v0'", "Hopper-v5", "CartPole-v1"], make_env, "Foo-v0")
    _raises(["'Hopper-v4'", "use 'Hopper-v5'"], make_env, "Hopper-v4")
    _raises(["'CartPole-v0'", "use 'CartPole-v1'"], env_parameters, "CartPole-v0")
    _raises(
        ["'gravity'", "Hopper-v5", "torso_length", "mass_scale:torso"],
        make_env,
        "Hopper-v5",
        schedule=FixedSchedule({"gravity": 9.81}),
    )
    _raises(
        ["'mass_scale:wing'", "torso_length"],
        PerturbedDynamicsEnvTransform,
        "Hopper-v5",
        FixedSchedule({"mass_scale:wing": 2.0}),
    )
    for bad in (-0.1, 0.0):
        _raises([repr(bad), ">= 0.02 and <= 2"], make_env, "Hopper-v5", schedule=FixedSchedule({"torso_length": bad}))
    for bad in (float("nan"), float("inf")):
        _raises(["finite"], FixedSchedule, {"torso_length": bad})
    # a schedule whose range leaves the valid set is refused up front
    _raises(
        ["torso_length", "-0.1", ">= 0.02 and <= 2"],
        make_env,
        "Hopper-v5",
        schedule={
            "kind": "sinusoid",
            "center": {"torso_length": 0.1},
            "amplitude": {"torso_length": 0.2},
            "frequency": 0.2,
        },
    )
    _raises(["'medium'", "paper", "low", "high", "nominal", "none"], make_env, "Hopper-v5", preset="medium")
    _raises(["'paper'", "low", "high"], make_schedule, "HalfCheetah-v5", "paper")
    _raises(
        ["'gaussian'", "sinusoid", "uniform", "fixed", "list"], make_env, "Hopper-v5", schedule={"kind": "gaussian"}
    )
    _raises(["'mode'", "kind"], make_env, "Hopper-v5", schedule={"kind": "uniform", "low": {}, "high": {}, "mode": 1})
    _raises(["'exact'", "consistent", "ompo"], make_env, "Hopper-v5", mode="exact")
    _raises(["low", "high"], UniformSchedule, {"torso_length": 0.5}, {"torso_length": 0.3})
    _raises(["same parameters"], UniformSchedule, {"torso_length": 0.3}, {"foot_length": 0.5})
    _raises(["num_envs"], make_env, "Hopper-v5", num_envs=0)
    _raises(
        ["batched", "worker"],
        lambda: TransformedEnv(
            SerialEnv(2, lambda: GymEnv("Hopper-v5")), PerturbedDynamicsEnvTransform("Hopper-v5")
        ).reset(),
    )
    _raises(
        ["'Hopper-v5'", "'Walker2d-v5'"],
        lambda: TransformedEnv(GymEnv("Walker2d-v5"), PerturbedDynamicsEnvTransform("Hopper-v5")).reset(),
    )


def test_applier_validates_body_names_against_the_live_model():
    model = mujoco.MjModel.from_xml_path(default_xml_path("Ant-v5"))
    with pytest.raises(AdaRLValueError, match="torso"):
        MujocoDynamics(model, "Ant-v5", ("mass_scale:wing",))


def test_humanoid_gravity_and_wind():
    env = make_env("Humanoid-v5", seed=0)
    td = env.reset()
    m = _model(env)
    g, w = float(td["dynamics", "gravity"]), float(td["dynamics", "wind"])
    assert (g, w) == pytest.approx((14.715, 1.0))
    np.testing.assert_allclose(m.opt.gravity, [0, 0, -14.715])
    np.testing.assert_allclose(m.opt.wind, [-1.0, 0, 0])
    td = env.reset()
    assert float(td["dynamics", "wind"]) == pytest.approx(1 + 0.5 * math.sin(0.5), rel=1e-6)
