"""TorchRL's own test conventions, run against adarl's pieces, so that a regression against TorchRL shows here first.

For ``PerturbedDynamicsEnvTransform`` the checklist of TorchRL's ``TransformBase`` tests (test/test_transforms.py),
adapted to an env-only transform as TorchRL adapts it for its own (e.g. ``StepCounter``): spec checks on a single,
a serial and a parallel env with the transform inside each worker; refused on top of a batched env, where it is
built; refused outside an env (no env, in a model, in a replay buffer); compose, clone, pickle, deepcopy and
state_dict. For ``LowRankLinear``: TorchRL's ``loss.reset_parameters_recursive()`` on the losses that vmap a Q
ensemble gives every member a draw of its own, as it does with ``nn.Linear``.
"""

from __future__ import annotations

import copy
import functools
import pickle

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from test_adapter_losses import LOSS_CASES
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, GymEnv, ParallelEnv, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from adarl.core.lowrank import LowRankLinear
from adarl.envs.perturbation import PerturbedDynamicsEnvTransform
from adarl.errors import AdaRLValueError

ENV = "Hopper-v5"


def _transform(**kw) -> PerturbedDynamicsEnvTransform:
    return PerturbedDynamicsEnvTransform(ENV, "paper", **kw)


def _env(seed: int = 0) -> TransformedEnv:
    return TransformedEnv(GymEnv(ENV), Compose(_transform(seed=seed), StepCounter()))


class _WorkerFactory:
    """A picklable env factory: worker ``i`` of ``n`` draws its own part of the schedule."""

    def __init__(self, i: int, n: int) -> None:
        self.i, self.n = i, n

    def __call__(self) -> TransformedEnv:
        return TransformedEnv(GymEnv(ENV), _transform(seed=3, worker_index=self.i, num_workers=self.n))


# ------------------------------------------------------------------------------------------ the transform


def test_single_trans_env_check():
    env = _env()
    check_env_specs(env)
    env.close()


def test_serial_trans_env_check():
    env = SerialEnv(2, [_WorkerFactory(0, 2), _WorkerFactory(1, 2)])
    check_env_specs(env)
    td = env.reset()
    assert td["dynamics", "torso_length"].shape == (2,)
    assert td["dynamics", "torso_length"][0] != td["dynamics", "torso_length"][1]  # each worker its own episode
    env.close()


@pytest.mark.slow
def test_parallel_trans_env_check():
    env = ParallelEnv(2, [_WorkerFactory(0, 2), _WorkerFactory(1, 2)])
    try:
        check_env_specs(env)
    finally:
        env.close()


@pytest.mark.parametrize("batched", [SerialEnv, ParallelEnv])
def test_trans_batched_env_is_refused_where_it_is_built(batched):
    """On top of a batched env the transform could only edit one worker's model: refused by TransformedEnv's
    constructor (TorchRL calls set_container there), not at the first reset; nothing is started."""
    with pytest.raises(AdaRLValueError, match="batched env .*inside each worker"):
        TransformedEnv(batched(2, functools.partial(GymEnv, ENV)), _transform())
    with pytest.raises(AdaRLValueError, match="batched env"):  # also as part of a Compose
        TransformedEnv(batched(2, functools.partial(GymEnv, ENV)), Compose(StepCounter(), _transform()))


def test_transform_no_env():
    with pytest.raises(AdaRLValueError, match="cannot be executed without a parent environment"):
        _transform()(TensorDict({}, []))


def test_transform_compose_outside_an_env_refuses_too():
    with pytest.raises(AdaRLValueError, match="without a parent environment"):
        Compose(_transform(), StepCounter())(TensorDict({"step_count": torch.zeros(1, dtype=torch.int64)}, []))


def test_transform_model():
    model = TensorDictSequential(_transform())
    with pytest.raises(AdaRLValueError, match="without a parent environment"):
        model(TensorDict({"observation": torch.zeros(11)}, []))


def test_transform_rb():
    rb = ReplayBuffer(storage=LazyTensorStorage(10), transform=_transform(), batch_size=2)
    rb.extend(TensorDict({"observation": torch.zeros(4, 11)}, [4]))
    with pytest.raises(AdaRLValueError, match="without a parent environment"):
        rb.sample()


def test_transform_clone_pickle_deepcopy_and_state_dict():
    env = _env(seed=7)
    for _ in range(2):
        env.reset()
    t = env.transform[0]
    clone = t.clone()
    assert clone.parent is None  # TorchRL's contract: a clone is free to join another env
    for other in (pickle.loads(pickle.dumps(t)), copy.deepcopy(t), clone):
        fresh = TransformedEnv(GymEnv(ENV), other)
        check_env_specs(fresh)
        fresh.close()
    # state_dict carries the schedule's position: a new transform loaded with it continues the same sequence
    state = t.state_dict()
    nxt = float(env.reset()["dynamics", "torso_length"])
    loaded = _transform(seed=7)
    loaded.load_state_dict(state)
    again = TransformedEnv(GymEnv(ENV), loaded)
    assert float(again.reset()["dynamics", "torso_length"]) == pytest.approx(nxt)
    again.close()
    env.close()


# ------------------------------------------------------------------------------------------ the layer in losses


@pytest.mark.parametrize("name", ["SACLoss", "TD3Loss", "REDQLoss", "CQLLoss"])
def test_reset_parameters_recursive_gives_each_ensemble_member_its_own_draw(name):
    """TorchRL's standard re-initialisation of a loss: with LowRankLinear critics every Q-ensemble member must
    differ afterwards (one draw copied into all would give the twin critics identical gradients forever)."""
    loss = LOSS_CASES[name][0]()
    before = loss.qvalue_network_params.flatten_keys(".").clone()
    loss.reset_parameters_recursive()
    after = loss.qvalue_network_params.flatten_keys(".")
    factors = [k for k in after.keys() if k.endswith((".w1", ".w2"))]
    assert factors, f"{name}: no LowRankLinear in the critic"
    for key in factors:
        stacked = after[key]
        assert stacked.shape[0] >= 2
        for i in range(1, stacked.shape[0]):
            assert not torch.equal(stacked[0], stacked[i]), f"{name}: members 0 and {i} of {key} are identical"
        assert not torch.equal(stacked, before[key]), f"{name}: {key} was not re-drawn"


def test_set_weight_takes_one_weight_per_member_of_a_stacked_layer():
    layer = LowRankLinear(6, 5, rank=5)
    stacked = TensorDict.from_module(layer).expand(3).clone()
    weights = torch.randn(3, 5, 6, dtype=torch.float64)
    with stacked.to_module(layer):
        layer.set_weight_(weights)
        product = layer.w1 @ layer.w2
    assert torch.allclose(product.double(), weights, atol=1e-5)
    with pytest.raises(AdaRLValueError, match=r"one per ensemble member, \(3, 5, 6\)"):
        with stacked.to_module(layer):
            layer.set_weight_(torch.randn(2, 5, 6))
