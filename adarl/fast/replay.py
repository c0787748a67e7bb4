"""Uniform replay sampling straight into the tensors an update reads, with the replay buffer's own RNG.

Why: ``TensorDictReplayBuffer.sample()`` costs ~0.4 ms per batch on CPU (sampler, storage and TensorDict
indexing of every key, plus the ``index`` bookkeeping), about a tenth of a fused (64, 64) SAC update.
:class:`UniformTensorSampler` draws the *same* indices the buffer's ``RandomSampler`` would draw (one
``torch.randint(0, len(storage), (batch_size,), generator=...)`` on the buffer's generator, so the RNG stream,
checkpoints and exact resume are unchanged) and gathers only the keys it is asked for from the storage's
tensors. The buffer stays the single owner of the data: extending, warm-start refills, checkpointing and
``rb.sample()`` keep working, and the two can be mixed.

Mirrors: ``TensorDictReplayBuffer.sample()`` with a ``RandomSampler`` and a one-dimensional tensor storage.
Equality: ``tests/test_fast_sac.py::test_uniform_tensor_sampler_draws_what_the_buffer_draws`` (the same tensors
and the same RNG consumption).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.data.replay_buffers.storages import TensorStorage

from adarl.errors import AdaRLValueError

__all__ = ["UniformTensorSampler"]


class UniformTensorSampler:
    """``sampler()`` returns ``rb.sample().get(key)`` for each of ``keys``, for a fraction of the cost.

    Args:
        replay_buffer: a TorchRL replay buffer with a ``RandomSampler``, a one-dimensional
            ``LazyTensorStorage``/``LazyMemmapStorage`` and no transform (what
            :func:`adarl.runtime.builders.sac.build_sac_components` builds); anything else raises, so a buffer this
            class cannot reproduce is never sampled differently.
        keys: the (nested) keys to gather, in the order they are returned.
        generator: the generator given to the buffer (``generator=`` of the buffer); ``None`` = torch's default
            generator, as the buffer uses then.
    """

    def __init__(self, replay_buffer, keys: Sequence[NestedKey], *, generator: torch.Generator | None = None) -> None:
        sampler, storage = replay_buffer._sampler, replay_buffer._storage
        if type(sampler) is not RandomSampler:
            raise AdaRLValueError(
                f"UniformTensorSampler reproduces RandomSampler only, the buffer has {type(sampler).__name__}"
            )
        if not isinstance(storage, TensorStorage) or storage.ndim != 1:
            raise AdaRLValueError(
                f"UniformTensorSampler needs a one-dimensional TensorStorage, the buffer has "
                f"{type(storage).__name__} (ndim {getattr(storage, 'ndim', '?')})"
            )
        if len(replay_buffer._transform) > 0:
            raise AdaRLValueError("UniformTensorSampler cannot apply replay-buffer transforms; sample with rb.sample()")
        if not isinstance(replay_buffer.batch_size, int) or replay_buffer.batch_size < 1:
            raise AdaRLValueError(f"the replay buffer needs an integer batch_size, got {replay_buffer.batch_size!r}")
        self.replay_buffer = replay_buffer
        self.keys = list(keys)
        self.generator = generator
        self._leaves: list[torch.Tensor] | None = None
        self._source = None

    def _tensors(self) -> list[torch.Tensor]:
        data = self.replay_buffer._storage._storage
        if data is not self._source:  # initialised lazily on the first extend (or replaced by a load)
            if data is None:
                raise AdaRLValueError("the replay buffer is empty: extend it before sampling")
            leaves = [data.get(k, None) for k in self.keys]
            missing = [k for k, t in zip(self.keys, leaves) if t is None]
            if missing:
                raise AdaRLValueError(
                    f"replay storage has no key(s) {missing}; it holds {sorted(map(str, data.keys(True, True)))}"
                )
            self._leaves = leaves
            self._source = data
        return self._leaves

    def __call__(self) -> tuple[torch.Tensor, ...]:
        rb = self.replay_buffer
        n = len(rb._storage)
        if n == 0:
            raise AdaRLValueError("the replay buffer is empty: extend it before sampling")
        leaves = self._tensors()
        # exactly RandomSampler.sample -> TensorStorage._rand_given_ndim for ndim == 1
        index = torch.randint(0, n, (rb.batch_size,), generator=self.generator, device=leaves[0].device)
        return tuple(t[index] for t in leaves)
