"""PerturbedDynamicsEnvTransform under ParallelEnv (the transform lives in each worker process)."""

from __future__ import annotations

import torch

from adarl.envs import dynamics_state_dict, make_env


def test_parallel_env_matches_serial_env():
    kwargs = dict(preset="high", num_envs=2, seed=4, max_episode_steps=5)
    parallel = make_env("Hopper-v5", parallel=True, **kwargs)
    try:
        roll = parallel.rollout(12, break_when_any_done=False)
        state = dynamics_state_dict(parallel)
    finally:
        parallel.close()
    serial = make_env("Hopper-v5", **kwargs).rollout(12, break_when_any_done=False)
    assert torch.equal(roll["next", "dynamics", "torso_length"], serial["next", "dynamics", "torso_length"])
    assert roll["next", "dynamics", "episode"][:, -1].tolist() == [2, 2]
    assert state["worker1"]["_extra_state"]["episode"] == 3
