"""Baselines: Parseval value, IPM reward shift, DS exact restore, sparsity, recipes and their validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives.value import GAE

from adarl.baselines import (
    DoubleSamplingTransform,
    IPMAdvantage,
    ParsevalRegularizer,
    SparsificationLayer,
    critic_parameter_norm,
    make_baseline_mlp,
    parseval_weights,
)
from adarl.baselines.normalization import RewardScaler, RunningObsNorm
from adarl.baselines.rnac import mujoco_state
from adarl.core.lowrank import LowRankLinear
from adarl.errors import AdaRLValueError, RecipeError
from adarl.runtime.config import list_recipes, load_recipe

# ------------------------------------------------------------------------------------------------ Parseval

REPO = Path(__file__).resolve().parents[1]


def _net_with(hidden: torch.Tensor) -> nn.Sequential:
    net = nn.Sequential(nn.Linear(hidden.shape[1], hidden.shape[0]), nn.ReLU(), nn.Linear(hidden.shape[0], 1))
    with torch.no_grad():
        net[0].weight.copy_(hidden)
        net[2].weight.fill_(7.0)  # the output layer must not count
    return net


def test_parseval_value_on_a_known_matrix():
    # W W^T - 2I = [[-1,0,1],[0,-1,1],[1,1,0]]: squared Frobenius norm 6
    w = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    net = _net_with(w)
    reg = ParsevalRegularizer(net, lam=0.5, s=2.0, base_width=3)
    assert reg.layers == ["network.0"]
    assert reg().item() == pytest.approx(0.5 * 6.0)
    # the (base_width / width)^2 scaling: width 3, base 64
    assert ParsevalRegularizer(net, lam=1.0, s=2.0, base_width=64)().item() == pytest.approx((64 / 3) ** 2 * 6.0)
    # orthogonal rows with squared norm s give exactly zero
    assert ParsevalRegularizer(_net_with(torch.eye(3) * 2**0.5), lam=1.0)().item() == pytest.approx(0.0, abs=1e-10)


def test_parseval_counts_low_rank_layers_by_their_product_and_has_gradients():
    torch.manual_seed(0)
    lr = LowRankLinear(5, 4, rank=2)
    net = nn.Sequential(lr, nn.ReLU(), nn.Linear(4, 1))
    dense = _net_with(lr.weight.detach().clone())
    assert ParsevalRegularizer(net, lam=1.0)().item() == pytest.approx(
        ParsevalRegularizer(dense, lam=1.0)().item(), rel=1e-5
    )
    ParsevalRegularizer(net, lam=1.0)().backward()
    assert lr.w1.grad is not None and lr.w2.grad is not None and net[2].weight.grad is None


def test_parseval_reads_the_stacked_critics_of_sacloss():
    from adarl.envs import make_env
    from adarl.runtime.builders import make_sac_modules

    recipe = load_recipe("baselines/hopper_parseval", ["env.id=InvertedPendulum-v5"])
    env = make_env("InvertedPendulum-v5", preset="none")
    loss = make_sac_modules(recipe, env).loss
    weights = parseval_weights(loss)
    paths = [w.path for w in weights]
    assert len(paths) == 4 and sum(p.startswith("qvalue_network") for p in paths) == 2, paths
    q = [w for w in weights if w.path.startswith("qvalue_network")][0]
    assert q.weight.shape[0] == 2  # the [num_qvalue_nets, out, in] parameter the loss trains
    assert any(q.weight is p for p in loss.qvalue_network_params.values(True, True))
    reg = ParsevalRegularizer(loss, lam=1e-4)
    td = reg.wrap_output(loss(env.rollout(3).reshape(-1)))
    assert td["loss_parseval"].item() > 0


def test_parseval_bad_input():
    with pytest.raises(AdaRLValueError, match="lam"):
        ParsevalRegularizer(_net_with(torch.eye(2)), lam=-1.0)
    with pytest.raises(AdaRLValueError, match="no hidden linear layers"):
        ParsevalRegularizer(nn.Sequential(nn.Linear(2, 1)))


def _original_hidden_layer(in_features: int, out_features: int, gain: float) -> nn.Linear:
    """A hidden layer as the originals build it (re-implemented): nn.Linear, torch's orthogonal_ with ``gain``,
    zero bias (wechu/parseval_reg agent.py orthogonal_layer_init; tliu1997/RNAC ppo_continuous.py orthogonal_init)."""
    layer = nn.Linear(in_features, out_features)
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def _init_stats(w: torch.Tensor) -> tuple[float, torch.Tensor]:
    """mean diag(W W^T) and the sorted singular values of one weight matrix."""
    w = w.detach().double()
    return float(torch.diagonal(w @ w.T).mean()), torch.linalg.svdvals(w)


@pytest.mark.parametrize("env", ["hopper", "walker2d", "ant", "humanoid"])
def test_parseval_recipes_use_the_originals_orthogonal_init(env):
    r = load_recipe(f"baselines/{env}_parseval")
    for net, head in (("actor", 0.01), ("critic", 1.0)):
        init = getattr(r.network, net).init
        assert (init.scheme, init.gain, init.head_gain) == ("orthogonal", pytest.approx(2**0.5), head)
    assert r.algorithm.parseval.s == pytest.approx(r.network.critic.init.gain**2)  # W W^T starts at s I


def test_parseval_sac_networks_start_where_the_originals_do():
    """Every hidden layer of actor and of each critic has the original's init statistics (mean diag(W W^T) = 2 for
    the 64x64 layers, all singular values sqrt(2)); the heads have gain 0.01 (policy) and 1 (value)."""
    from adarl.envs import make_env
    from adarl.runtime.builders import make_sac_modules

    torch.manual_seed(0)
    recipe = load_recipe("baselines/hopper_parseval")
    env = make_env("Hopper-v5", preset="none")
    loss = make_sac_modules(recipe, env).loss
    gain = 2**0.5
    checked = 0
    for w in parseval_weights(loss):  # the hidden layers, as the loss trains them (critics stacked [2, out, in])
        members = w.weight if w.weight.dim() == 3 else w.weight.unsqueeze(0)
        for m in members:
            out_f, in_f = m.shape
            mean_diag, sv = _init_stats(m)
            ref_diag, ref_sv = _init_stats(_original_hidden_layer(in_f, out_f, gain).weight)
            assert mean_diag == pytest.approx(ref_diag, rel=1e-4), (w.path, mean_diag, ref_diag)
            torch.testing.assert_close(sv, ref_sv, rtol=1e-4, atol=1e-5)
            if out_f == in_f == 64:
                assert mean_diag == pytest.approx(2.0, rel=1e-4)  # s I with s = 2 (PyTorch's default: ~0.33)
            checked += 1
    assert checked == 2 + 2 * 2  # actor's two hidden layers, two per critic
    q = loss.qvalue_network_params.flatten_keys(".")
    assert not torch.equal(q["module.2.weight"][0], q["module.2.weight"][1])  # each critic drawn apart
    for k, v in loss.target_qvalue_network_params.flatten_keys(".").items():
        assert torch.equal(v, q[k].data), k  # the targets start equal to the critics
    assert all(float(v.detach().abs().max()) == 0 for k, v in q.items() if k.endswith("bias"))
    torch.testing.assert_close(torch.linalg.svdvals(q["module.4.weight"][0].detach()), torch.ones(1))
    actor_head = [v for k, v in loss.actor_network_params.flatten_keys(".").items() if k.endswith("weight")][-1]
    torch.testing.assert_close(torch.linalg.svdvals(actor_head.detach()), torch.full((6,), 0.01))
    # the penalty starts at the input layers' share only: the 64x64 layers are already s-orthogonal
    reg = ParsevalRegularizer(loss, lam=1.0)
    with torch.no_grad():
        wide = sum(float(((w.gram() - 2 * torch.eye(64)) ** 2).sum()) for w in reg._weights if w.weight.shape[-1] == 64)
    assert wide < 1e-6


def test_orthogonal_init_of_low_rank_and_plain_networks():
    from adarl.baselines import orthogonal_init_

    torch.manual_seed(0)
    net = nn.Sequential(LowRankLinear(8, 6), nn.Tanh(), LowRankLinear(6, 6, rank=2), nn.Tanh(), nn.Linear(6, 2))
    assert orthogonal_init_(net, gain=1.5, head_gain=0.01) == 3
    torch.testing.assert_close(torch.linalg.svdvals(net[0].weight.detach()), torch.full((6,), 1.5))
    sv = torch.linalg.svdvals(net[2].weight.detach())  # rank 2: the best rank-2 part of an orthogonal draw
    torch.testing.assert_close(sv[:2], torch.full((2,), 1.5))
    assert float(sv[2:].abs().max()) < 1e-5
    torch.testing.assert_close(torch.linalg.svdvals(net[4].weight.detach()), torch.full((2,), 0.01))
    assert all(float(b.abs().max()) == 0 for n, b in net.named_parameters() if n.endswith("bias"))
    with pytest.raises(AdaRLValueError, match="gain"):
        orthogonal_init_(net, gain=0.0)
    with pytest.raises(AdaRLValueError, match="no Linear"):
        orthogonal_init_(nn.Tanh())


# ---------------------------------------------------------------------------------------- sparsification


def test_sparsification_layer_activations_are_k_sparse():
    torch.manual_seed(0)
    layer = SparsificationLayer(11, width=1024, k=7)
    out = layer(torch.randn(256, 11))
    nonzero = (out != 0).sum(-1)
    assert out.shape == (256, 1024)
    assert int(nonzero.max()) <= 7 and float(nonzero.float().mean()) > 6  # exactly k active (ReLU may zero a few)
    assert (out >= 0).all()
    # gradients reach only the winners' rows
    layer(torch.randn(1, 11)).sum().backward()
    rows_with_grad = (layer[0].weight.grad.abs().sum(1) > 0).sum()
    assert int(rows_with_grad) <= 7
    with pytest.raises(AdaRLValueError):
        SparsificationLayer(11, width=8, k=9)


def test_recipe_sparse_network_is_wide_and_sparse():
    from adarl.envs import make_env
    from adarl.runtime.builders import make_sac_modules

    recipe = load_recipe("baselines/hopper_sparse")
    env = make_env("Hopper-v5", preset="none")
    modules = make_sac_modules(recipe, env)
    layers = [m for m in modules.actor.modules() if isinstance(m, SparsificationLayer)]
    assert len(layers) == 1 and layers[0].width == 1024 and layers[0].k == 7  # 2 * 3 + 1 for Hopper
    x = torch.randn(32, 11)
    body = layers[0]
    h = body(torch.relu(torch.randn(32, 64)))
    assert int((h != 0).sum(-1).max()) <= 7
    # the critic (obs, action inputs) runs too
    assert modules.loss(env.rollout(3, modules.actor).reshape(-1))["loss_qvalue"].isfinite()
    del x


def test_baseline_mlp_variants_layout():
    net = make_baseline_mlp(
        4,
        2,
        [8, 8],
        low_rank_layers=[0],
        rank=2,
        sparse_layer=1,
        sparse_width=32,
        sparse_k=4,
        diagonal_scale=True,
        input_scale=True,
    )
    assert net(torch.randn(3, 4)).shape == (3, 2)
    assert net(torch.randn(3, 3), torch.randn(3, 1)).shape == (3, 2)  # inputs concatenated like torchrl's MLP
    with pytest.raises(AdaRLValueError, match="both low-rank"):
        make_baseline_mlp(4, 2, [8, 8], low_rank_layers=[1], sparse_layer=1)
    # Parseval's diagonal layer is the original's DiagLinear: x * c + b, c = 1 and b = 0 at the start
    from adarl.baselines import DiagonalScale

    diag = [m for m in net.modules() if isinstance(m, DiagonalScale)]
    assert len(diag) == 2
    assert all(
        torch.equal(d.scale, torch.ones_like(d.scale)) and torch.equal(d.bias, torch.zeros_like(d.bias)) for d in diag
    )
    x = torch.randn(3, 8)
    with torch.no_grad():
        diag[0].scale.fill_(2.0), diag[0].bias.fill_(0.5)
    torch.testing.assert_close(diag[0](x), 2 * x + 0.5)


# --------------------------------------------------------------------------------------------- RNAC-IPM


def test_critic_norm_excludes_only_the_output_bias():
    critic = nn.Sequential(nn.Linear(2, 2), nn.Tanh(), nn.Linear(2, 1))
    with torch.no_grad():
        critic[0].weight.copy_(torch.tensor([[1.0, 2.0], [0.0, 2.0]]))
        critic[0].bias.copy_(torch.tensor([1.0, 1.0]))
        critic[2].weight.copy_(torch.tensor([[3.0, 0.0]]))
        critic[2].bias.fill_(100.0)
    # 1 + 4 + 0 + 4 + 1 + 1 + 9 = 20
    assert critic_parameter_norm(critic).item() == pytest.approx(20**0.5)
    assert critic_parameter_norm(ValueOperator(critic, in_keys=["observation"])).item() == pytest.approx(20**0.5)


def test_ipm_advantage_matches_a_hand_computation():
    lin = nn.Linear(2, 1)
    with torch.no_grad():
        lin.weight.copy_(torch.tensor([[3.0, 4.0]]))  # ||theta|| = 5 (output bias excluded)
        lin.bias.fill_(0.5)
    critic = ValueOperator(lin, in_keys=["observation"])
    kappa, gamma = 0.1, 0.9
    obs = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    nxt = torch.tensor([[0.0, 1.0], [1.0, 1.0], [2.0, 0.0]])
    reward = torch.tensor([[1.0], [2.0], [3.0]])
    done = torch.tensor([[False], [False], [True]])
    td = TensorDict(
        {
            "observation": obs,
            "done": torch.zeros_like(done),
            "terminated": torch.zeros_like(done),
            "next": {"observation": nxt, "reward": reward, "done": done, "terminated": done},
        },
        batch_size=[3],
    )
    ipm = IPMAdvantage(gamma=gamma, lmbda=0.0, value_network=critic, kappa=kappa)
    ipm(td)
    v = lambda o: o @ torch.tensor([3.0, 4.0]) + 0.5  # noqa: E731
    expected = reward.squeeze(-1) - kappa * 5.0 + gamma * v(nxt) * (~done.squeeze(-1)) - v(obs)
    torch.testing.assert_close(td["advantage"].squeeze(-1), expected)
    assert ipm.last_shift == pytest.approx(0.5)
    torch.testing.assert_close(td["next", "reward"], reward)  # the stored reward is untouched
    # kappa = 0 is plain GAE
    td2 = td.exclude("advantage", "value_target", "state_value")
    IPMAdvantage(gamma=gamma, lmbda=0.95, value_network=critic, kappa=0.0)(td2)
    td3 = td.exclude("advantage", "value_target", "state_value")
    GAE(gamma=gamma, lmbda=0.95, value_network=critic)(td3)
    torch.testing.assert_close(td2["advantage"], td3["advantage"])


# ------------------------------------------------------------------------------ RNAC's original trainer


@pytest.mark.parametrize("env", ["hopper", "walker2d", "ant", "humanoid"])
@pytest.mark.parametrize("mode", ["ipm", "ds"])
def test_rnac_recipes_resolve_to_the_original_trainer(env, mode):
    r = load_recipe(f"baselines/{env}_rnac_{mode}")
    ppo = r.algorithm.ppo
    assert ppo.policy == "clipped_gaussian" and ppo.normalize_advantage == "batch"
    a, c = r.network.actor.init, r.network.critic.init
    assert (a.scheme, a.gain, a.head_gain) == ("orthogonal", 1.0, 0.01)  # ppo_continuous.py: orthogonal_init gain 1
    assert (c.scheme, c.gain, c.head_gain) == ("orthogonal", 1.0, 1.0)
    assert r.network.actor.activation == r.network.critic.activation == "tanh"
    # the tanh policy stays available, and old boolean values keep their meaning
    assert (
        load_recipe(f"baselines/{env}_rnac_{mode}", ["algorithm.ppo.policy=tanh_gaussian"]).algorithm.ppo.policy
        == "tanh_gaussian"
    )
    assert (
        load_recipe(
            "baselines/hopper_rnac_ipm", ["algorithm.ppo.normalize_advantage=true"]
        ).algorithm.ppo.normalize_advantage
        == "minibatch"
    )


def _ppo_components(*overrides):
    from adarl.runtime.builders.ppo import build_ppo_components

    recipe = load_recipe(
        "baselines/hopper_rnac_ipm",
        ["collector.total_frames=256", "collector.frames_per_batch=128", "algorithm.ppo.epochs=1", *overrides],
    )
    return recipe, build_ppo_components(recipe)


def test_rnac_networks_and_policy_start_as_the_original():
    from adarl.baselines import BoxTanh, ClippedNormal

    torch.manual_seed(0)
    _, c = _ppo_components()
    actor, critic = c.modules.actor, c.modules.critic
    weights = {f"actor.{n}": p for n, p in actor.named_parameters()}
    weights |= {f"critic.{n}": p for n, p in critic.named_parameters()}
    mats = [(n, p) for n, p in weights.items() if n.endswith("weight")]
    assert len(mats) == 6
    for n, p in mats:
        expected = 0.01 if n.startswith("actor") and p.shape[0] == 3 else 1.0  # policy head 0.01, others gain 1
        torch.testing.assert_close(torch.linalg.svdvals(p.detach()), torch.full((min(p.shape),), expected), msg=n)
    assert all(float(p.abs().max()) == 0 for n, p in weights.items() if n.endswith("bias"))
    scale = [p for n, p in weights.items() if n.endswith("state_independent_scale")]
    assert len(scale) == 1 and float(scale[0].abs().max()) == 0  # log_std = 0: std 1, as the original
    assert any(isinstance(m, BoxTanh) for m in actor.modules())
    batch = next(iter(c.collector))
    dist = actor.get_dist(batch)
    assert isinstance(dist, ClippedNormal)
    act = batch["action"]
    assert float(act.abs().max()) <= 1.0 and float((act.abs() == 1.0).float().mean()) > 0.05  # clipped, not squashed
    # the stored log-probability is the unclipped Gaussian's density at the clipped action (the original's)
    gauss = torch.distributions.Normal(batch["loc"], batch["scale"])
    torch.testing.assert_close(batch["action_log_prob"], gauss.log_prob(act).sum(-1))
    # the loss's entropy bonus is the Gaussian's closed form, not a one-sample estimate
    from adarl.runtime.trainers.ppo import normalize_advantage_

    with torch.no_grad():
        c.modules.advantage(batch)
    normalize_advantage_(batch)
    out = c.modules.loss(batch)
    torch.testing.assert_close(out["loss_entropy"], -0.01 * gauss.entropy().sum(-1).mean())


def test_clipped_normal_and_box_tanh():
    from adarl.baselines import BoxTanh, ClippedNormal

    torch.manual_seed(0)
    low, high = torch.full((2,), -0.4), torch.full((2,), 0.4)  # Humanoid's box
    x = torch.randn(5, 2) * 3
    torch.testing.assert_close(BoxTanh(low, high)(x), 0.4 * torch.tanh(x))  # max_action * tanh(mean_layer(s))
    torch.testing.assert_close(BoxTanh(torch.tensor([0.0]), torch.tensor([2.0]))(torch.zeros(1)), torch.ones(1))
    loc, scale = torch.zeros(4000, 2), torch.ones(4000, 2)
    d = ClippedNormal(loc, scale, low=low, high=high)
    a = d.sample()
    assert float(a.abs().max()) == pytest.approx(0.4) and float((a.abs() == 0.4).float().mean()) > 0.6
    assert bool((d.rsample().abs() <= high).all())
    torch.testing.assert_close(d.log_prob(a), torch.distributions.Normal(loc, scale).log_prob(a).sum(-1))
    torch.testing.assert_close(d.entropy(), torch.distributions.Normal(loc, scale).entropy().sum(-1))
    torch.testing.assert_close(
        ClippedNormal(torch.full((2,), 3.0), torch.ones(2), low, high).deterministic_sample, high
    )
    with pytest.raises(ValueError, match="low <= high"):
        ClippedNormal(loc, scale, low=high, high=low)


def _advantage_seen_by_the_loss(tmp_path, how: str) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Run one PPO iteration on a batch whose advantages are 0 .. 127, and return the raw advantages of the first
    minibatch, all raw advantages, and the first update's loss_objective (ratio 1 there, so it is -mean(A_used))."""
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import PPOTrainer

    torch.manual_seed(0)
    recipe = load_recipe(
        "baselines/ppo_base",
        [
            "env.id=Hopper-v5",
            "collector.total_frames=256",
            "collector.frames_per_batch=128",
            "algorithm.ppo.epochs=1",
            f"algorithm.ppo.normalize_advantage={how}",
        ],
    )
    trainer = PPOTrainer(recipe, RunDir.create(tmp_path / how), quiet=True)
    m = trainer.c.modules
    raw = torch.arange(128, dtype=torch.float32).reshape(1, 128, 1)
    real = m.advantage

    def designed(td):
        real(td)
        td.set("advantage", raw.clone())
        td.set("raw_advantage", raw.clone())
        return td

    m.advantage = designed
    seen = []
    forward = m.loss.forward

    def spy(td):
        out = forward(td)
        seen.append((td["raw_advantage"].clone(), float(out["loss_objective"])))
        return out

    m.loss.forward = spy
    batch = next(iter(trainer.c.collector)).unsqueeze(0)
    trainer._iteration(batch)
    trainer.close()
    assert len(seen) == 2  # 128 frames, minibatches of 64
    return seen[0][0], raw, seen[0][1]


