"""Callbacks in recipe runs (issue 48.5): ``stop_on_return`` ends a run early with the record; a user callback from
a recipe's local plugin module is called at its hook points and its state survives a resume from a checkpoint; a
stopped run resumed is complete, and trains on once its callbacks are dropped; an unknown callback name or a bad
option is refused by name with exit 2 and no run folder."""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from _helpers import tiny

from adarl import plugins
from adarl.cli import main
from adarl.experiments.execute import run_is_finished
from adarl.runtime.config import local_plugins
from adarl.runtime.trainers import BaseTrainer

#: counts every hook point it is called at; its counts are its checkpointed state
MODULE = '''
"""A callback that counts its hook points, registered at import."""
from pydantic import BaseModel, ConfigDict, Field

from adarl import Callback, register_callback


class CountOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    label: str = Field("n", min_length=1)


@register_callback("count_hooks", options=CountOptions)
class CountHooks(Callback):
    def __init__(self, label="n"):
        self.label = label
        self.counts = {"post_optim": 0, "post_steps": 0, "post_eval": 0, "post_rank_event": 0}
        self.frames = []

    def post_optim(self, losses):
        assert losses.batch_size == () and len(losses.keys()) > 0
        self.counts["post_optim"] += 1

    def post_steps(self, batch):
        self.counts["post_steps"] += 1
        self.frames.append(int(self.trainer.frames))

    def post_eval(self, result):
        assert set(result) >= {"frames", "updates", "eval/mean_reward"}
        self.counts["post_eval"] += 1

    def post_rank_event(self, event):
        self.counts["post_rank_event"] += 1

    def state_dict(self):
        return {"counts": dict(self.counts), "frames": list(self.frames)}

    def load_state_dict(self, state):
        self.counts, self.frames = dict(state["counts"]), list(state["frames"])
'''

RECIPE = """
extends: quickstart
plugins: [my_callbacks]
callbacks:
  - {name: count_hooks, options: {label: a}}
"""

CKPT = "ckpt-{:012d}.pt"
STOP = "callbacks=[{name: stop_on_return, options: {threshold: -1.0e9, min_frames: 300}}]"


@pytest.fixture(autouse=True)
def _undone(monkeypatch):
    """The local module's registration and import are undone after each test."""
    monkeypatch.setattr(plugins._callback, "_callbacks", dict(plugins._callback._callbacks))
    monkeypatch.setattr(local_plugins, "_IMPORTED", {})
    monkeypatch.setattr(sys, "path", list(sys.path))
    yield
    sys.modules.pop("my_callbacks", None)


def _summary(run: Path) -> dict:
    return json.loads((run / "summary.json").read_text())


