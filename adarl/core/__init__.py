"""The paper's components, as TorchRL pieces: they depend on torch, TorchRL and tensordict, and of adarl on
:mod:`adarl.errors` and :mod:`adarl.plugins` only (:mod:`~adarl.core.rank` finds rank rules by name there).

* :mod:`~adarl.core.lowrank` - :class:`~adarl.core.lowrank.LowRankLinear` (``W = W1 @ W2``), the low-rank MLP,
  factor SVDs;
* :mod:`~adarl.core.rank` - rank rules (paper Eq. 10, Eq. 33, fixed, the Eq. 8 policy fit);
* :mod:`~adarl.core.acceptance` - Algorithm 1's acceptance step (``r_new = r_old`` unless the truncated network
  still fits);
* :mod:`~adarl.core.adapter` - :class:`~adarl.core.adapter.RankAdapter`, Algorithm 1's rank-adaptation step on any
  TorchRL loss;
* :mod:`~adarl.core.lr_schedule` - the restartable warm-up + cosine learning-rate schedule;
* :mod:`~adarl.core.warmstart` - the warm-start replay buffer after a truncation;
* :mod:`~adarl.core.collector_rebuild` - a collector rebuilt after each rank event (process collectors);
* :mod:`~adarl.core.ensemble` - a TorchRL Q ensemble's low-rank members drawn with their own init;
* :mod:`~adarl.core.product_polyak` - Polyak averaging of a factorised layer's product (``algorithm.polyak: product``);
* :mod:`~adarl.core.restarts` - a rank event's restarts without its truncation (the control of the restarts);
* :mod:`~adarl.core.target_shift` - a ``SACLoss`` with a shifted TD target (RNAC-IPM's robust SAC).
"""