def test_ppo_advantage_normalisation_spans_the_whole_batch(tmp_path):
    first, raw, objective = _advantage_seen_by_the_loss(tmp_path, "batch")
    batch_wide = (first - raw.mean()) / (raw.std() + 1e-5)  # RNAC's trainer, over its whole batch
    per_minibatch = (first - first.mean()) / first.std()
    assert abs(float(batch_wide.mean())) > 0.05  # the two normalisations differ on this minibatch
    assert objective == pytest.approx(-float(batch_wide.mean()), abs=1e-5)
    assert objective != pytest.approx(-float(per_minibatch.mean()), abs=1e-3)
    # TorchRL's per-minibatch standardisation stays available: each minibatch then has mean advantage 0
    _, _, objective_mb = _advantage_seen_by_the_loss(tmp_path, "minibatch")
    assert objective_mb == pytest.approx(0.0, abs=1e-5)
    from adarl.runtime.trainers.ppo import normalize_advantage_

    one = normalize_advantage_(TensorDict({"advantage": torch.tensor([[3.0]])}, batch_size=[1]))
    assert one["advantage"].item() == 0.0  # a one-frame batch: no spread, no NaN


def test_simulator_steps_per_frame():
    from adarl.runtime.builders.ppo import simulator_steps_per_frame

    assert simulator_steps_per_frame(load_recipe("baselines/hopper_rnac_ds")) == 3  # m = 2 probes + the real step
    assert (
        simulator_steps_per_frame(load_recipe("baselines/hopper_rnac_ds", ["algorithm.options.num_candidates=4"])) == 5
    )
    assert simulator_steps_per_frame(load_recipe("baselines/hopper_rnac_ipm")) == 1
    assert simulator_steps_per_frame(load_recipe("hopper_adarl")) == 1


