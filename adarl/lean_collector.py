"""A lean single-process collector for SAC's TanhNormal policy: TorchRL's ``Collector`` without its per-step cost.

Why: with one env on CPU, ``torchrl.collectors.Collector`` spends ~0.6 ms per frame in TensorDict and
policy-wrapper bookkeeping on top of the environment itself (docs/performance.md). :class:`LeanCollector`
steps the same TorchRL env (transforms, perturbations and all) with ``env.step_and_maybe_reset`` and samples
the action straight from the actor's network: ``tanh(loc + scale * eps)`` (then scaled to the action box),
the same distribution the ``ProbabilisticActor`` samples from in ``ExplorationType.RANDOM``. Batches carry the
keys the replay buffer and the training loop read (``observation``, ``action``, ``("next", ...)`` with reward,
done flags and the env's own extra keys).
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDictBase

from adarl.errors import AdaRLValueError

__all__ = ["LeanCollector", "wants_lean"]


def _is_tanh_normal_actor(policy) -> bool:
    from tensordict.nn import NormalParamExtractor

    first = getattr(policy, "module", [None])[0]
    net = getattr(first, "module", None)
    return isinstance(net, torch.nn.Sequential) and isinstance(net[-1], NormalParamExtractor)


def wants_lean(setting, env, policy) -> bool:
    """Resolve ``collector.lean``: ``'auto'`` is on for one env and a TanhNormal actor; ``True`` insists."""
    ok = tuple(env.batch_size) == () and _is_tanh_normal_actor(policy)
    if setting == "auto":
        return ok
    if setting is True and not ok:
        raise AdaRLValueError("collector.lean: true needs one env (env.num_envs: 1) and a TanhNormal (box-action) "
                              "actor; allowed otherwise: 'auto' or false")
    return bool(setting)


class LeanCollector:
    """Iterate batches of ``frames_per_batch`` transitions from ``env`` under ``policy`` (uniform-random first).

    Args:
        env: a TorchRL env with a batch size of ``[]`` (one environment).
        policy: a ``ProbabilisticActor`` built by :func:`adarl.builders.make_sac_actor` for a box action space.
        frames_per_batch: transitions per yielded batch.
        init_random_frames: frames of uniform-random actions before the policy acts.
        total_frames: stop after this many frames; ``-1`` never stops (as the Trainer uses it).
    """

    def __init__(self, env, policy, *, frames_per_batch: int, init_random_frames: int = 0,
                 total_frames: int = -1) -> None:
        if tuple(env.batch_size) != ():
            raise AdaRLValueError(f"LeanCollector runs one env (batch_size []), got batch_size {tuple(env.batch_size)}; "
                                  "set collector.lean: false for vectorised envs")
        if not _is_tanh_normal_actor(policy):
            raise AdaRLValueError("LeanCollector needs a TanhNormal actor from adarl.builders.make_sac_actor; "
                                  "set collector.lean: false")
        if frames_per_batch < 1:
            raise AdaRLValueError(f"frames_per_batch must be >= 1, got {frames_per_batch}")
        self.env, self.policy, self.net = env, policy, policy.module[0].module
        self.frames_per_batch = int(frames_per_batch)
        self.init_random_frames = int(init_random_frames)
        self.total_frames = int(total_frames)
        kw = policy.module[1].distribution_kwargs
        low = torch.as_tensor(kw.get("low", -1.0), dtype=torch.float32)
        high = torch.as_tensor(kw.get("high", 1.0), dtype=torch.float32)
        self._mid, self._half = (high + low) / 2, (high - low) / 2
        self._affine = bool((low != -1).any() or (high != 1).any())
        self.frames = 0
        self._td: TensorDictBase | None = None

    def reset(self) -> None:
        """Start a fresh episode at the next step (call after anything else stepped or reset the env)."""
        self._td = None

    @torch.no_grad()
    def act(self, td: TensorDictBase) -> torch.Tensor:
        """One action: uniform-random during the random phase, else a TanhNormal sample from the policy."""
        if self.frames < self.init_random_frames:
            return self.env.action_spec.rand()
        loc, scale = self.net(td.get("observation"))
        action = torch.tanh(loc + scale * torch.randn_like(loc))
        return action * self._half + self._mid if self._affine else action

    def __iter__(self) -> Iterator[TensorDictBase]:
        while self.total_frames < 0 or self.frames < self.total_frames:
            steps = []
            for _ in range(self.frames_per_batch):
                if self._td is None:
                    self._td = self.env.reset()
                self._td.set("action", self.act(self._td))
                out, self._td = self.env.step_and_maybe_reset(self._td)
                steps.append(out)
                self.frames += 1
            yield torch.stack(steps).contiguous()

    def state_dict(self) -> dict:
        """Frame counter and the live step's TensorDict (the carrier), for exact resume."""
        return {"frames": self.frames, "iter": 0, "traj_pool": None,
                "carrier": None if self._td is None else self._td.to_dict(),
                "carrier_batch_size": [] if self._td is None else list(self._td.batch_size)}

    def load_state_dict(self, state: dict, *, carrier: bool = True) -> None:
        from tensordict import TensorDict

        self.frames = int(state["frames"])
        if carrier and state.get("carrier") is not None:
            self._td = TensorDict(state["carrier"], batch_size=state["carrier_batch_size"])
        else:
            self._td = None

    def shutdown(self) -> None:
        """Nothing runs in the background; provided for the Collector's interface."""
        self._td = None
