"""The trainers: one loop per kind of loop, on one base that owns everything else.

* :mod:`~adarl.runtime.trainers.base` - :class:`BaseTrainer`: the run folder, logging, evaluation and checkpoint
  cadence, divergence guards, signals, exact resume, summary and report; :func:`trainer_class` (the recipe's loop's
  trainer, :mod:`adarl.runtime.families`);
* :mod:`~adarl.runtime.trainers.off_policy` - :class:`OffPolicyTrainer`: every off-policy family (AdaRL-SAC and the
  SAC baselines, TD3, DDPG, a family of your own), its components built by ``family(recipe).build(...)``;
* :mod:`~adarl.runtime.trainers.ppo` - :class:`PPOTrainer`: the RNAC baselines' PPO loop;
* :mod:`~adarl.runtime.trainers.packed` - :class:`~adarl.runtime.trainers.packed.SeedPack`: seeds of one SAC recipe
  side by side in one process, their updates batched (``adarl run --pack-seeds``).
"""

from adarl.runtime.trainers.base import BaseTrainer, trainer_class
from adarl.runtime.trainers.off_policy import OffPolicyTrainer
from adarl.runtime.trainers.ppo import PPOTrainer

__all__ = ["BaseTrainer", "OffPolicyTrainer", "PPOTrainer", "trainer_class"]
