"""rank.num_threads: 'auto' gives a rank event every core this process may use, or a launcher's share of them."""

from __future__ import annotations

import os

import pytest
import torch
from _helpers import tiny

from adarl import build_sac_components, load_recipe
from adarl.errors import AdaRLValueError
from adarl.runtime.builders import build_ppo_components
from adarl.runtime.builders.sac import event_threads

TINY = tiny(
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "replay.size=600",
    "replay.warm_start.frames=50",
    drop=(
        "rank.interval",
        "lr_schedule.warmup_steps",
        "eval.interval",
        "eval.episodes",
        "eval.max_steps",
        "checkpoint.interval",
    ),
)


def test_auto_is_the_launchers_share_or_every_core():
    cores = len(os.sched_getaffinity(0))
    assert event_threads("auto", {}) == cores
    assert event_threads("auto", {"OMP_NUM_THREADS": "1"}) == 1  # adarl experiment -j N > 1
    assert event_threads("auto", {"OMP_NUM_THREADS": "4"}) == 4  # Ray / SLURM cpus_per_run
    assert event_threads("auto", {"OMP_NUM_THREADS": "junk"}) == cores
    assert event_threads(3) == 3 and event_threads(None) is None


@pytest.mark.parametrize("omp, expected", [(None, "cores"), ("1", 1)])
def test_the_recipe_default_reaches_the_adapter(monkeypatch, omp, expected):
    if omp is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", omp)
    recipe = load_recipe("quickstart", TINY)
    assert recipe.rank.num_threads == "auto"
    c = build_sac_components(recipe)
    try:
        want = len(os.sched_getaffinity(0)) if expected == "cores" else expected
        assert c.adapter.num_threads == want
    finally:
        c.close()
    c = build_sac_components(load_recipe("quickstart", [*TINY, "rank.num_threads=null"]))
    try:
        assert c.adapter.num_threads is None
    finally:
        c.close()


@pytest.mark.parametrize(
    "name, build", [("quickstart", build_sac_components), ("baselines/hopper_rnac_ipm", build_ppo_components)]
)
def test_algorithm_num_threads_is_applied_by_every_builder(name, build):
    """algorithm.num_threads (base.yaml: 1) is the training loop's torch thread count for SAC and the PPO loop alike
    (the PPO builder once ignored it: two RNAC runs side by side on two cores then fought over four threads)."""
    torch.set_num_threads(1)
    try:
        c = build(load_recipe(name, ["algorithm.num_threads=2"]))
        c.close()
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)


def test_build_components_refuses_a_ppo_recipe_by_name():
    """The SAC builder on an RNAC recipe names the builder to use (it once failed deep inside, on a missing critic)."""
    with pytest.raises(AdaRLValueError, match="rnac_ipm.*'ppo' loop.*build_ppo_components"):
        build_sac_components(load_recipe("baselines/hopper_rnac_ipm"))