# ---------------------------------------------------------------------------------------------- RNAC-DS


def _ds_env(seed=0):
    from adarl.envs import make_env

    env = make_env("Hopper-v5", preset="paper", seed=seed)
    ds = DoubleSamplingTransform(num_candidates=2, noise=5e-3, seed=seed)
    env.append_transform(ds)
    return env, ds


def test_double_sampling_restores_the_state_exactly():
    env, ds = _ds_env()
    env.reset()
    gym = ds._gym_env()
    before = mujoco_state(gym.model, gym.data)
    actions, observations = ds.probe(torch.full((3,), 0.3))
    assert np.array_equal(mujoco_state(gym.model, gym.data), before)  # restored bit for bit
    assert not np.array_equal(observations[0], observations[1])  # the noise made the candidates differ
    # the same noisy action from the restored state gives a bit-identical next observation
    obs, *_ = gym.step(actions[1].numpy().astype(np.float64))
    assert np.array_equal(obs, observations[1])


def test_double_sampling_steps_into_a_candidate_and_keeps_the_policy_action():
    env, ds = _ds_env()
    critic = ValueOperator(nn.Sequential(nn.Linear(11, 16), nn.Tanh(), nn.Linear(16, 1)), in_keys=["observation"])
    ds.set_value_network(critic)
    td = env.reset()
    gym = ds._gym_env()
    for _ in range(20):
        td["action"] = torch.full((3,), 0.2)
        snapshot = mujoco_state(gym.model, gym.data)
        state = ds.rng_state()
        actions, observations = ds.probe(td["action"])
        # replay the same draw inside env.step
        from adarl.baselines.rnac import set_mujoco_state

        set_mujoco_state(gym.model, gym.data, snapshot)
        ds.set_rng_state(state)
        out = env.step(td)
        assert torch.equal(out["action"], torch.full((3,), 0.2))  # the stored action is the policy's
        nxt = out["next", "observation"].double().numpy()
        assert any(np.array_equal(nxt, o.astype(np.float32).astype(np.float64)) for o in observations)
        td = out["next"].clone()
        if out["next", "done"].item():
            td = env.reset()
    assert ds.steps == 20 and 0 < ds.worst_picks < 20
    assert list(ds.state_dict().keys()) == []  # the critic is not part of the env's state


