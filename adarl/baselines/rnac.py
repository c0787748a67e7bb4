"""RNAC (Zhou et al., 2023, "Natural actor-critic for robust RL with function approximation") on TorchRL's PPO.

Two ways RNAC makes the critic pessimistic over an uncertainty set, each as a stock TorchRL piece:

* **RNAC-IPM** (integral probability metric set): the TD error is shifted by ``kappa * ||theta_critic||``,
  ``delta = r + gamma V(s') - V(s) - kappa ||theta||``, i.e. GAE on the reward ``r - kappa ||theta||``.
  :class:`IPMAdvantage` is a :class:`torchrl.objectives.value.GAE` that applies the shift; ``||theta||`` is the
  norm of all critic weights and all biases but the output bias, detached (as the original code).
* **RNAC-DS** (double sampling): at every step, ``m`` candidate next states are drawn with actuation noise
  ``U[-noise, noise]`` from snapshots of the current MuJoCo state; with probability ``1/(m+1)`` the one the critic
  values lowest is taken, otherwise a uniformly random one. :class:`DoubleSamplingTransform` does it inside a
  TorchRL env at collection time: in its inverse pass (before the base env steps) it probes the candidates on
  the unwrapped MuJoCo env, restores the state exactly (``mj_setState`` + ``mj_forward``) and hands the base
  env the chosen candidate's noisy action, which re-simulates that candidate bit for bit through the full
  gymnasium wrapper stack (so time limits and episode statistics stay right). Cost: ``(m + 1)`` physics steps
  per env step. The stored ``"action"`` stays the policy's own action (PPO's log-probabilities need it).
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs import Transform
from torchrl.objectives.value import GAE

from adarl.errors import AdaRLValueError

__all__ = [
    "critic_parameter_norm",
    "IPMAdvantage",
    "DoubleSamplingTransform",
    "mujoco_state",
    "set_mujoco_state",
    "make_ipm_advantage",
    "make_double_sampling",
]


def critic_parameter_norm(critic: nn.Module) -> torch.Tensor:
    """``||theta||_2`` over every parameter of ``critic`` except the bias of its last linear layer (detached)."""
    linears = [p for p, m in critic.named_modules() if isinstance(m, nn.Linear) or hasattr(m, "w1")]
    out_bias = f"{linears[-1]}.bias" if linears else None
    if out_bias is not None and out_bias.startswith("."):
        out_bias = out_bias[1:]
    squares = [p.detach().pow(2).sum() for name, p in critic.named_parameters() if name != out_bias]
    if not squares:
        raise AdaRLValueError(f"critic {type(critic).__name__} has no parameters to take the norm of")
    return torch.stack(squares).sum().sqrt()


class IPMAdvantage(GAE):
    """GAE on the IPM-shifted reward ``r - kappa * ||theta_critic||`` (RNAC-IPM's robust TD error).

    Same arguments as :class:`~torchrl.objectives.value.GAE` plus ``kappa`` (the original uses 1e-5). The shift
    is recomputed at every call from the critic's current parameters; :attr:`last_shift` holds the last value.
    The input's reward is left untouched; advantage and value target are written into it."""

    def __init__(self, *, gamma: float, lmbda: float, value_network, kappa: float = 1e-5, **kwargs) -> None:
        if isinstance(kappa, bool) or not isinstance(kappa, (int, float)) or kappa < 0:
            raise AdaRLValueError(f"kappa must be a number >= 0, got {kappa!r}")
        super().__init__(gamma=gamma, lmbda=lmbda, value_network=value_network, **kwargs)
        self.kappa = float(kappa)
        self.last_shift = float("nan")

    def reward_shift(self) -> torch.Tensor:
        """``kappa * ||theta_critic||`` for the critic as it is now."""
        return self.kappa * critic_parameter_norm(self.value_network)

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        shift = self.reward_shift()
        self.last_shift = float(shift)
        reward_key = ("next", self.tensor_keys.reward)
        shifted = tensordict.copy()
        shifted.set("next", tensordict.get("next").copy())
        shifted.set(reward_key, tensordict.get(reward_key) - shift.to(tensordict.get(reward_key).dtype))
        out = super().forward(shifted, **kwargs)
        for key in (self.tensor_keys.advantage, self.tensor_keys.value_target, self.tensor_keys.value):
            if key in out.keys(True):
                tensordict.set(key, out.get(key))
        return tensordict


def _mujoco():
    import mujoco

    return mujoco


def mujoco_state(model, data) -> np.ndarray:
    """A full integration-state snapshot of a live MuJoCo ``data`` (``mj_getState``)."""
    mj = _mujoco()
    spec = mj.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mj.mj_stateSize(model, spec), dtype=np.float64)
    mj.mj_getState(model, data, state, spec)
    return state


def set_mujoco_state(model, data, state: np.ndarray) -> None:
    """Restore a :func:`mujoco_state` snapshot exactly (``mj_setState`` then ``mj_forward``)."""
    mj = _mujoco()
    mj.mj_setState(model, data, state, mj.mjtState.mjSTATE_INTEGRATION)
    mj.mj_forward(model, data)


