"""Step a :func:`adarl.envs.make_env` env's gymnasium env directly, writing a batch of frames into preallocated tensors.

Why: with one env on CPU, TorchRL's ``step_and_maybe_reset`` through ``TransformedEnv(GymEnv, Compose(...))``
costs ~0.5 ms per frame of TensorDict and spec bookkeeping on top of the ~0.2 ms the simulator takes, and
stacking the per-frame TensorDicts costs more: the :class:`~adarl.fast.collector.LeanCollector` took 1.19 ms per
Hopper-v5 frame that way and takes 0.52 ms this way (``benchmarks/collector_speed.py``, policy actions, one
torch thread). :class:`DirectStepper` calls the wrapped gymnasium env's ``step``
itself (the same wrappers, ``TimeLimit`` included, so the simulator, gymnasium's counters and RNG end up where
TorchRL's path leaves them) and computes what the four transforms of ``make_env`` add to each frame
(``DoubleToFloat``'s cast, ``StepCounter``'s count, ``RewardSum``'s float32 running sum and the episode's
perturbation values), producing exactly the TensorDicts TorchRL's path does: same keys in the same order,
dtypes, shapes and values, bit for bit. Resets (once per episode) still go through TorchRL
(``env.reset()``/``env.maybe_reset``), so the perturbation draw, seeding and every transform's reset are TorchRL's
own; so is the carrier (the step-MDP'd last frame) handed back. Any other env layout is refused
(:func:`direct_stepper` returns None under ``"auto"``): there the caller keeps TorchRL's path.

Mirrors: ``TransformedEnv.step_and_maybe_reset`` of a :func:`adarl.envs.make_env` env (``GymEnv`` with its four
transforms), frame by frame.
Equality: ``tests/test_direct_env.py::test_direct_batches_and_carrier_equal_torchrls_bit_for_bit`` (bit for bit,
carrier included) and ``tests/test_direct_env.py::test_humanoid_batches_equal_torchrls``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import unravel_key
from torchrl.envs import Compose, DoubleToFloat, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.libs.gym import GymEnv, GymWrapper

from adarl.envs.perturbation import EPISODE_KEY, PerturbedDynamicsEnvTransform
from adarl.errors import AdaRLValueError

__all__ = ["DirectStepper", "direct_stepper", "DIRECT_SETTINGS"]

DIRECT_SETTINGS = ("auto", True, False)

_LAYOUT = "Compose(PerturbedDynamicsEnvTransform (optional), DoubleToFloat, StepCounter, RewardSum), as make_env builds"
_FLAGS = ("done", "terminated", "truncated")


def direct_stepper(env, setting: bool | str = "auto") -> DirectStepper | None:
    """Resolve ``direct``: a :class:`DirectStepper` for ``env``, or None for TorchRL's own stepping.

    ``"auto"`` steps directly where the env is one this module reproduces exactly; ``True`` insists (raises
    naming what is not supported); ``False`` always keeps TorchRL's path."""
    if not (isinstance(setting, bool) or setting == "auto"):
        raise AdaRLValueError(f"direct must be one of {DIRECT_SETTINGS}, got {setting!r}")
    if setting is False:
        return None
    why = _unsupported(env)
    if why is None:
        return DirectStepper(env)
    if setting is True:
        raise AdaRLValueError(
            f"direct=True cannot step this env directly: {why}; use direct='auto' or False for TorchRL's own stepping"
        )
    return None


