"""Continuing a finished run to more frames (issue 31, point 1): ``adarl resume RUN collector.total_frames=M``
gives the run started with M frames when the recipe's schedules do not depend on the total; only the budget may
change (raised), every other key is refused by name; a finished run without a larger total is "already
complete" (exit 0)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from _helpers import INTERVALS_1200, tiny

from adarl.cli import main

# N = 1200 frames: a multiple of the batch (100), the evaluation (600), logging (200) and checkpoint (400) intervals
TINY = tiny(*INTERVALS_1200)


def _results(run: Path) -> dict[str, str]:
    """Every metric file and the evaluation/rank records, as text (wall-clock fields left out)."""
    root = run / "metrics" / "scalars"
    out = {
        p.relative_to(root).as_posix(): p.read_text()
        for p in sorted(root.rglob("*.csv"))
        if p.relative_to(root).parts[0] != "time"
    }
    for name in ("eval.csv", "ranks.json"):
        out[name] = (run / name).read_text()
    summary = json.loads((run / "summary.json").read_text())
    for k in ("wall_time_s", "updates_per_s"):
        summary.pop(k)
    out["summary.json"] = json.dumps(summary, sort_keys=True)
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A 1200-frame run continued to 1800 frames, beside a run started with 1800 (no LR cosine: no schedule
    depends on the total)."""
    root = tmp_path_factory.mktemp("continue")
    recipe = [*TINY, "lr_schedule.cosine=false"]
    short, long_ = root / "short", root / "long"
    assert main(["run", "quickstart", *recipe, "-o", str(short), "--quiet"]) == 0
    assert main(["run", "quickstart", *recipe, "collector.total_frames=1800", "-o", str(long_), "--quiet"]) == 0
    finished = _results(short)
    return {"short": short, "long": long_, "finished": finished}


def test_a_finished_run_is_already_complete(runs, capsys):
    capsys.readouterr()
    files = sorted(p.relative_to(runs["short"]) for p in runs["short"].rglob("*"))
    assert main(["resume", str(runs["short"]), "--quiet"]) == 0
    assert main(["resume", str(runs["short"]), "--quiet"]) == 0
    # not one file more: each resume of a complete run added a TensorBoard event file (issue 48.6)
    assert sorted(p.relative_to(runs["short"]) for p in runs["short"].rglob("*")) == files
    out = capsys.readouterr().out
    assert "already complete: 1200 frames of collector.total_frames=1200" in out, out
    assert "run finished" not in out
    assert "collector.total_frames=N" in out
    assert _results(runs["short"]) == runs["finished"]  # nothing was trained, evaluated or rewritten


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["rank.beta=0.9"], "cannot change 'rank.beta'"),
        (["collector.total_frames=2400", "seed=3"], "cannot change 'seed'"),
        (["collector.total_frame=2400"], "did you mean 'collector.total_frames'?"),
        (["collector.total_frames=600"], "may only raise the frame budget"),
    ],
)
def test_other_changes_are_refused_by_name(runs, capsys, overrides, message):
    before = (runs["short"] / "recipe.yaml").read_text()
    capsys.readouterr()
    assert main(["resume", str(runs["short"]), *overrides, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    if "raise" not in message:
        assert "allowed: 'collector.total_frames'" in err
    assert (runs["short"] / "recipe.yaml").read_text() == before


def test_continued_to_more_frames_equals_the_run_started_with_them(runs, capsys):
    short, long_ = runs["short"], runs["long"]
    assert main(["resume", str(short), "collector.total_frames=1800", "--quiet"]) == 0
    assert "run finished: 1800 frames" in capsys.readouterr().out
    assert yaml.safe_load((short / "recipe.yaml").read_text())["collector"]["total_frames"] == 1800
    want, got = _results(long_), _results(short)
    assert set(want) == set(got)
    for name in want:  # bit-identical, not approximately equal
        assert got[name] == want[name], f"{name} differs from the run started with 1800 frames"
    assert main(["resume", str(short), "collector.total_frames=1800", "--quiet"]) == 0
    assert "already complete: 1800 frames" in capsys.readouterr().out


def test_continuing_re_plans_the_lr_cosine_from_where_the_run_is(tmp_path):
    """With ``lr_schedule.cosine`` (over the planned updates) the continued run's cosine is the longer run's from
    the step it is at (docs/resuming.md)."""
    from adarl.runtime.builders.sac import planned_updates
    from adarl.runtime.config import load_recipe
    from adarl.runtime.trainers import BaseTrainer

    run = tmp_path / "run"
    assert main(["run", "quickstart", *TINY, "-o", str(run), "--quiet"]) == 0
    longer = load_recipe("quickstart", [*TINY, "collector.total_frames=2400"])
    trainer = BaseTrainer.resume(run, quiet=True, overrides=["collector.total_frames=2400"])
    try:
        assert trainer.frames == 1200 and trainer.recipe.collector.total_frames == 2400
        for name in ("actor", "critic"):
            sched = trainer.c.schedulers[name]
            fn = sched.lr_lambdas[0]
            assert fn.total_steps == planned_updates(longer) != planned_updates(load_recipe("quickstart", TINY))
            lr = trainer.c.optimizers[name].param_groups[0]["lr"]
            assert lr == pytest.approx(sched.base_lrs[0] * fn(sched.last_epoch)) and lr > 0
    finally:
        trainer.close()
    assert yaml.safe_load((run / "recipe.yaml").read_text())["collector"]["total_frames"] == 2400


def test_a_run_stopped_after_its_last_checkpoint_is_finished_not_complete(runs, capsys):
    """Its end (summary, report) was not written: resuming writes it, as before, instead of "already complete"."""
    long_ = runs["long"]
    (long_ / "summary.json").unlink()
    capsys.readouterr()
    assert main(["resume", str(long_), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "run finished: 1800 frames" in out and "already complete" not in out
    assert json.loads((long_ / "summary.json").read_text())["frames"] == 1800
