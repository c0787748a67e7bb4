"""The trainers: one loop per kind of loop, on one base that owns everything else.

* :mod:`~adarl.runtime.trainers.base` - :class:`BaseTrainer`: the run folder, logging, evaluation and checkpoint
  cadence, divergence guards, signals, exact resume, summary and report; :func:`trainer_class` (the recipe's loop's
  trainer, :mod:`adarl.runtime.families`); what a checkpoint holds, written and loaded, in its private mixin
  :mod:`~adarl.runtime.trainers._checkpointing`;
* :mod:`~adarl.runtime.trainers.off_policy` - :class:`OffPolicyTrainer`: every off-policy family (AdaRL-SAC and the
  SAC baselines, TD3, DDPG, a family of your own), its components built by ``family(recipe).build(...)``;
* :mod:`~adarl.runtime.trainers.ppo` - :class:`PPOTrainer`: the RNAC baselines' PPO loop;
* :mod:`~adarl.runtime.trainers.packed` - :class:`~adarl.runtime.trainers.packed.SeedPack`: seeds of one SAC recipe
  side by side in one process, their updates batched (``adarl run --pack-seeds``).

Each name is imported on first use (PEP 562): the trainers import torch and TorchRL (seconds), and a module of this
package that needs neither (:mod:`~adarl.runtime.trainers.pack_folder`'s reading of a pack folder) or a command
refused before it trains must not pay for them.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from adarl.runtime.trainers.base import BaseTrainer, trainer_class
    from adarl.runtime.trainers.off_policy import OffPolicyTrainer
    from adarl.runtime.trainers.ppo import PPOTrainer

__all__ = ["BaseTrainer", "OffPolicyTrainer", "PPOTrainer", "trainer_class"]

_HOME = {"BaseTrainer": "base", "trainer_class": "base", "OffPolicyTrainer": "off_policy", "PPOTrainer": "ppo"}


def __getattr__(name: str):
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_HOME])
