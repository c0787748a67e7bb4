"""adarl bench: the CLI validates its options and the report/table hold what one measurement produced."""

from __future__ import annotations

import importlib.util

import pytest

from adarl.cli import main
from adarl.experiments.bench import format_table, measure


def test_bench_rejects_bad_options(tmp_path, capsys):
    out = tmp_path / "b.json"
    assert main(["bench", "--repeats", "0", "--output", str(out)]) == 2
    assert "--repeats" in capsys.readouterr().err and not out.exists()
    with pytest.raises(SystemExit):
        main(["bench", "--variants", "nope"])
    assert main(["bench", "--set", "rank.beta=3", "--output", str(out)]) == 2  # checked before measuring
    assert "rank.beta" in capsys.readouterr().err and not out.exists()
    # checked against each width's own recipe: rank 128 fits a 256-wide layer, not a 64-wide one
    assert main(["bench", "--widths", "64", "--set", "network.actor.rank=128", "--output", str(out)]) == 2
    assert "network.actor.rank" in capsys.readouterr().err and not out.exists()


def test_overrides_apply_to_our_loops_only():
    out = measure(
        "adarl_norank",
        "Hopper-v5",
        16,
        warmup=50,
        steps=20,
        skip=5,
        batch=32,
        overrides=("network.actor.rank=3", "network.critic.rank=2"),
    )
    assert out["updates_per_s"] > 0
    from adarl.experiments.bench._update import _recipe

    r = _recipe("Hopper-v5", 16, "adarl", 10, 100, 30, 8, ("network.actor.rank=3",))
    assert r.network.actor.rank == 3


def test_measure_adarl_times_updates_and_rank_events():
    out = measure("adarl", "Hopper-v5", 16, warmup=50, steps=60, skip=10, batch=32, rank_interval=30)
    assert out["updates_per_s"] > 0 and out["env_steps_per_s"] > 0 and out["peak_rss_mb"] > 0
    assert out["rank_events"] >= 1 and all(t > 0 for t in out["rank_event_s"])


@pytest.mark.skipif(importlib.util.find_spec("stable_baselines3") is None, reason="stable-baselines3 not installed")
def test_measure_sb3():
    out = measure("sb3", "Hopper-v5", 16, warmup=50, steps=30, skip=10, batch=32)
    assert out["updates_per_s"] > 0


def test_table_lists_variants_and_ratios():
    v = {"updates_per_s": 100.0, "env_steps_per_s": 100.0, "peak_rss_mb": 400.0, "rank_event_ms": 4.0, "runs": []}
    w = dict(v, updates_per_s=50.0, rank_event_ms=None)
    report = {
        "results": [
            {
                "env": "Hopper-v5",
                "width": 64,
                "variants": {"adarl": v, "torchrl": w},
                "ratios": {"adarl/torchrl": 2.0},
                "rank_overhead_at_paper_interval": 4e-7,
            }
        ],
        "rank_events_standalone": [{"width": 64, "threads": 1, "ms": 3.0}],
        "skipped": ["sb3"],
    }
    table = format_table(report)
    assert "| Hopper-v5 | (64, 64) | adarl | 100.0 |" in table and "2.00x" in table and "sb3" in table
    assert "| 64 | 1 | 3.0 |" in table


def test_measure_compiled_times_each_recompiling_event_after_the_window():
    out = measure("adarl_compiled", "Hopper-v5", 16, warmup=50, steps=30, skip=10, batch=32, rank_interval=30)
    assert out["updates_per_s"] > 0 and out["rank_events"] == 2 and all(t > 0 for t in out["rank_event_s"])
