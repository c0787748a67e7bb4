"""Metric names, as TorchRL and Stable-Baselines3 users read them: ``<group>/<name>``.

TensorBoard and wandb group scalars by the part before the first ``/`` (TorchRL's ``WandbLogger`` also gives each
group its own step metric, ``train/step``, ...), and TorchRL's ``CSVLogger`` writes ``train/episode_return`` to
``metrics/scalars/train/episode_return.csv``. Every step is the environment frames collected.

=========================  =====================================================================================
``train/episode_return``   mean return of the training episodes that ended in a batch (perturbed dynamics)
``train/episode_length``   their mean length
``train/episodes``         episodes finished so far
``train/<loss>``           losses (``loss_actor``, ``loss_qvalue``, ...) averaged over ``logging.log_interval``
``train/updates``          optimisation steps so far; ``train/lr``: the actor's learning rate
``eval/return``            mean return of the nominal-dynamics evaluation; ``eval/return_std`` its std
``rank/<net>.<layer>``     the rank of a low-rank layer (``rank/actor.layer0``) at every rank event
``rank_error/<net>.<layer>``  the acceptance step's relative output error at the applied rank
``warm_start/frames``      frames a post-event warm start collected (one row per rank event that changed a rank)
``dynamics/<param>``       mean drawn value of a perturbation parameter over the episodes that ended
``time/fps``               frames per second of this process (collection and updates); ``time/updates_per_s``
``guards/rollbacks``       rollbacks after non-finite values
=========================  =====================================================================================

Run folders written before these names (``train.episode_return``, ``eval.return_mean``,
``rank.warm_start_frames``, ``rank.<module path>``, ...) are still read: :func:`series` falls back to the old
name, so reports, aggregates and progress boards mix old and new runs.
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
    "WARM_START_FRAMES",
    "FPS",
    "UPDATES_PER_S",
    "ROLLBACKS",
    "LEGACY_NAMES",
    "train",
    "rank",
    "rank_error",
    "dynamics",
    "legacy_name",
    "series",
    "csv_paths",
]

TRAIN_RETURN = "train/episode_return"
TRAIN_LENGTH = "train/episode_length"
TRAIN_EPISODES = "train/episodes"
TRAIN_UPDATES = "train/updates"
TRAIN_LR = "train/lr"
EVAL_RETURN = "eval/return"
EVAL_RETURN_STD = "eval/return_std"
WARM_START_FRAMES = "warm_start/frames"
FPS = "time/fps"
UPDATES_PER_S = "time/updates_per_s"
ROLLBACKS = "guards/rollbacks"

#: names that did not just trade their first "." for "/" (the rest did: ``train.loss_actor``, ``dynamics.<p>``)
LEGACY_NAMES: dict[str, str] = {
    EVAL_RETURN: "eval.return_mean",
    WARM_START_FRAMES: "rank.warm_start_frames",
}


def train(name: str) -> str:
    return f"train/{name}"


def rank(layer_name: str) -> str:
    """``rank/actor.layer0``: the metric of a layer's rank (``layer_name`` is its human name)."""
    return f"rank/{layer_name}"


def rank_error(layer_name: str) -> str:
    return f"rank_error/{layer_name}"


def dynamics(param: str) -> str:
    return f"dynamics/{param}"


def legacy_name(name: str) -> str:
    """The name an older adarl wrote for the metric ``name`` (``train/episode_return`` -> ``train.episode_return``)."""
    return LEGACY_NAMES.get(name, name.replace("/", ".", 1))


def series(scalars: Mapping[str, list], name: str) -> list:
    """The rows of metric ``name`` in ``scalars`` (as :meth:`adarl.runtime.run_dir.RunDir.scalars` returns them), or of
    its
    legacy name for a run folder written by an older adarl; ``[]`` when neither was logged."""
    rows = scalars.get(name)
    if rows:
        return rows
    return scalars.get(legacy_name(name)) or []


def csv_paths(name: str) -> tuple[str, str]:
    """The CSV file of metric ``name`` relative to a run folder, then its legacy file (for readers of one file)."""
    return f"metrics/scalars/{name}.csv", f"metrics/scalars/{legacy_name(name)}.csv"