def _unsupported(env) -> str | None:
    """Why ``env`` is not a layout :class:`DirectStepper` reproduces (None when it is)."""
    if not isinstance(env, TransformedEnv) or type(env.base_env) not in (GymEnv, GymWrapper):
        what = type(env).__name__ + (f" over {type(env.base_env).__name__}" if isinstance(env, TransformedEnv) else "")
        return f"the env is a {what}; allowed: a TransformedEnv over one GymEnv with {_LAYOUT}"
    base = env.base_env
    if tuple(env.batch_size) != () or env.device is None or torch.device(env.device).type != "cpu":
        return f"batch_size {list(env.batch_size)} on {env.device}; allowed: one env (batch_size []) on the CPU"
    transforms = list(env.transform) if isinstance(env.transform, Compose) else [env.transform]
    expected = [DoubleToFloat, StepCounter, RewardSum]
    if transforms and type(transforms[0]) is PerturbedDynamicsEnvTransform:
        expected.insert(0, PerturbedDynamicsEnvTransform)
    for i, t in enumerate(transforms):
        if i >= len(expected) or type(t) is not expected[i]:
            return f"transform {type(t).__name__} at position {i} is not supported; allowed: {_LAYOUT}"
    if len(transforms) != len(expected):
        return f"transforms {[type(t).__name__ for t in transforms]}; allowed: {_LAYOUT}"
    spec = env.full_observation_spec  # resolves the transforms' keys from the specs
    cast, counter, rsum = transforms[-3:]
    if (
        list(cast.in_keys or ()) != ["observation"]
        or list(cast.out_keys or ()) != ["observation"]
        or cast.in_keys_inv is None
        or list(cast.in_keys_inv)
    ):
        return (
            f"DoubleToFloat(in_keys={cast.in_keys}, out_keys={cast.out_keys}, in_keys_inv={cast.in_keys_inv}); "
            "allowed: in_keys=out_keys=['observation'], in_keys_inv=[]"
        )
    if counter.max_steps is not None or counter.step_count_key != "step_count":
        return (
            f"StepCounter(max_steps={counter.max_steps}, step_count_key={counter.step_count_key!r}); allowed: "
            "max_steps=None, step_count_key='step_count' (the time limit is gymnasium's)"
        )
    if [*rsum.in_keys] != ["reward"] or [*rsum.out_keys] != ["episode_reward"]:
        return f"RewardSum(in_keys={rsum.in_keys}, out_keys={rsum.out_keys}); allowed: ['reward'] -> ['episode_reward']"
    if (
        base.wrapper_frame_skip != 1
        or base.info_dict_reader
        or getattr(base, "from_pixels", False)
        or not base._convert_actions_to_numpy
        or base.__dict__.get("_torchrl_native_autoreset", False)
        or "_compiled_step_and_maybe_reset" in env.__dict__
    ):
        return (
            "the GymEnv uses frame skipping, an info-dict reader, pixels, native auto-reset or a compiled step; "
            "allowed: a plain GymEnv(env_id) as make_env builds"
        )
    perturbation = transforms[0] if len(transforms) == 4 else None
    dynamics = (
        set()
        if perturbation is None
        else {unravel_key((*perturbation.out_key, k)) for k in (*perturbation.params, EPISODE_KEY)}
    )
    wanted = {"observation": torch.float32, "step_count": torch.int64, "episode_reward": torch.float32}
    leaves = set(spec.keys(True, True))
    if leaves != set(wanted) | dynamics or any(spec[k].dtype is not d for k, d in wanted.items()):
        return f"observation entries {sorted(map(str, leaves))}; allowed: {sorted(map(str, set(wanted) | dynamics))}"
    if base.observation_spec["observation"].dtype not in (torch.float32, torch.float64) or set(
        base.observation_spec.keys(True, True)
    ) != {"observation"}:
        return "the GymEnv observes more than one float 'observation' array"
    reward, done, action = env.full_reward_spec, env.full_done_spec, env.full_action_spec
    if (
        list(reward.keys(True, True)) != ["reward"]
        or reward["reward"].dtype is not torch.float32
        or tuple(reward["reward"].shape) != (1,)
    ):
        return f"reward entries {list(reward.keys(True, True))}; allowed: one float32 'reward' of shape [1]"
    if set(done.keys(True, True)) != set(_FLAGS) or any(tuple(done[k].shape) != (1,) for k in _FLAGS):
        return f"done entries {list(done.keys(True, True))}; allowed: {list(_FLAGS)} of shape [1]"
    if list(action.keys(True, True)) != ["action"] or action["action"].dtype is not torch.float32:
        return f"action entries {list(action.keys(True, True))}; allowed: one float32 'action'"
    return None


