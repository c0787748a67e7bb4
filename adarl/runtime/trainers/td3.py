"""TD3 (and DDPG) end to end: :class:`TD3Trainer` runs a recipe on the ``td3`` loop in a run folder.

It is :class:`~adarl.runtime.trainers.sac.SACTrainer`'s loop (the replay buffer's update-to-data cadence, the rank
adapter after each update, warm starts, exact resume, divergence guards) with the ``td3`` family's components
(:func:`~adarl.runtime.builders.td3.build_td3_components`): its update step updates the actor and the targets every
``algorithm.td3.policy_update_delay``-th step (:class:`~adarl.runtime.update.DelayedActorStep`).
"""

from __future__ import annotations

from adarl.runtime.builders.td3 import TD3Components, build_td3_components
from adarl.runtime.trainers.sac import SACTrainer

__all__ = ["TD3Trainer"]


class TD3Trainer(SACTrainer, algorithm="td3"):
    """Runs a recipe on the ``td3`` loop (``algorithm.name: td3``, ``ddpg``, or a plugin's TD3Loss / DDPGLoss) in one
    run folder: train, adapt ranks, evaluate the deterministic actor on nominal dynamics, checkpoint, report.

    ``TD3Trainer(recipe, run_dir).train()`` for a new run; ``BaseTrainer.resume(run_dir).train()`` continues one."""

    def _build_components(self, state: dict | None) -> TD3Components:
        init_random = None
        if state is not None and state.get("collector") is None:
            init_random = max(0, self.recipe.collector.init_random_frames - int(state["counters"]["frames"]))
        return build_td3_components(
            self.recipe,
            init_random_frames=init_random,
            scratch_dir=None if self.read_only else self.run_dir.path / "replay_storage",
        )
