"""adarl bench: the CLI validates its options and the report/table hold what one measurement produced (the update
window here, and ``--pack``: packed seeds against solo seeds)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import pytest

from adarl.cli import main
from adarl.errors import AdaRLValueError
from adarl.experiments.bench import _packed, _update, format_table, measure


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


# ---------------------------------------------------------------------------------------------- adarl bench --pack
PACK_TINY = ["--seeds", "1", "2", "--widths", "64", "--repeats", "1", "--batch", "32"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seeds", "0", "2"], "--seeds must be distinct seed counts >= 1"),
        (["--seeds", "2", "2"], "--seeds must be distinct seed counts >= 1"),
        (["--variants", "torchrl"], "--pack packs the adarl variant only"),
        (["--frames", "600"], "--pack does not take --frames; it takes --envs, --widths"),
        (["--whole-run", "--steps", "3"], "--pack --whole-run does not take --steps"),
        (["--event-widths", "8"], "--pack does not take --event-widths"),
        (["--steps", "0"], "--steps must be >= 1"),
        (["--whole-run", "--frames", "600", "--warmup", "600"], "--warmup (600) must be >= 0 and below --frames"),
        (["--whole-run", "--pack-threads", "0"], "--pack-threads must be >= 1"),
        (["--set", "algorithm.fused=false"], "cannot be packed: LossStep"),
    ],
)
def test_pack_refuses_bad_options_naming_what_it_takes(tmp_path, capsys, args, message):
    out = tmp_path / "p.json"
    assert main(["bench", "--pack", *args, "--output", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("adarl: error:") and message in err, err
    assert not out.exists()


def test_pack_options_need_pack(capsys):
    assert main(["bench", "--seeds", "2", "--no-two-packs"]) == 2
    assert "only --pack takes --seeds, --no-two-packs" in capsys.readouterr().err
    with pytest.raises(AdaRLValueError, match="adarl bench --pack"):  # python -m adarl.experiments.bench
        _update.main(["--pack"])


def test_a_tiny_pack_window_reports_every_row_it_promised(tmp_path):
    """`adarl bench --pack`, the update window, end to end in a subprocess: a row per (width, N), the table printed
    and written, each per seed-update time next to the floor (structure only: no timing is asserted)."""
    out, md = tmp_path / "p.json", tmp_path / "p.md"
    argv = ["bench", "--pack", *PACK_TINY, "--steps", "2", "--skip", "1", "--warmup", "100"]
    proc = subprocess.run(
        [sys.executable, "-m", "adarl.cli", *argv, "--output", str(out), "--markdown", str(md), "--quiet"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["mode"] == "pack" and report["command"].startswith("adarl bench --pack --seeds 1 2")
    assert report["floor"]["step_ms"] == 1.3 and report["settings"]["steps"] == 2
    assert [(r["env"], r["width"], r["seeds"]) for r in report["rows"]] == [("Hopper-v5", 64, 1), ("Hopper-v5", 64, 2)]
    for r in report["rows"]:
        assert r["floor_ms"] == 1.0 and len(r["solo_windows_s"]) == len(r["packed_windows_s"]) == 1
        assert r["solo_ms_per_seed_update"] > 0 and r["packed_ms_per_seed_update"] > 0
        assert r["ratio_packed_over_solo"] == pytest.approx(r["solo_windows_s"][0] / r["packed_windows_s"][0])
    table = md.read_text().strip()
    assert table in proc.stdout and table.startswith(f"Command: `{report['command']}`")
    assert "| solo ms / seed-update | packed ms / seed-update | update floor (ms) |" in table
    for n in (1, 2):
        assert f"| Hopper-v5 | (64, 64) | {n} | " in table


def test_pack_whole_run_times_every_layout_side_by_side(tmp_path, capsys, monkeypatch):
    """--whole-run's layouts with stand-in runs (a process that writes each run folder's summary.json): the commands
    it would start, a row per (N, layout) with its ratio to the solo runs and the floor, the table."""
    started = []

    def stand_in(a, env_id, width, threads, seeds, out):
        cmd, threads = real(a, env_id, width, threads, seeds, out)
        started.append(cmd)
        folders = [out] if isinstance(seeds, int) else [out / f"seed={s}" for s in seeds]
        code = (
            "import pathlib, sys\nfor f in sys.argv[1:]: (pathlib.Path(f) / 'summary.json').parent.mkdir(parents=True)"
        )
        code += "\nfor f in sys.argv[1:]: (pathlib.Path(f) / 'summary.json').write_text('{}')"
        return [sys.executable, "-c", code, *map(str, folders)], threads

    real = _packed._adarl_run
    monkeypatch.setattr(_packed, "_adarl_run", stand_in)
    monkeypatch.setattr(_packed, "pack_refusal", lambda recipe: None)
    out = tmp_path / "w.json"
    argv = ["bench", "--pack", "--whole-run", *PACK_TINY, "--frames", "600", "--frames-per-batch", "100"]
    assert main([*argv, "--pack-threads", "1", "2", "--output", str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    packed1, packed2 = "packed, 1 thread(s)", "packed, 2 thread(s)"
    assert [(r["seeds"], r["variant"]) for r in report["rows"]] == [
        (1, _packed.SOLO),
        (1, packed1),
        (1, packed2),
        (2, _packed.SOLO),
        (2, packed1),
        (2, packed2),
        (2, _packed.TWO_PACKS),
    ]
    for r in report["rows"]:
        assert r["floor_ms"] == 1.3 and r["wall_s"] > 0 and len(r["walls_s"]) == 1
        assert r["aggregate_frames_per_s"] == pytest.approx(r["seeds"] * 600 / r["wall_s"])
        assert r["ms_per_seed_step"] == pytest.approx(1e3 / r["aggregate_frames_per_s"])
    assert all(r["vs_solo"] == 1.0 for r in report["rows"] if r["variant"] == _packed.SOLO)
    assert report["mode"] == "pack-whole-run" and report["settings"]["warmup"] == 100  # --frames // 6
    assert "collector.init_random_frames=100" in report["overrides"]["Hopper-v5 (64, 64)"]
    solo = [c for c in started if "--pack-seeds" not in c]
    packs = [c[c.index("--pack-seeds") + 1 : c.index("-o")] for c in started if "--pack-seeds" in c]
    assert sorted(c[c.index("-o") - 1] for c in solo) == ["seed=0", "seed=0", "seed=1"]
    assert packs == [["0"], ["0"], ["0", "1"], ["0", "1"], ["0"], ["1"]]
    threads = [[x for x in c if x.startswith("algorithm.num_threads=")] for c in started]
    assert threads == [[f"algorithm.num_threads={t}"] for t in (1, 1, 2, 1, 1, 1, 2, 1, 1)]
    table = capsys.readouterr().out
    assert "| Hopper-v5 | (64, 64) | 2 | 2 packs of N/2 side by side |" in table and "| 1.30 |" in table


@pytest.mark.slow
def test_a_tiny_packed_whole_run_end_to_end(tmp_path):
    """Real `adarl run` processes: two seeds solo, two at a time, against one pack of two (~1 min of CPU)."""
    out = tmp_path / "w.json"
    argv = ["bench", "--pack", "--whole-run", "--seeds", "2", "--no-two-packs", "--widths", "16", "--repeats", "1"]
    argv += ["--batch", "32", "--frames", "600", "--frames-per-batch", "100", "--output", str(out), "--quiet"]
    proc = subprocess.run([sys.executable, "-m", "adarl.cli", *argv], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(out.read_text())
    assert [r["variant"] for r in report["rows"]] == [_packed.SOLO, "packed, 1 thread(s)"]
    assert all(r["floor_ms"] is None and r["wall_s"] > 0 for r in report["rows"])  # no floor estimated at (16, 16)
    assert "| Hopper-v5 | (16, 16) | 2 | packed, 1 thread(s) |" in proc.stdout