def test_double_sampling_needs_a_single_mujoco_env():
    from adarl.envs import make_env

    env = make_env("CartPole-v1", preset="none")
    with pytest.raises(AdaRLValueError, match="MuJoCo"):
        env.append_transform(DoubleSamplingTransform())
        env.rollout(2)


# ------------------------------------------------------------------------------------- normalisation


def test_running_obs_norm_and_reward_scaler():
    norm = RunningObsNorm(2)
    x = torch.tensor([[1.0, 10.0], [3.0, 30.0]])
    assert torch.equal(norm(x), x)  # identity before any statistics
    norm.update(x[:1])
    norm.update(x[1:])
    torch.testing.assert_close(norm.mean, torch.tensor([2.0, 20.0], dtype=torch.float64))
    torch.testing.assert_close(norm.var, torch.tensor([1.0, 100.0], dtype=torch.float64))
    scaler = RewardScaler(gamma=0.0)  # returns == rewards: scaled by their running std
    out = scaler(torch.tensor([[1.0, 3.0]]), torch.tensor([[False, False]]))
    assert out[0, 1].item() == pytest.approx(3.0 / 1.0, rel=1e-6)
    # the run's first reward: one sample, std 0; scaled by |R| to +-1 as the original (not by 1 / 1e-8)
    first = RewardScaler(gamma=0.99)(torch.tensor([[0.8, 0.8, 0.8]]), torch.tensor([[False, False, False]]))
    assert first[0, 0].item() == pytest.approx(1.0, rel=1e-6) and first.abs().max().item() < 10
    assert RewardScaler(gamma=0.99)(torch.tensor([[-0.5]]), torch.tensor([[False]])).item() == pytest.approx(-1.0)
    two = RewardScaler(gamma=0.99)(torch.tensor([[0.8], [0.8]]), torch.tensor([[False], [False]]))  # 2 envs, no spread
    torch.testing.assert_close(two, torch.ones(2, 1))


