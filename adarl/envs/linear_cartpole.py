"""The linearised CartPole of the AdaRL paper (App. A.1, Eq. 17): a batched TorchRL env with a known rank of 4.

Around the upright equilibrium, with Florian's (2007) corrected dynamics, the cart-pole is linear::

    d/dt [x, x', th, th'] = A(l) [x, x', th, th'] + B(l) u

with ``A(l)``, ``B(l)`` exactly as Eq. 17 (``l`` the half pole length, 0.5 by default; ``m`` pole mass 0.1,
``M`` cart mass 1.0, ``g`` 9.8, as gymnasium's CartPole). It is integrated with explicit Euler at ``tau`` = 0.02 s.
The 4x4 transition has rank 4: the paper's "intrinsic rank" of the Fig. 1 experiment.

Actions: the paper writes ``u in {0, 1}``; like gymnasium's CartPole we read that as the action *index* and push
with force ``u = force_mag * (2 a - 1)`` (+-10 N), since a force in one direction only cannot balance the pole.
The action spec is ``OneHot(2)`` as TorchRL's ``GymEnv("CartPole-v1")``, so recipes and the discrete SAC loss
treat both envs alike. Reward 1 per step; an episode terminates when ``|x| > 2.4`` or ``|th| > 12 deg`` and is
truncated after ``max_episode_steps`` (500, as CartPole-v1).

Pole-length uncertainty: ``pole_length_range=(lo, hi)`` draws ``l`` uniformly per sub-env at every reset (the
paper's ``l in [0.95 l0, 1.05 l0]``), or the env runs under ``adarl.envs.make_env("LinearCartPole-v0")`` where the
usual :class:`~adarl.envs.PerturbedDynamicsEnvTransform` schedules set it (parameter ``pole_length``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

from adarl.errors import AdaRLValueError

__all__ = ["LinearCartPoleEnv", "linear_cartpole_matrices", "LINEAR_CARTPOLE_ID"]

LINEAR_CARTPOLE_ID = "LinearCartPole-v0"


def linear_cartpole_matrices(
    pole_length: float | torch.Tensor,
    *,
    masspole: float = 0.1,
    masscart: float = 1.0,
    gravity: float = 9.8,
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``A(l)`` (``[..., 4, 4]``) and ``B(l)`` (``[..., 4]``) of Eq. 17 for a (batch of) half pole length(s)."""
    l = torch.as_tensor(pole_length, dtype=dtype)
    m, M, g = masspole, masscart, gravity
    total = m + M
    denom = 4.0 / 3.0 - m / total
    A = torch.zeros(*l.shape, 4, 4, dtype=dtype)
    A[..., 0, 1] = 1.0
    A[..., 1, 2] = -m * g / (total * denom)
    A[..., 2, 3] = 1.0
    A[..., 3, 2] = g / (l * denom)
    B = torch.zeros(*l.shape, 4, dtype=dtype)
    B[..., 1] = 1.0 / total + m / (total**2 * denom)
    B[..., 3] = -1.0 / (l * total * denom)
    return A, B


