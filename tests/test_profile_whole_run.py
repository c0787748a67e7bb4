"""benchmarks/profile_whole_run.py files py-spy's samples under the phases of a whole run (the first match wins)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "profile_whole_run.py"


@pytest.fixture(scope="module")
def prof():
    spec = importlib.util.spec_from_file_location("profile_whole_run", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _line(*frames, count):
    return ";".join(f"{f} (adarl/x.py:1)" for f in frames) + f" {count}"


def test_samples_go_to_the_first_matching_phase(prof):
    raw = "\n".join(
        [
            _line("main", "BaseTrainer.train", "BaseTrainer._train_batches", "Trainer._update", count=300),
            _line("main", "BaseTrainer._train_batches", "LeanCollector.__iter__", count=100),
            # the warm start runs inside the rank event: it is its own phase, not the event's
            _line("main", "Trainer._update", "RankAdapter.step", "ReplayWarmStart.__call__", count=50),
            _line("main", "Trainer._update", "RankAdapter.step", "torch.linalg.svd", count=20),
            _line("main", "BaseTrainer._train_batches", "BaseTrainer._evaluate", "episode_runner", count=30),
            _line("<module>", "_find_and_load", count=400),
            _line("<module>", "parse_args", count=7),
            _line("Thread._bootstrap", "Thread._bootstrap_inner", "TMonitor.run", "Event.wait", count=90),  # tqdm's
            " 40",  # no Python frame
            "",
        ]
    )
    got = prof.classify(raw)
    assert got == {
        "updates": 3.0,
        "collection (env steps, policy, replay writes)": 1.0,
        "warm start after a rank event": 0.5,
        "rank event (SVD, re-factorisation, optimiser reset)": 0.2,
        "evaluation": 0.3,
        "imports": 4.0,
        prof.OTHER: 0.07,
    }
    table = prof.format_table([{"env": "Hopper-v5", "width": 64, "variant": "adarl", "wall_s": 9.9, "phases": got}])
    assert "| updates | 3.0 |" in table and "| wall time under py-spy | 9.9 |" in table