def test_stop_on_return_ends_the_run_early_with_the_record_and_resume_says_complete_or_trains_on(tmp_path, capsys):
    run = tmp_path / "stop"
    overrides = tiny("collector.total_frames=600", "eval.episodes=1", "rank.interval=100000", STOP)
    assert main(["run", "quickstart", *overrides, "-o", str(run), "--quiet"]) == 0
    summary = _summary(run)
    stop = summary["stopped_early"]
    # the first evaluation (300 frames) reaches any return: the run ends there, cleanly
    assert summary["frames"] == 300 and stop["frames"] == 300 and stop["callback"] == "stop_on_return"
    assert "eval/mean_reward" in stop["reason"] and "-1e+09" in stop["reason"] and stop["total_frames"] == 600
    assert stop["updates"] == summary["updates"] > 0
    assert (run / "report.md").is_file() and (run / "checkpoints" / CKPT.format(300)).is_file()
    assert not (run / "checkpoints" / CKPT.format(600)).exists()
    assert len((run / "eval.csv").read_text().strip().splitlines()) == 2  # header + the one evaluation
    assert "stopped early at 300 frames by callback 'stop_on_return'" in capsys.readouterr().out
    recorded = json.loads((run / "plugins.json").read_text())["callbacks"]
    assert recorded == [
        {
            "name": "stop_on_return",
            "callback": "adarl.runtime.callbacks:StopOnReturn",
            "package": "adarl",
            "version": recorded[0]["version"],
            "options": {"threshold": -1e9, "min_frames": 300},
        }
    ]
    fingerprint = json.loads((run / "fingerprint.json").read_text())["sha256"]
    assert run_is_finished(run)  # an experiment does not train it again

    # resumed as it is: complete, nothing trained
    assert main(["resume", str(run), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "is complete: callback 'stop_on_return' stopped it early at 300 frames" in out and "callbacks=[]" in out
    assert _summary(run)["frames"] == 300 and not (run / "checkpoints" / CKPT.format(600)).exists()

    # the stop dropped on resume: it trains on to the budget, and says so
    assert main(["resume", str(run), "callbacks=[]", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "this run stopped early at 300 frames" in err and "training on to collector.total_frames=600" in err
    summary = _summary(run)
    assert summary["frames"] == 600 and summary["stopped_early"] is None
    assert [s["frames"] for s in summary["earlier_stops"]] == [300]
    assert run_is_finished(run)
    assert json.loads((run / "plugins.json").read_text())["callbacks"] == []
    assert json.loads((run / "fingerprint.json").read_text())["sha256"] != fingerprint  # callbacks are fingerprinted


def test_a_user_callback_from_a_local_module_is_called_at_its_hook_points_and_its_state_survives_a_resume(tmp_path):
    (tmp_path / "my_callbacks.py").write_text(MODULE)
    (tmp_path / "cb.yaml").write_text(textwrap.dedent(RECIPE))
    run = tmp_path / "run"
    # 600 frames in batches of 100, updates from 400 frames on, a rank event every 150 updates (its warm start's
    # frames not counted)
    overrides = tiny("collector.init_random_frames=400", "eval.episodes=1", "replay.warm_start.count_frames=false")
    assert main(["run", str(tmp_path / "cb.yaml"), *overrides, "-o", str(run), "--quiet"]) == 0
    summary = _summary(run)
    assert summary["stopped_early"] is None and summary["rank_events"] > 0

    def state(ckpt: str) -> dict:  # the callback's state in a checkpoint
        saved = torch.load(run / "checkpoints" / ckpt, weights_only=True)["state"]["callbacks"]
        assert saved["stop"] is None
        return saved["modules"]["count_hooks"]

    whole = state(CKPT.format(600))
    assert whole["counts"] == {
        "post_optim": summary["updates"],
        "post_steps": 6,  # 600 frames in batches of 100
        "post_eval": 2,  # at 300 and 600 frames
        "post_rank_event": summary["rank_events"],
    }
    assert whole["frames"] == [100, 200, 300, 400, 500, 600]
    halfway = state(CKPT.format(300))
    assert halfway["counts"]["post_steps"] == 3 and halfway["counts"]["post_eval"] == 1
    recorded = json.loads((run / "plugins.json").read_text())
    assert [(c["name"], c["callback"], c["options"]) for c in recorded["callbacks"]] == [
        ("count_hooks", "my_callbacks:CountHooks", {"label": "a"})
    ]
    assert [m["module"] for m in recorded["modules"]] == ["my_callbacks"]

    # killed at 300 frames, as far as the run can tell: resumed from that checkpoint, its counts continue from there
    trainer = BaseTrainer.resume(run, quiet=True, checkpoint=run / "checkpoints" / CKPT.format(300))
    assert trainer.hooks.modules["count_hooks"].counts == halfway["counts"]
    trainer.train()
    assert state(CKPT.format(600)) == whole


@pytest.mark.parametrize(
    ("entry", "named"),
    [
        ("{name: stop_on_retrun, options: {threshold: 1}}", "callbacks[0].name = 'stop_on_retrun'"),
        ("{name: stop_on_return, options: {threshold: 1, patience: 3}}", "callbacks[0].options.patience = 3"),
        ("{name: stop_on_return, options: {threshold: .nan}}", "callbacks[0].options.threshold"),
    ],
)
def test_an_unknown_callback_or_a_bad_option_is_refused_by_name_with_no_run_folder(entry, named, tmp_path, capsys):
    run = tmp_path / "runs" / "bad"
    assert main(["run", "quickstart", *tiny(f"callbacks=[{entry}]"), "-o", str(run), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert named in err and "stop_on_return" in err
    assert not run.exists() and not run.parent.exists()