class DoubleSamplingTransform(Transform):
    """RNAC-DS at collection time: probe ``m`` noisy next states, step into the worst with probability 1/(m+1).

    Args:
        num_candidates: ``m`` (the original uses 2).
        noise: half-width of the uniform actuation noise (the original uses 5e-3).
        value_network: a TensorDict module mapping ``obs_key`` to ``"state_value"``; pass it here or through
            :meth:`set_value_network` once the critic exists. Without one, candidates are picked uniformly.
        seed: seed of the transform's own generator (noise and choices).
        obs_key / action_key: the env's keys.

    Works on a single (non-batched) gymnasium MuJoCo env: put it inside each worker's env for batched envs.
    :attr:`worst_picks` / :attr:`steps` count how often the pessimistic candidate was taken.
    """

    def __init__(
        self,
        num_candidates: int = 2,
        noise: float = 5e-3,
        value_network: nn.Module | None = None,
        seed: int | None = None,
        obs_key: str = "observation",
        action_key: str = "action",
    ) -> None:
        if isinstance(num_candidates, bool) or not isinstance(num_candidates, int) or num_candidates < 1:
            raise AdaRLValueError(f"num_candidates must be an integer >= 1, got {num_candidates!r}")
        if isinstance(noise, bool) or not isinstance(noise, (int, float)) or noise < 0:
            raise AdaRLValueError(f"noise must be a number >= 0, got {noise!r}")
        super().__init__(in_keys=[], out_keys=[])
        self.num_candidates = num_candidates
        self.noise = float(noise)
        self.set_value_network(value_network)
        self.obs_key, self.action_key = obs_key, action_key
        self.rng = np.random.default_rng(seed)
        self.worst_picks = 0
        self.steps = 0

    @property
    def value_network(self) -> nn.Module | None:
        return self.__dict__["_value_network"]

    def set_value_network(self, value_network: nn.Module | None) -> None:
        """Use ``value_network`` to rank the candidates (kept outside this module's parameters and state)."""
        self.__dict__["_value_network"] = value_network

    # -- the live MuJoCo env behind the TorchRL env
    def _gym_env(self):
        parent = self.parent
        base = getattr(parent, "base_env", None) if parent is not None else None
        gym_env = getattr(base, "_env", None)
        if gym_env is None or not hasattr(gym_env, "unwrapped") or not hasattr(gym_env.unwrapped, "data"):
            raise AdaRLValueError(
                "DoubleSamplingTransform needs a single gymnasium MuJoCo env as its base env (GymEnv of a MuJoCo "
                f"id); got {type(base).__name__}. For batched envs put it inside each worker's env."
            )
        return gym_env.unwrapped

    @torch.no_grad()
    def _values(self, observations: np.ndarray, like: torch.Tensor) -> np.ndarray:
        obs = torch.as_tensor(observations, dtype=like.dtype, device=like.device)
        td = TensorDict({self.obs_key: obs}, batch_size=[obs.shape[0]], device=like.device)
        return self.value_network(td).get("state_value").reshape(-1).double().cpu().numpy()

    def probe(self, action: torch.Tensor) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Noisy candidate actions (in the dtype the env receives) and the next observations they lead to; the
        MuJoCo state is restored exactly afterwards."""
        env = self._gym_env()
        model, data = env.model, env.data
        snapshot = mujoco_state(model, data)
        actions, observations = [], []
        base = action.detach().cpu()
        for _ in range(self.num_candidates):
            eps = torch.as_tensor(self.rng.uniform(-self.noise, self.noise, size=base.shape), dtype=base.dtype)
            noisy = base + eps
            obs, *_ = env.step(noisy.numpy().astype(np.float64))
            actions.append(noisy)
            observations.append(np.asarray(obs, dtype=np.float64).copy())
            set_mujoco_state(model, data, snapshot)
        return actions, observations

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        if action.ndim != 1:
            raise AdaRLValueError(
                f"DoubleSamplingTransform works on one env; got an action of shape {tuple(action.shape)}"
            )
        actions, observations = self.probe(action)
        m = self.num_candidates
        if self.value_network is not None and self.rng.random() < 1.0 / (m + 1):
            values = self._values(np.stack(observations), action)
            pick = int(np.argmin(values))
            self.worst_picks += 1
        else:
            pick = int(self.rng.integers(m))
        self.steps += 1
        tensordict.set(self.action_key, actions[pick].to(device=action.device, dtype=action.dtype))
        return tensordict

    def rng_state(self) -> dict:
        """The generator's state (for exact resume)."""
        return self.rng.bit_generator.state

    def set_rng_state(self, state: dict) -> None:
        self.rng.bit_generator.state = state


# ---- the hooks through which the registered algorithms rnac_ipm and rnac_ds (adarl.plugins) plug into the PPO loop


def make_ipm_advantage(recipe, critic) -> IPMAdvantage:
    """``rnac_ipm``'s advantage hook: GAE on the reward shifted by ``algorithm.options.kappa * ||theta_critic||``."""
    alg = recipe.algorithm
    return IPMAdvantage(
        gamma=alg.gamma,
        lmbda=alg.ppo.gae_lambda,
        value_network=critic,
        kappa=alg.options["kappa"],
        average_gae=False,
    )


def make_double_sampling(recipe, critic) -> DoubleSamplingTransform:
    """``rnac_ds``'s env hook: the double-sampling transform on the training env, pessimistic w.r.t. ``critic``."""
    o = recipe.algorithm.options
    return DoubleSamplingTransform(o["num_candidates"], o["noise"], value_network=critic, seed=recipe.seed + 2)