class DirectStepper:
    """Batches of frames from ``env`` (a layout :func:`direct_stepper` accepted), identical to TorchRL's.

    :meth:`rollout` is ``n`` times ``td["action"] = act(...)``, ``out, td = env.step_and_maybe_reset(td)`` and
    ``torch.stack`` of the ``out``\\ s, without building a TensorDict per frame.
    """

    def __init__(self, env) -> None:
        self.env = env
        transform = env.transform[0]
        self.perturbation = transform if isinstance(transform, PerturbedDynamicsEnvTransform) else None
        spec = env.full_observation_spec
        # the perturbation's entries, in the order its output has them
        self.dynamics = (
            []
            if self.perturbation is None
            else [unravel_key((*self.perturbation.out_key, k)) for k in (*self.perturbation.params, EPISODE_KEY)]
        )
        # ("next", ...) in the order TorchRL writes it: GymLikeEnv._step, then the transforms in turn
        layout = [
            ("observation", spec["observation"]),
            ("reward", env.full_reward_spec["reward"]),
            *((k, env.full_done_spec[k]) for k in ("truncated", "done", "terminated")),
            *((k, spec[k]) for k in self.dynamics),
            ("step_count", spec["step_count"]),
            ("episode_reward", spec["episode_reward"]),
        ]
        self.next_layout = [(k, tuple(s.shape), s.dtype) for k, s in layout]
        # the entries step_mdp moves from ("next", ...) to the root, i.e. the carrier's, less the action
        self.state_keys = [k for k, _, _ in self.next_layout if k != "reward"]
        self.action_spec = env.full_action_spec["action"]

    def accepts(self, td: TensorDictBase) -> bool:
        """Whether ``td`` is a carrier this stepper continues exactly (its entries are the env's, action aside)."""
        return set(td.keys(True, True)) - {"action"} == set(self.state_keys)

    def rollout(
        self,
        td: TensorDictBase | None,
        n: int,
        act: Callable[[torch.Tensor, int], torch.Tensor],
        *,
        until_done: bool = False,
    ) -> tuple[TensorDictBase, TensorDictBase | None]:
        """``n`` frames from the carrier ``td`` (None: reset first): the batch and the carrier that follows.

        ``act(observation, i)`` gives frame ``i``'s action from its float32 observation. ``until_done``: stop at the
        first episode end instead (the batch is cut there and no carrier is made, so the env is not reset: what
        ``env.rollout(n, policy, break_when_any_done=True)`` leaves, the evaluation's episode)."""
        env = self.env
        gym = env.base_env._env  # the gymnasium env with its wrappers (TimeLimit, OrderEnforcing, ...)
        if td is None:
            td = env.reset()
        batch = self._empty(td, n)
        nxt = batch.get("next")
        observations = nxt.get("observation")
        action_np, obs_np, reward_np = batch.get("action").numpy(), observations.numpy(), nxt.get("reward").numpy()
        term_np, trunc_np = nxt.get("terminated").numpy(), nxt.get("truncated").numpy()
        i = 0
        while i < n:
            start, obs = i, td.get("observation")
            while True:
                # GymLikeEnv._step: the action as numpy, the reward summed from 0 (frame skip), float32 casts
                action = act(obs, i).detach().cpu().numpy()
                o, r, terminated, truncated, _ = gym.step(action)
                action_np[i] = action  # after the step, as TorchRL's frame shares the array gymnasium was given
                obs_np[i] = o
                reward_np[i] = 0 + r
                term_np[i] = terminated
                trunc_np[i] = truncated
                i += 1
                if terminated or truncated or i == n:
                    break
                obs = observations[i - 1].clone()  # a tensor of its own, as TorchRL hands the policy
            self._finish(batch, td, start, i)
            if until_done:
                return batch[:i], None
            # TorchRL's own step_mdp and (at an episode end) reset make the next carrier (tensors of its own)
            td = env.maybe_reset(env._step_mdp(batch[i - 1]).clone())
        return batch, td

    def _empty(self, td: TensorDictBase, n: int) -> TensorDictBase:
        """The batch's tensors, keyed in the order ``torch.stack`` of TorchRL's frames would have them."""
        batch = TensorDict(batch_size=[n], device=self.env.device)
        for key, value in td.items(True, True):
            batch.set(key, torch.empty((n, *value.shape), dtype=value.dtype))
        if "action" not in td.keys():
            batch.set("action", torch.empty((n, *self.action_spec.shape), dtype=self.action_spec.dtype))
        for key, shape, dtype in self.next_layout:
            batch.set(unravel_key(("next", key)), torch.empty((n, *shape), dtype=dtype))
        return batch

    def _finish(self, batch: TensorDictBase, td: TensorDictBase, start: int, end: int) -> None:
        """Fill what the transforms add to frames ``start:end`` of one episode, which began from carrier ``td``."""
        nxt = batch.get("next")
        seg = slice(start, end)
        torch.logical_or(nxt.get("terminated")[seg], nxt.get("truncated")[seg], out=nxt.get("done")[seg])
        # StepCounter: +1 a frame; RewardSum: a float32 running sum (numpy accumulates in float32, in order)
        steps = torch.arange(1, end - start + 1).unsqueeze(-1)
        torch.add(td.get("step_count"), steps, out=nxt.get("step_count")[seg])
        total = np.empty(end - start + 1, dtype=np.float32)
        total[0] = td.get("episode_reward").numpy()[0]
        total[1:] = nxt.get("reward").numpy()[seg, 0]
        np.add.accumulate(total, out=total)
        nxt.get("episode_reward").numpy()[seg, 0] = total[1:]
        if self.perturbation is not None:  # the episode's values, as the transform writes them at every step
            values = self.perturbation._output()
            for key in self.dynamics:
                nxt.get(key)[seg] = values.get(key[len(self.perturbation.out_key) :])
        # step_mdp: a frame's root is the carrier, then the previous frame's ("next", ...)
        for key in self.state_keys:
            root = batch.get(key)
            root[start] = td.get(key)
            root[start + 1 : end] = nxt.get(key)[start : end - 1]
