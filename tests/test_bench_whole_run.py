"""adarl bench --whole-run: options are checked before anything runs, the overrides give every variant the same
frames, updates and evaluations, and a tiny invocation writes the JSON report and the markdown table."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from types import SimpleNamespace

import pytest

from adarl.cli import main
from adarl.experiments.bench import _whole_run as wr

TINY = [
    "bench",
    "--whole-run",
    "--frames",
    "600",
    "--warmup",
    "200",
    "--frames-per-batch",
    "100",
    "--widths",
    "16",
    "--batch",
    "64",
    "--eval-interval",
    "300",
    "--eval-episodes",
    "1",
    "--repeats",
    "1",
]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--frames", "0"], "--frames must be >= 1"),
        (["--warmup", "600"], "--warmup (600) must be below --frames"),
        (["--frames", "650"], "must be a multiple of --frames-per-batch"),
        (["--eval-interval", "250"], "must be a multiple of --frames-per-batch"),
        (["--widths", "16", "0"], "--widths must be >= 1"),
        (["--variants", "adarl", "adarl_compiled"], "adarl_compiled"),
        (["--repeats", "0"], "--repeats must be >= 1"),
        (["--rank-events", "500"], "too few for --rank-events 500"),
        (["--event-threads", "many"], "--event-threads must be 'auto' or an integer"),
        (["--inference", "--inference-rank", "32"], "--inference-rank (32)"),
        (["--set", "rank.beta=3"], "rank.beta"),
        (["--envs", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
    ],
)
def test_bad_options_are_clear_errors_before_anything_runs(tmp_path, capsys, args, message):
    out = tmp_path / "w.json"
    assert main([*TINY, *args, "--output", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("adarl: error:") and message in err, err
    assert not out.exists()


def test_unknown_variant_is_refused_by_the_parser():
    with pytest.raises(SystemExit):
        main([*TINY, "--variants", "nope"])


def test_rank_interval_gives_exactly_the_events_asked_for():
    for updates in (400, 7000, 7001, 100_000):
        for events in (1, 3, 5):
            interval = wr.rank_interval(updates, events)
            assert interval * events <= updates < interval * (events + 1), (updates, events)


def _args(**kw):
    base = dict(
        frames=600,
        warmup=200,
        frames_per_batch=100,
        batch=64,
        threads=1,
        eval_interval=300,
        eval_episodes=1,
        rank_events=3,
        event_threads=4,
        set=["network.actor.rank=5"],
    )
    return SimpleNamespace(**{**base, **kw})


def test_overrides_give_every_variant_the_same_budget():
    a = _args()
    ov = {v: wr.adarl_overrides(a, "Hopper-v5", 16, v) for v in ("adarl", "adarl_norank", "torchrl")}
    shared = [
        "collector.total_frames=600",
        "collector.init_random_frames=200",
        "algorithm.update_after=201",
        "algorithm.batch_size=64",
        "algorithm.num_threads=1",
        "network.actor.num_cells=[16,16]",
        "network.critic.num_cells=[16,16]",
        "replay.warm_start.count_frames=false",
        "eval.interval=300",
        "eval.episodes=1",
    ]
    for v, o in ov.items():
        assert all(s in o for s in shared), v
    assert "rank.interval=101" in ov["adarl"] and "rank.num_threads=4" in ov["adarl"]
    assert "rank.enabled=false" in ov["adarl_norank"] and "rank.enabled=false" in ov["torchrl"]
    assert {"algorithm.fused=false", "collector.lean=false", "network.actor.low_rank_layers=[]"} <= set(ov["torchrl"])
    # --set is for our loops only
    assert ov["adarl"][-1] == ov["adarl_norank"][-1] == "network.actor.rank=5"
    assert "network.actor.rank=5" not in ov["torchrl"]


def test_the_driver_imports_neither_torch_nor_torchrl():
    code = (
        "import sys; import adarl.cli, adarl.experiments.bench._whole_run; "
        "print(sorted(m for m in ('torch', 'torchrl', 'stable_baselines3') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def _report(**kw) -> dict:
    v = {
        "wall_s": 20.0,
        "loop_s": 15.0,
        "cpu_s": 21.0,
        "peak_rss_mb": 500.0,
        "updates": 7000,
        "env_frames": 18000,
        "eval_episodes": 9,
        "rank_events": 3,
        "final_ranks": {"actor.layer0": 11},
    }
    s = dict(v, wall_s=30.0, loop_s=25.0, env_frames=12000, rank_events=0, final_ranks={})
    report = {
        "command": "adarl bench --whole-run --widths 64",
        "recipe": "quickstart",
        "rank_interval": 1751,
        "settings": {
            "frames": 12000,
            "warmup": 5000,
            "batch": 256,
            "threads": 1,
            "eval_interval": 4000,
            "eval_episodes": 3,
            "event_threads": 2,
            "repeats": 3,
        },
        "machine": {"date": "2026-11-24 04:00", "cpus": 2, "load_avg_before": (0.1, 0, 0), "load_avg_after": (1, 0, 0)},
        "results": [
            {
                "env": "Hopper-v5",
                "width": 64,
                "variants": {"adarl": v, "sb3": s},
                "ratios": {"sb3/adarl": 1.5},
            }
        ],
        "inference": [],
        "skipped": [],
    }
    report.update(kw)
    return report


def test_table_has_the_command_rows_ratios_and_notes():
    table = wr.format_whole_run_table(_report())
    assert table.startswith("Command: `adarl bench --whole-run --widths 64`")
    assert (
        "| Hopper-v5 | (64, 64) | adarl | 20.0 | 15.0 | 21.0 | 7000 | 18000 | 9 | 3 | actor.layer0=11 | 500 |" in table
    )
    assert "| Hopper-v5 | (64, 64) | sb3 / adarl | 1.50x |" in table
    assert "note:" not in table and wr.SB3_NOTE not in table
    latency = {
        "env": "Hopper-v5",
        "width": 64,
        "actor": "low-rank, rank <= 7",
        "ranks": "7/7",
        "parameters": 1000,
        "act_us": 250.0,
        "network_us": 30.0,
    }
    table = wr.format_whole_run_table(_report(skipped=["sb3"], inference=[latency]))
    assert "| Hopper-v5 | (64, 64) | low-rank, rank <= 7 | 7/7 | 1000 | 250.0 | 30.0 |" in table
    assert table.endswith(wr.SB3_NOTE)
    report = _report()
    report["results"][0]["variants"]["sb3"]["updates"] = 6999
    assert "note: the variants took different numbers of updates" in wr.format_whole_run_table(report)


@pytest.mark.slow
def test_a_tiny_whole_run_writes_the_report_and_table(tmp_path, capsys, monkeypatch):
    """adarl and adarl_norank end to end at a tiny size; sb3 asked for but (made) absent: skipped with a note."""
    monkeypatch.setattr(wr, "_sb3_available", lambda: False)
    out, md = tmp_path / "w.json", tmp_path / "w.md"
    argv = [*TINY, "--variants", "adarl", "adarl_norank", "sb3", "--set", "replay.warm_start.frames=100"]
    argv += ["--inference", "--inference-calls", "20", "--output", str(out), "--markdown", str(md), "--quiet"]
    assert main(argv) == 0
    printed = capsys.readouterr()
    report = json.loads(out.read_text())
    assert report["mode"] == "whole-run" and report["skipped"] == ["sb3"] and report["rank_interval"] == 101
    (row,) = report["results"]
    assert row["env"] == "Hopper-v5" and row["width"] == 16 and set(row["variants"]) == {"adarl", "adarl_norank"}
    for name, d in row["variants"].items():
        assert d["wall_s"] > d["loop_s"] > 0 and d["cpu_s"] > 0 and d["peak_rss_mb"] > 0, name
        assert d["updates"] == 400 and d["frames"] == 600 and d["evals"] == 2 and d["eval_episodes"] == 2, name
        assert len(d["runs"]) == 1 and d["runs"][0]["command"].startswith("python -m adarl.cli run quickstart")
    assert row["variants"]["adarl"]["rank_events"] >= 1 and row["variants"]["adarl_norank"]["rank_events"] == 0
    assert row["variants"]["adarl"]["warm_start_frames"] > 0
    assert set(row["ratios"]) == {"adarl_norank/adarl"}
    assert {r["actor"] for r in report["inference"]} == {
        "dense (nn.Linear)",
        "low-rank, full rank",
        "low-rank, rank <= 7",
    }
    assert all(r["act_us"] > 0 and r["network_us"] > 0 for r in report["inference"])
    table = md.read_text().strip()
    assert table in printed.out and table.startswith(f"Command: `{report['command']}`")
    assert "--whole-run" in report["command"] and "| Hopper-v5 | (16, 16) | adarl |" in table
    assert wr.SB3_NOTE in printed.out and wr.SB3_NOTE in printed.err


@pytest.mark.skipif(importlib.util.find_spec("stable_baselines3") is None, reason="stable-baselines3 not installed")
def test_sb3_whole_run_takes_the_same_updates_and_evaluations():
    from adarl.experiments.bench import whole_run_sb3

    out = whole_run_sb3(
        "Hopper-v5", 16, frames=600, warmup=200, batch=64, threads=1, eval_interval=250, eval_episodes=1
    )
    # evaluations at 250 and 500 frames, and once more at the end (600), as adarl's trainer does
    assert out["frames"] == 600 and out["updates"] == 400 and out["evals"] == 3 and out["eval_episodes"] == 3
