"""The envs' data in one place (adarl.envs.registry): the action dimension and the intrinsic rank ``2 * d_a + 1``
of Tiwari et al. that reports draw (paper Fig. 4), and adarl's own env ids registered through the same registry as a
plugin's."""

from __future__ import annotations

from adarl.envs import ACTION_DIMS, action_dim, intrinsic_rank
from adarl.envs.registry import ENV_IDS, SUPPORTED_ENVS, supported_envs


def test_the_intrinsic_rank_is_two_action_dimensions_plus_one():
    assert (action_dim("Hopper-v5"), intrinsic_rank("Hopper-v5")) == (3, 7)
    assert intrinsic_rank("Humanoid-v5") == 35 and intrinsic_rank("CartPole-v1") == 3
    assert action_dim("NoSuchEnv-v0") is None and intrinsic_rank("NoSuchEnv-v0") is None
    assert all(intrinsic_rank(env) == 2 * d + 1 for env, d in ACTION_DIMS.items())
    assert set(ACTION_DIMS) <= set(SUPPORTED_ENVS)


def test_adarl_own_env_ids_are_registry_entries_listed_first():
    assert supported_envs(load=False)[: len(SUPPORTED_ENVS)] == SUPPORTED_ENVS
    assert all(ENV_IDS.entries[env].provider is None for env in SUPPORTED_ENVS)
