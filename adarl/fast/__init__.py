"""The optional speed engine: the same numbers as TorchRL's pieces, with less Python per frame and per update.

Each module names the TorchRL piece it mirrors and the test that proves the two equal:

* :mod:`adarl.fast.sac` - :class:`~adarl.fast.sac.FusedSACUpdate`: ``SACLoss`` + backward + optimisers +
  ``SoftUpdate`` on plain tensors (refuses, by name, the loss settings it does not implement);
* :mod:`adarl.fast.manual_backward` - the fused step's gradients written out by hand;
* :mod:`adarl.fast.kernels` - the affine map and fresh-code ``torch.compile`` the two share;
* :mod:`adarl.fast.adam` - fused Adam's ``step()`` without its per-call Python;
* :mod:`adarl.fast.packed` - :class:`~adarl.fast.packed.PackedSACUpdate`: N seeds' fused updates as one batched step;
* :mod:`adarl.fast.replay` - :class:`~adarl.fast.replay.UniformTensorSampler`: ``rb.sample()`` into tensors;
* :mod:`adarl.fast.collector` - :class:`~adarl.fast.collector.LeanCollector`: TorchRL's ``Collector`` for one env;
* :mod:`adarl.fast.direct_env` - a ``make_env`` env's ``step_and_maybe_reset`` without TorchRL's wrapper;
* :mod:`adarl.fast.evaluation` - a deterministic SAC episode: ``env.rollout(n, actor, break_when_any_done=True)``;
* :mod:`adarl.fast._torch_private` - every torch-private call above, behind one version guard: on a torch it was
  not tested on, each caller takes its public path (``Adam.step()``, autograd, ...) after a one-line warning.

Recipes turn it on with ``algorithm.fused`` and ``collector.lean`` (``'auto'``: wherever it applies); switched
off, a run uses TorchRL's own pieces. Evaluation takes the fast path wherever it reproduces ``env.rollout``
exactly (a SAC actor on a ``make_env`` env), in every run. Nothing here depends on the recipe runtime.
"""
