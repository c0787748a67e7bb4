"""The run folder: refusal to overwrite, safe checkpoint loading, rotation, metric truncation, logger extras."""

from __future__ import annotations

import importlib.util
import types

import pytest
import torch

from adarl.errors import AdaRLError, CheckpointError
from adarl.run_dir import RunDir


def test_create_refuses_existing_non_empty(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "keep.txt").write_text("precious")
    with pytest.raises(AdaRLError, match="already exists"):
        RunDir.create(tmp_path / "run")
    assert (tmp_path / "run" / "keep.txt").read_text() == "precious"
    RunDir.create(tmp_path / "run", overwrite=True)
    assert not (tmp_path / "run" / "keep.txt").exists()


def test_checkpoint_round_trip_and_rotation(tmp_path):
    run = RunDir.create(tmp_path / "run")
    for frames in (100, 200, 300, 400):
        run.save_checkpoint({"counters": {"frames": frames}, "x": torch.full((3,), float(frames))},
                            frames=frames, keep_last=2)
    assert [p.name for p in run.checkpoints()] == ["ckpt-000000000300.pt", "ckpt-000000000400.pt"]
    state = run.load_latest_checkpoint()
    assert state["counters"]["frames"] == 400 and torch.equal(state["x"], torch.full((3,), 400.0))
    assert not list(run.checkpoint_dir.glob("*.tmp"))


def test_corrupt_latest_falls_back_to_previous(tmp_path):
    run = RunDir.create(tmp_path / "run")
    run.save_checkpoint({"counters": {"frames": 1}}, frames=1)
    latest = run.save_checkpoint({"counters": {"frames": 2}}, frames=2)
    latest.write_bytes(latest.read_bytes()[:50])  # truncated by a crash or a full disk
    with pytest.raises(CheckpointError, match="cannot be loaded safely"):
        run.load_checkpoint(latest)
    assert run.load_latest_checkpoint()["counters"]["frames"] == 1


class _Evil:
    def __reduce__(self):
        return (print, ("owned",))


def test_malicious_pickle_is_refused(tmp_path):
    run = RunDir.create(tmp_path / "run")
    run.checkpoint_dir.mkdir()
    bad = run.checkpoint_dir / "ckpt-000000000001.pt"
    torch.save({"format": "adarl.checkpoint", "version": 1, "state": _Evil()}, bad)
    with pytest.raises(CheckpointError, match="cannot be loaded safely"):
        run.load_checkpoint(bad)


def test_newer_checkpoint_version_is_refused(tmp_path):
    run = RunDir.create(tmp_path / "run")
    run.checkpoint_dir.mkdir()
    p = run.checkpoint_dir / "ckpt-000000000001.pt"
    torch.save({"format": "adarl.checkpoint", "version": 99, "state": {}}, p)
    with pytest.raises(CheckpointError, match="newer adarl"):
        run.load_checkpoint(p)
    torch.save({"something": "else"}, p)
    with pytest.raises(CheckpointError, match="not an adarl checkpoint"):
        run.load_checkpoint(p)


def test_truncate_metrics_drops_rows_after_checkpoint(tmp_path):
    run = RunDir.create(tmp_path / "run")
    scalars = run.path / "metrics" / "scalars"
    scalars.mkdir(parents=True)
    (scalars / "train.episode_return.csv").write_text("100,1.0\n200,2.0\n300,3.0\n")
    run.truncate_metrics(200)
    assert (scalars / "train.episode_return.csv").read_text() == "100,1.0\n200,2.0\n"
    assert run.scalars()["train.episode_return"] == [(100, 1.0), (200, 2.0)]


@pytest.mark.skipif(importlib.util.find_spec("tensorboard") is not None, reason="tensorboard is installed")
def test_missing_logger_extra_is_a_clear_error(tmp_path):
    run = RunDir.create(tmp_path / "run")
    recipe = types.SimpleNamespace(logging=types.SimpleNamespace(backends=["csv", "tensorboard"], wandb_mode="offline",
                                                                 wandb_project="adarl"), name="x")
    with pytest.raises(AdaRLError, match=r"adarl\[tensorboard\]"):
        run.make_logger(recipe)