class LinearCartPoleEnv(EnvBase):
    """Batched linear CartPole (paper Eq. 17) with per-episode pole length.

    Args:
        pole_length: nominal half pole length ``l0`` (used when no range is given).
        pole_length_range: ``(lo, hi)``: draw ``l`` uniformly in it for each sub-env at each reset.
        max_episode_steps: truncation horizon.
        batch_size: e.g. ``(8,)`` for 8 independent cart-poles stepped as one tensor op.
        tau, force_mag: integration step and push force (gymnasium's 0.02 s and 10 N).
    """

    #: lets :func:`adarl.envs.find_gym_env` hand this env itself to the dynamics applier
    adarl_native = True

    def __init__(
        self,
        pole_length: float = 0.5,
        *,
        pole_length_range: Sequence[float] | None = None,
        max_episode_steps: int = 500,
        batch_size: Sequence[int] = (),
        device: str | torch.device = "cpu",
        tau: float = 0.02,
        force_mag: float = 10.0,
        seed: int | None = None,
    ) -> None:
        if not (isinstance(pole_length, (int, float)) and math.isfinite(pole_length) and pole_length > 0):
            raise AdaRLValueError(f"pole_length must be a finite number > 0, got {pole_length!r}")
        if pole_length_range is not None:
            lo, hi = (float(v) for v in pole_length_range)
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise AdaRLValueError(
                    f"pole_length_range must be (lo, hi) with 0 < lo <= hi, got {pole_length_range!r}"
                )
            pole_length_range = (lo, hi)
        if isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1:
            raise AdaRLValueError(f"max_episode_steps must be an integer >= 1, got {max_episode_steps!r}")
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.default_length = float(pole_length)
        self.pole_length_range = pole_length_range
        self.max_episode_steps = max_episode_steps
        self.tau, self.force_mag = float(tau), float(force_mag)
        self.x_threshold, self.theta_threshold = 2.4, 12 * 2 * math.pi / 360
        bs = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, 4), dtype=torch.float32, device=self.device), shape=bs, device=self.device
        )
        self.action_spec = OneHot(2, shape=(*bs, 2), device=self.device)
        self.reward_spec = Unbounded(shape=(*bs, 1), dtype=torch.float32, device=self.device)
        self.full_done_spec = Composite(
            {
                k: Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=self.device)
                for k in ("done", "terminated", "truncated")
            },
            shape=bs,
            device=self.device,
        )
        self._state = torch.zeros(*bs, 4, dtype=torch.float64, device=self.device)
        self._length = torch.full(tuple(bs), self.default_length, dtype=torch.float64, device=self.device)
        self._fixed_length: float | None = None
        self._steps = torch.zeros(tuple(bs), dtype=torch.int64, device=self.device)
        self.np_random_seed: int | None = None
        self._np_random = torch.Generator(device=self.device)
        self._np_random.seed()
        if seed is not None:
            self.set_seed(seed)

    # ------------------------------------------------------------------ dynamics parameters
    @property
    def pole_length(self) -> torch.Tensor:
        """The half pole length of each sub-env in the current episode (shape ``batch_size``)."""
        return self._length.clone()

    def set_pole_length(self, length: float | None) -> None:
        """Fix ``l`` for the next episodes (None: back to the nominal length or the range). Applied at reset."""
        if length is not None and not (math.isfinite(float(length)) and float(length) > 0):
            raise AdaRLValueError(f"pole_length must be a finite number > 0, got {length!r}")
        self._fixed_length = None if length is None else float(length)
        self._length.fill_(self.default_length if length is None else float(length))

    # ------------------------------------------------------------------ EnvBase
    def snapshot(self) -> dict:
        """The live episode (state, pole lengths, step counts) and the generator, for exact resume."""
        return {
            "state": self._state.clone(),
            "length": self._length.clone(),
            "steps": self._steps.clone(),
            "rng": self._np_random.get_state(),
            "fixed_length": self._fixed_length,
            "seed": getattr(self, "np_random_seed", None),
        }

    def restore(self, snap: dict) -> None:
        self._state, self._length, self._steps = snap["state"].clone(), snap["length"].clone(), snap["steps"].clone()
        self._np_random.set_state(snap["rng"])
        self._fixed_length = snap["fixed_length"]
        self.np_random_seed = snap["seed"]

    def _set_seed(self, seed: int | None) -> None:
        # A new generator object per seeding (as gymnasium does) so the perturbation transform sees the reseed.
        self._np_random = torch.Generator(device=self.device)
        if seed is None:
            self._np_random.seed()
            self.np_random_seed = None
        else:
            self._np_random.manual_seed(int(seed))
            self.np_random_seed = int(seed)

    def _uniform(self, shape, lo: float, hi: float) -> torch.Tensor:
        u = torch.rand(shape, generator=self._np_random, dtype=torch.float64, device=self.device)
        return lo + (hi - lo) * u

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        bs = tuple(self.batch_size)
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(bs)
        new_state = self._uniform((*bs, 4), -0.05, 0.05)
        if self._fixed_length is not None:
            new_len = torch.full(bs, self._fixed_length, dtype=torch.float64, device=self.device)
        elif self.pole_length_range is not None:
            new_len = self._uniform(bs, *self.pole_length_range)
        else:
            new_len = torch.full(bs, self.default_length, dtype=torch.float64, device=self.device)
        if mask is None:
            self._state, self._length = new_state, new_len
            self._steps.zero_()
        else:
            self._state = torch.where(mask.unsqueeze(-1), new_state, self._state)
            self._length = torch.where(mask, new_len, self._length)
            self._steps = torch.where(mask, torch.zeros_like(self._steps), self._steps)
        false = torch.zeros(*bs, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                "observation": self._state.float(),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        push_right = action[..., 1].to(torch.float64)  # one-hot [left, right]
        u = self.force_mag * (2.0 * push_right.reshape(tuple(self.batch_size)) - 1.0)
        A, B = linear_cartpole_matrices(self._length)
        A, B = A.to(self.device), B.to(self.device)
        deriv = (A @ self._state.unsqueeze(-1)).squeeze(-1) + B * u.unsqueeze(-1)
        self._state = self._state + self.tau * deriv
        self._steps = self._steps + 1
        x, th = self._state[..., 0], self._state[..., 2]
        terminated = (x.abs() > self.x_threshold) | (th.abs() > self.theta_threshold)
        truncated = (self._steps >= self.max_episode_steps) & ~terminated
        terminated, truncated = terminated.unsqueeze(-1), truncated.unsqueeze(-1)
        return TensorDict(
            {
                "observation": self._state.float(),
                "reward": torch.ones(*self.batch_size, 1, dtype=torch.float32, device=self.device),
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def __repr__(self) -> str:
        rng = f", pole_length_range={self.pole_length_range}" if self.pole_length_range else ""
        return (
            f"{type(self).__name__}(pole_length={self.default_length}{rng}, batch_size={list(self.batch_size)}, "
            f"max_episode_steps={self.max_episode_steps})"
        )