# ------------------------------------------------------------------------------------------------ recipes

ENVS = ("hopper", "walker2d", "ant", "humanoid")
BASELINES = ("sac_full", "sac_fixed", "parseval", "sparse", "rnac_ipm", "rnac_ds")
ABLATIONS = ("scope_actor", "scope_critic", "ratio_rule", "no_warm_start", "softplus")


def test_every_baseline_and_ablation_is_listed_for_every_env():
    names = dict(list_recipes())
    for env in ENVS:
        for b in BASELINES:
            assert names.get(f"baselines/{env}_{b}"), (env, b)
        for a in ABLATIONS:
            assert names.get(f"ablations/{env}_{a}"), (env, a)


@pytest.mark.parametrize("env", ENVS)
def test_baseline_recipes_say_what_they_run(env):
    adarl = load_recipe(f"{env}_adarl")
    full = load_recipe(f"baselines/{env}_sac_full")
    assert not full.rank.enabled and full.network.actor.low_rank_layers == [] and full.env.id == adarl.env.id
    fixed = load_recipe(f"baselines/{env}_sac_fixed")
    assert not fixed.rank.enabled and fixed.network.actor.rank == fixed.network.critic.rank >= 7
    assert load_recipe(f"baselines/{env}_parseval").algorithm.parseval.enabled
    assert load_recipe(f"baselines/{env}_sparse").network.critic.sparse.width == 1024
    for mode in ("ipm", "ds"):
        r = load_recipe(f"baselines/{env}_rnac_{mode}")
        assert r.algorithm.name == f"rnac_{mode}" and r.algorithm.base == "ppo" and r.env.id == adarl.env.id
        assert r.collector.frames_per_batch == 2048 and r.algorithm.lr == 3e-4 and r.algorithm.max_grad_norm == 0.5
    assert load_recipe(f"ablations/{env}_scope_actor").rank.scope == "actor"
    assert load_recipe(f"ablations/{env}_ratio_rule").rank.rule == "ratio"
    # the paper's control (App. D.5.3): the buffer is emptied at each rank update and refilled by the new policy
    assert load_recipe(f"ablations/{env}_no_warm_start").replay.warm_start.mode == "reset"
    assert load_recipe(f"ablations/{env}_softplus").network.actor.activation == "softplus"


