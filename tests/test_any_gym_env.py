"""Any gymnasium id from a recipe (issue 48.1): plain dynamics, parameters declared on MuJoCo model fields, the
errors of an unknown id, spaces the networks cannot use; and observation normalisation (TorchRL's VecNormV2):
checkpointed, restored exactly on resume, frozen during evaluation, applied by load_policy and adarl export."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from _helpers import adarl, tiny

from adarl.envs import check_any_env_id, make_env, make_eval_env
from adarl.envs.obs_norm import find_observation_norm
from adarl.envs.perturbation import find_gym_env
from adarl.errors import AdaRLValueError, RecipeError, UnknownNameError
from adarl.runtime.config import load_recipe

PENDULUM = ("env.id=Pendulum-v1", "env.perturbation=none", "env.normalize_observations=true")
#: 400 frames: checkpoints at 200 and 400, rank events at updates 100 and 200
SHORT = (
    "collector.total_frames=400",
    "collector.init_random_frames=100",
    "rank.interval=100",
    "eval.interval=200",
    "eval.episodes=1",
    "checkpoint.interval=200",
)
DECLARED = "env.parameters={torso_mass: {field: body_mass, index: torso, low: 1.0, high: 10.0}}"
TORSO_SCHEDULE = "env.perturbation.schedule={kind: uniform, low: {torso_mass: 2.0}, high: {torso_mass: 5.0}}"


def _stats(env) -> dict[str, torch.Tensor]:
    norm = find_observation_norm(env)
    return {k: v.clone() for k, v in norm.get_extra_state().items()}


def _equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _state(path):
    return torch.load(path, weights_only=True)["state"]


def test_pendulum_sac_from_the_cli_with_normalised_observations(tmp_path):
    """One tiny Pendulum-v1 run (rank events on), then: exact resume of its statistics, frozen evaluation, and
    load_policy / adarl export acting on raw observations as the in-process policy does on normalised ones."""
    import adarl as api
    from adarl.runtime.evaluation import evaluate_policy
    from adarl.runtime.export import _actor_actions
    from adarl.runtime.trainers.base import BaseTrainer

    run = tmp_path / "run"
    proc = adarl("run", "quickstart", *tiny(*PENDULUM, *SHORT), "-o", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "2 rank events" in proc.stdout, proc.stdout
    final = run / "checkpoints" / "ckpt-000000000400.pt"
    saved = _state(final)["obs_norm"]
    assert int(saved["count.-|-.observation"]) >= 400  # every step and reset of 400 frames moved them

    # a run killed after its middle checkpoint and resumed ends with the same statistics and networks (exact)
    middle = run / "checkpoints" / "ckpt-000000000200.pt"
    assert _state(middle)["obs_norm"]["count.-|-.observation"] < saved["count.-|-.observation"]
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    (copy / "checkpoints" / final.name).unlink()
    shutil.rmtree(copy / "checkpoints" / "rb-000000000400")
    trainer = BaseTrainer.resume(copy, quiet=True)
    assert trainer.frames == 200
    trainer.train()
    trainer.close()
    resumed = _state(copy / "checkpoints" / final.name)
    assert _equal(resumed["obs_norm"], saved)
    assert _equal(resumed["loss"], _state(final)["loss"])

    trainer = BaseTrainer.resume(run, quiet=True, read_only=True)
    try:
        c = trainer.c
        assert _equal(_stats(c.env), saved)  # restored from the checkpoint: equal tensors
        evaluation = find_observation_norm(c.eval_env)
        assert evaluation.frozen and evaluation._loc is find_observation_norm(c.env)._loc  # shares, frozen
        before = _stats(c.env)
        evaluate_policy(c.modules.actor, c.eval_env, episodes=1, max_steps=20)
        assert _equal(_stats(c.env), before)  # the evaluation did not move them

        obs = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 6.0], [-0.5, 0.8, -4.0]]) + 0.1 * torch.randn(3, 3)
        norm = find_observation_norm(c.env)
        in_process = _actor_actions(c.modules.actor, (obs - norm.loc["observation"]) / norm.scale["observation"])
        raw_actor = c.raw_observation_actor()
    finally:
        trainer.close()
    loaded = api.load_policy(run)
    assert torch.allclose(_actor_actions(loaded, obs), in_process, atol=1e-6)
    assert torch.allclose(_actor_actions(raw_actor, obs), in_process, atol=1e-6)
    # without the statistics the actions differ: the normalisation really is applied
    assert not torch.allclose(_actor_actions(c.modules.actor, obs), in_process, atol=1e-3)

    exported = api.ExportedPolicy(api.export_policy(run, tmp_path / "policy.pt").path)
    assert torch.allclose(exported(obs), in_process, atol=1e-5)
    assert "VecNorm" in exported.metadata["observation_normalisation"]["kind"]
    assert np.allclose(exported.predict(obs.numpy())[0], in_process.numpy(), atol=1e-5)


def test_an_unknown_id_is_refused_with_a_did_you_mean_and_plain_ids_need_preset_none():
    with pytest.raises(RecipeError, match=r"env\.id = 'Pendulm-v1'.*did you mean 'Pendulum-v1'.*gymnasium"):
        load_recipe("quickstart", ["env.id=Pendulm-v1"])
    with pytest.raises(UnknownNameError, match="neither adarl nor gymnasium registers it; did you mean 'Pendulum-v1'"):
        check_any_env_id("Pendulm-v1")
    with pytest.raises(AdaRLValueError, match="neither adarl nor gymnasium"):
        make_env("Pendulm-v1", preset="none")
    with pytest.raises(RecipeError, match=r"preset = 'paper': not available for Pendulum-v1; allowed: 'none'"):
        load_recipe("quickstart", ["env.id=Pendulum-v1"])
    recipe = load_recipe("quickstart", list(PENDULUM))
    assert recipe.env.perturbation.preset == "none" and recipe.env.normalize_observations
    with pytest.raises(RecipeError, match=r"env\.normalize_observations.*PPO loop.*algorithm\.ppo\.obs_norm"):
        load_recipe("baselines/hopper_rnac_ipm", ["env.normalize_observations=true"])


def test_a_declared_parameter_schedule_on_a_mujoco_env_is_validated_and_applied():
    recipe = load_recipe("quickstart", ["env.id=Hopper-v4", DECLARED, TORSO_SCHEDULE])
    declared = recipe.env.declared()
    assert declared == {"torso_mass": {"field": "body_mass", "index": "torso", "low": 1.0, "high": 10.0}}
    # refused by name when the recipe is validated: a field, a schedule value out of range, an unknown name
    for overrides, match in (
        (
            ["env.parameters={m: {field: body_mas, index: torso}}", "env.perturbation=none"],
            r"env\.parameters\.m: unknown MuJoCo model field 'body_mas'; allowed: .*'geom_size'.*did you mean "
            r"'body_mass'",
        ),
        ([DECLARED, TORSO_SCHEDULE.replace("5.0", "50.0")], r"torso_mass .*reaches 50.0.*<= 10"),
        ([DECLARED, "env.perturbation.schedule={kind: fixed, values: {torso_mas: 2.0}}"], "did you mean 'torso_mass'"),
        (["env.parameters={torso_length: {field: body_mass, index: 1}}", "env.id=Hopper-v5"], "already has"),
    ):
        with pytest.raises(RecipeError, match=match):
            load_recipe("quickstart", ["env.id=Hopper-v4", *overrides])
    with pytest.raises(RecipeError, match="Pendulum-v1 does not simulate with MuJoCo"):
        load_recipe("quickstart", [*PENDULUM, DECLARED])

    # applied at every reset, absolutely, from the model's own values; the rest of the model untouched
    schedule = recipe.env.perturbation.schedule
    env = make_env("Hopper-v4", schedule=schedule, parameters=declared, seed=0)
    model = find_gym_env(env).model
    own = model.body_mass.copy()
    drawn = []
    for _ in range(3):
        td = env.reset()
        drawn.append(float(td["dynamics", "torso_mass"]))
        assert model.body_mass[model.body("torso").id] == pytest.approx(drawn[-1], rel=1e-6)
        others = np.delete(model.body_mass, model.body("torso").id)
        assert np.array_equal(others, np.delete(own, model.body("torso").id))
    assert all(2.0 <= m <= 5.0 for m in drawn) and len(set(drawn)) == 3
    env.close()
    nominal = make_eval_env("Hopper-v4", schedule, parameters=declared)  # the centre: 3.5
    assert float(nominal.reset()["dynamics", "torso_mass"]) == pytest.approx(3.5)
    nominal.close()

    # refused by name when the env is built: an index out of range, a name the model lacks, a wrong arity
    for spec, match in (
        ({"field": "body_mass", "index": 99}, r"index: 99 is out of range for body_mass.*0 to 4"),
        ({"field": "body_mass", "index": "torsoo"}, r"no body named 'torsoo'; allowed: .*did you mean 'torso'"),
        ({"field": "geom_size", "index": 1}, r"geom_size has shape \[5, 3\].*needs 2 entries"),
    ):
        with pytest.raises(AdaRLValueError, match=match):
            make_env("Hopper-v4", schedule={"kind": "fixed", "values": {"m": 1.0}}, parameters={"m": spec})


def test_spaces_the_networks_cannot_use_are_refused_naming_why():
    from adarl.runtime.builders.common import check_spaces

    td3 = load_recipe("baselines/hopper_td3", ["env.id=Acrobot-v1", "env.perturbation=none"])
    env = make_env("Acrobot-v1", preset="none")
    try:
        with pytest.raises(AdaRLValueError, match=r"discrete actions.*'td3' loop.*allowed for discrete.*sac"):
            check_spaces(td3, env)
        check_spaces(load_recipe("quickstart", ["env.id=Acrobot-v1", "env.perturbation=none"]), env)  # SAC: fine
    finally:
        env.close()
