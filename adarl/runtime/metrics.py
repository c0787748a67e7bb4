"""Metric names, as Stable-Baselines3 (and rl-zoo, and TensorBoard/wandb) users read them: ``<group>/<name>``.

TensorBoard and wandb group scalars by the part before the first ``/`` (TorchRL's ``WandbLogger`` also gives each
group its own step metric, ``rollout/step``, ...), and TorchRL's ``CSVLogger`` writes ``rollout/ep_rew_mean`` to
``metrics/scalars/rollout/ep_rew_mean.csv`` (each file starts with the header row ``step,value``). Every step is
the environment frames collected (SB3's ``time/total_timesteps``).

Where SB3 logs the quantity, the name is SB3's (its SAC, and its PPO for the RNAC baselines' loop):

==============================  ==============================  ========================================================
this name                       SB3's                           what
==============================  ==============================  ========================================================
``rollout/ep_rew_mean``         ``rollout/ep_rew_mean``         mean return of the training episodes ended in a batch
``rollout/ep_len_mean``         ``rollout/ep_len_mean``         their mean length
``time/episodes``               ``time/episodes``               episodes finished so far
``time/fps``                    ``time/fps``                    frames per second of this process
``time/time_elapsed``           ``time/time_elapsed``           wall-clock seconds of training, summed over the run's
                                                                processes (SB3's restarts at each ``learn()``)
``eval/mean_reward``            ``eval/mean_reward``            mean return of the nominal-dynamics evaluation
``eval/std_reward``             ``std_reward``                  its standard deviation (SB3's ``evaluate_policy``)
``eval/mean_ep_length``         ``eval/mean_ep_length``         mean length of its episodes
``train/actor_loss``            ``train/actor_loss``            SAC's actor loss (TorchRL's ``loss_actor``)
``train/critic_loss``           ``train/critic_loss``           SAC's Q loss (``loss_qvalue``)
``train/ent_coef``              ``train/ent_coef``              SAC's temperature (``alpha``)
``train/ent_coef_loss``         ``train/ent_coef_loss``         its loss (``loss_alpha``)
``train/policy_gradient_loss``  ``train/policy_gradient_loss``  PPO's clipped objective (``loss_objective``)
``train/value_loss``            ``train/value_loss``            PPO's value loss (``loss_critic``)
``train/entropy_loss``          ``train/entropy_loss``          PPO's entropy bonus (``loss_entropy``)
``train/approx_kl``             ``train/approx_kl``             PPO's KL estimate (``kl_approx``)
``train/clip_fraction``         ``train/clip_fraction``         PPO's clipped fraction
``train/n_updates``             ``train/n_updates``             optimisation steps so far
``train/learning_rate``         ``train/learning_rate``         the actor's learning rate
==============================  ==============================  ========================================================

Every scalar is also in one wide table, ``metrics/progress.csv`` (SB3's ``progress.csv``: a row per logged step,
``time/total_timesteps`` first), rewritten from these files at every checkpoint and at the end of the run.

Losses are averaged over ``logging.log_interval`` frames; any other loss term keeps TorchRL's name under
``train/`` (``train/entropy``, ``train/loss_parseval``, ...). adarl's own, which SB3 does not have:

=============================  ====================================================================================
``rank/<net>.<layer>``         the rank of a low-rank layer (``rank/actor.layer0``) at every rank event
``rank_error/<net>.<layer>``   the acceptance step's relative output error at the applied rank
``warm_start/frames``          frames a post-event warm start collected (one row per rank event that changed a rank)
``dynamics/<param>``           mean drawn value of a perturbation parameter over the episodes that ended
``time/updates_per_s``         optimisation steps per second of this process
``guards/rollbacks``           rollbacks after non-finite values
=============================  ====================================================================================

Run folders written by earlier adarl versions are still read: :func:`series` falls back to a metric's former
names (:func:`former_names`: the ``train/episode_return`` generation, then the flat dotted ``train.episode_return``
one), and a file without the header row reads the same, so reports, aggregates and progress boards mix old and
new runs.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = [
    "TRAIN_RETURN",
    "TRAIN_LENGTH",
    "TRAIN_EPISODES",
    "TRAIN_UPDATES",
    "TRAIN_LR",
    "EVAL_RETURN",
    "EVAL_RETURN_STD",
    "EVAL_LENGTH",
    "TIME_ELAPSED",
    "WARM_START_FRAMES",
    "FPS",
    "UPDATES_PER_S",
    "ROLLBACKS",
    "LOSS_NAMES",
    "LEGACY_NAMES",
    "CSV_HEADER",
    "train",
    "rank",
    "rank_error",
    "dynamics",
    "former_names",
    "legacy_name",
    "series",
    "csv_paths",
]

TRAIN_RETURN = "rollout/ep_rew_mean"
TRAIN_LENGTH = "rollout/ep_len_mean"
TRAIN_EPISODES = "time/episodes"
TRAIN_UPDATES = "train/n_updates"
TRAIN_LR = "train/learning_rate"
EVAL_RETURN = "eval/mean_reward"
EVAL_RETURN_STD = "eval/std_reward"
EVAL_LENGTH = "eval/mean_ep_length"
TIME_ELAPSED = "time/time_elapsed"
WARM_START_FRAMES = "warm_start/frames"
FPS = "time/fps"
UPDATES_PER_S = "time/updates_per_s"
ROLLBACKS = "guards/rollbacks"

#: the first row of every metric CSV file
CSV_HEADER = "step,value"

#: TorchRL's loss keys -> SB3's names for the same quantity (logged as ``train/<SB3 name>``)
LOSS_NAMES: dict[str, str] = {
    "loss_actor": "actor_loss",
    "loss_qvalue": "critic_loss",
    "alpha": "ent_coef",
    "loss_alpha": "ent_coef_loss",
    "loss_objective": "policy_gradient_loss",
    "loss_critic": "value_loss",
    "loss_entropy": "entropy_loss",
    "kl_approx": "approx_kl",
}

#: the names before SB3's (adarl before issue 31), for the metrics whose name changed
_SLASH_NAMES: dict[str, str] = {
    TRAIN_RETURN: "train/episode_return",
    TRAIN_LENGTH: "train/episode_length",
    TRAIN_EPISODES: "train/episodes",
    TRAIN_UPDATES: "train/updates",
    TRAIN_LR: "train/lr",
    EVAL_RETURN: "eval/return",
    EVAL_RETURN_STD: "eval/return_std",
    **{f"train/{sb3}": f"train/{ours}" for ours, sb3 in LOSS_NAMES.items()},
}

#: flat dotted names (adarl before issue 20) that did not just trade their first "/" for "."
LEGACY_NAMES: dict[str, str] = {
    EVAL_RETURN: "eval.return_mean",
    WARM_START_FRAMES: "rank.warm_start_frames",
}


def former_names(name: str) -> list[str]:
    """The names earlier adarl versions wrote for metric ``name``, newest first
    (``rollout/ep_rew_mean`` -> ``['train/episode_return', 'train.episode_return']``)."""
    slash = _SLASH_NAMES.get(name)
    out = [slash] if slash else []
    out.append(LEGACY_NAMES.get(name) or (slash or name).replace("/", ".", 1))
    return out


def train(name: str) -> str:
    """``train/<name>``, TorchRL's loss keys under SB3's names (``loss_actor`` -> ``train/actor_loss``)."""
    return f"train/{LOSS_NAMES.get(name, name)}"


def rank(layer_name: str) -> str:
    """``rank/actor.layer0``: the metric of a layer's rank (``layer_name`` is its human name)."""
    return f"rank/{layer_name}"


def rank_error(layer_name: str) -> str:
    return f"rank_error/{layer_name}"


def dynamics(param: str) -> str:
    return f"dynamics/{param}"


def legacy_name(name: str) -> str:
    """The name the oldest adarl wrote for the metric ``name`` (``rollout/ep_rew_mean`` -> ``train.episode_return``)."""
    return former_names(name)[-1]


def series(scalars: Mapping[str, list], name: str) -> list:
    """The rows of metric ``name`` in ``scalars`` (as :meth:`adarl.runtime.run_folder.run_dir.RunDir.scalars` returns
    them), or
    of its newest former name for a run folder written by an older adarl; ``[]`` when none was logged."""
    for candidate in (name, *former_names(name)):
        rows = scalars.get(candidate)
        if rows:
            return rows
    return []


def csv_paths(name: str) -> tuple[str, ...]:
    """The CSV file of metric ``name`` relative to a run folder, then its former files (for readers of one file)."""
    return tuple(f"metrics/scalars/{n}.csv" for n in (name, *former_names(name)))