@pytest.mark.parametrize(
    "recipe, overrides, expected",
    [
        ("quickstart", ["algorithm.rnac.mode=ipm"], "RNAC is now a registered algorithm: algorithm.name=rnac_ipm"),
        (
            "quickstart",
            ["algorithm.name=rnac_ipm"],
            "rank.enabled = true: must be false with algorithm.name='rnac_ipm'",
        ),
        (
            "baselines/hopper_rnac_ipm",
            ["algorithm.options.m=3"],
            "unknown option of algorithm 'rnac_ipm'; allowed: 'kappa'",
        ),
        ("baselines/hopper_rnac_ds", ["algorithm.options.num_candidates=0"], "algorithm.options.num_candidates = 0"),
        ("baselines/hopper_rnac_ds", ["env.id=LinearCartPole-v0"], "needs a MuJoCo env"),
        ("quickstart", ["algorithm.name=ppo"], "rank.enabled = true: must be false"),
        ("baselines/hopper_rnac_ds", ["env.num_envs=2"], "env.num_envs = 2: must be 1"),
        ("baselines/hopper_rnac_ipm", ["env.id=CartPole-v1"], "continuous-action env"),
        ("baselines/hopper_rnac_ipm", ["algorithm.ppo.minibatch_size=4096"], "must be <= collector.frames_per_batch"),
        ("baselines/hopper_rnac_ipm", ["algorithm.name=rnac_worst"], "did you mean 'rnac_ds'"),
        ("baselines/hopper_parseval", ["algorithm.parseval.lam=0"], "algorithm.parseval.lam"),
        ("quickstart", ["network.actor.sparse.layer=1"], "low-rank or the sparsification layer"),
        ("baselines/hopper_sparse", ["network.critic.sparse.layer=2"], "must index a hidden layer"),
        ("baselines/hopper_sparse", ["network.critic.sparse.k=4096"], "must be <= width (1024)"),
        ("baselines/hopper_rnac_ipm", ["algorithm.ppo.policy=gaussian"], "one of 'clipped_gaussian', 'tanh_gaussian'"),
        (
            "baselines/hopper_rnac_ipm",
            ["algorithm.ppo.normalize_advantage=global"],
            "one of 'batch', 'minibatch', 'none'",
        ),
        ("baselines/hopper_parseval", ["network.critic.init.scheme=xavier"], "one of 'default', 'orthogonal'"),
        (
            "baselines/hopper_parseval",
            ["network.actor.init.gain=-1"],
            "network.actor.init.gain = -1: must be a number > 0",
        ),
    ],
)
def test_bad_baseline_settings_are_recipe_errors(recipe, overrides, expected):
    with pytest.raises(RecipeError) as err:
        load_recipe(recipe, overrides)
    assert expected in str(err.value)


