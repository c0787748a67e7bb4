"""The trainers: one loop per algorithm on one base that owns everything else.

* :mod:`~adarl.runtime.trainers.base` - :class:`BaseTrainer`: the run folder, logging, evaluation and checkpoint
  cadence, divergence guards, signals, exact resume, summary and report; :func:`trainer_class` (the recipe's loop's
  trainer, :mod:`adarl.runtime.families`);
* :mod:`~adarl.runtime.trainers.sac` - :class:`SACTrainer` (alias ``Trainer``): AdaRL-SAC and the SAC baselines;
* :mod:`~adarl.runtime.trainers.ppo` - :class:`PPOTrainer`: the RNAC baselines' PPO loop;
* :mod:`~adarl.runtime.trainers.td3` - :class:`TD3Trainer`: TD3 and DDPG (SAC's loop with TD3's components).
"""

from adarl.runtime.trainers.base import BaseTrainer, trainer_class
from adarl.runtime.trainers.ppo import PPOTrainer
from adarl.runtime.trainers.sac import SACTrainer, Trainer
from adarl.runtime.trainers.td3 import TD3Trainer

__all__ = ["BaseTrainer", "SACTrainer", "Trainer", "PPOTrainer", "TD3Trainer", "trainer_class"]