def test_recipes_with_the_old_rnac_section_still_load(tmp_path):
    """Run folders written before RNAC became registered algorithms say name: ppo + algorithm.rnac: read as the new
    names, and their checkpoints (fingerprint algorithm.name 'ppo', no options) still load."""
    from adarl.runtime.run_folder._checkpoints import _same_in_fingerprint, recipe_fingerprint

    old = tmp_path / "old.yaml"
    base = (REPO / "recipes" / "baselines" / "ppo_base.yaml").as_posix()
    old.write_text(
        f"extends: {base}\nname: old\nenv: {{id: Hopper-v5}}\n"
        "algorithm:\n  name: ppo\n  rnac: {mode: ds, kappa: 1.0e-5, num_candidates: 3, noise: 0.01}\n"
    )
    r = load_recipe(str(old))
    assert r.algorithm.name == "rnac_ds" and r.algorithm.options == {"num_candidates": 3, "noise": 0.01}
    fp = recipe_fingerprint(r)
    theirs = {k: v for k, v in fp.items() if k != "algorithm.options"} | {"algorithm.name": "ppo"}
    assert _same_in_fingerprint("algorithm.name", theirs, fp)
    assert not _same_in_fingerprint("algorithm.name", {**theirs, "algorithm.options": {}}, fp)
    plain = tmp_path / "plain.yaml"
    plain.write_text(f"extends: {base}\nname: plain\nenv: {{id: Hopper-v5}}\nalgorithm:\n  rnac: {{mode: none}}\n")
    assert load_recipe(str(plain)).algorithm.name == "ppo"
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        f"extends: {base}\nname: bad\nenv: {{id: Hopper-v5}}\nalgorithm:\n  name: sac\n  rnac: {{mode: ipm}}\n"
    )
    with pytest.raises(RecipeError, match="write algorithm.name: rnac_ipm"):
        load_recipe(str(bad))
