"""The run folder: refusal to overwrite, safe checkpoint loading, rotation, metric truncation, logger extras."""

from __future__ import annotations

import importlib.util
import os
import types

import pytest
import torch

from adarl.errors import AdaRLError, CheckpointError
from adarl.runtime.run_folder.run_dir import LOCK_FILE, RunDir


def test_create_refuses_existing_non_empty(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "keep.txt").write_text("precious")
    with pytest.raises(AdaRLError, match="already exists") as info:
        RunDir.create(tmp_path / "run")
    assert "keep.txt" in str(info.value) and "adarl resume" not in str(info.value)  # not a run: nothing to resume
    # --overwrite replaces only an adarl run folder that holds nothing else: keep.txt is named, and stays
    with pytest.raises(AdaRLError, match="--overwrite refused") as info:
        RunDir.create(tmp_path / "run", overwrite=True)
    assert "keep.txt" in str(info.value) and "nothing was deleted" in str(info.value)
    assert (tmp_path / "run" / "keep.txt").read_text() == "precious"
    run = RunDir.create(tmp_path / "other")
    run.save_checkpoint({"counters": {"frames": 1}}, frames=1)
    (run.path / "summary.json.tmp").write_text("{")  # a write a crash cut short is adarl's too
    run.unlock()
    with pytest.raises(AdaRLError, match="adarl resume"):
        RunDir.create(run.path)
    RunDir.create(run.path, overwrite=True).unlock()
    assert sorted(p.name for p in run.path.iterdir()) == [".adarl.lock"]


def test_checkpoint_round_trip_and_rotation(tmp_path):
    run = RunDir.create(tmp_path / "run")
    for frames in (100, 200, 300, 400):
        run.save_checkpoint(
            {"counters": {"frames": frames}, "x": torch.full((3,), float(frames))}, frames=frames, keep_last=2
        )
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
    recipe = types.SimpleNamespace(
        logging=types.SimpleNamespace(backends=["csv", "tensorboard"], wandb_mode="offline", wandb_project="adarl"),
        name="x",
    )
    with pytest.raises(AdaRLError, match=r"adarl\[tensorboard\]"):
        run.make_logger(recipe)


def _create_after(barrier, path, results) -> None:
    barrier.wait()
    try:
        RunDir.create(path)
        results.put("won")
    except AdaRLError as err:
        results.put(str(err))


@pytest.mark.parametrize("existing", [False, True])
def test_create_is_exclusive_when_processes_race(tmp_path, existing):
    """The check-then-create race of two `adarl run -o SAME`: processes released by one barrier, one wins each round."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    for round_ in range(5):
        path = tmp_path / f"run{round_}"
        if existing:
            path.mkdir()  # an empty folder the user made: the emptiness check alone cannot decide
        barrier, results = ctx.Barrier(4), ctx.Queue()
        procs = [ctx.Process(target=_create_after, args=(barrier, path, results)) for _ in range(4)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(30)
        outcomes = [results.get(timeout=5) for _ in procs]
        assert outcomes.count("won") == 1, outcomes
        assert all(o == "won" or "already exists" in o or "claimed by another process" in o for o in outcomes)


def test_lock_is_per_process_and_released_with_the_process(tmp_path):
    import subprocess
    import sys

    run = RunDir.create(tmp_path / "run")
    run.lock()  # re-entrant in the process that holds it
    RunDir(run.path).lock()
    code = "import sys; from adarl.runtime.run_folder.run_dir import RunDir; RunDir(sys.argv[1]).lock()"
    proc = subprocess.run([sys.executable, "-c", code, str(run.path)], capture_output=True, text=True)
    assert proc.returncode != 0 and "in use by another process" in proc.stderr
    assert f"pid {os.getpid()}" in proc.stderr
    run.discard(keep_folder=True)  # released: another process may take it now
    proc = subprocess.run([sys.executable, "-c", code, str(run.path)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_write_json_is_strict_json(tmp_path):
    import json
    import math

    run = RunDir.create(tmp_path / "run")
    run.write_json(
        "summary.json",
        {"a": float("nan"), "b": [1.0, float("inf")], "c": torch.tensor([float("-inf"), 2.0]), "d": {"e": math.pi}},
    )
    text = (run.path / "summary.json").read_text()
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    assert data == {"a": None, "b": [1.0, None], "c": [None, 2.0], "d": {"e": math.pi}}


def test_checkpoint_of_another_recipe_is_refused_by_name(tmp_path):
    run = RunDir.create(tmp_path / "run")
    mine = {"env.id": "Hopper-v5", "network.actor.num_cells": [64, 64], "replay.size": 1000}
    theirs = {**mine, "network.actor.num_cells": [32]}
    path = run.save_checkpoint({"counters": {"frames": 1}}, frames=1, fingerprint=theirs)
    with pytest.raises(CheckpointError, match=r"another recipe \(network.actor.num_cells: \[32\] in it, \[64, 64\]"):
        run.load_checkpoint(path, fingerprint=mine)
    # keys one side does not know (another adarl version) are not compared; no fingerprint given: not checked
    assert run.load_checkpoint(path, fingerprint={"env.id": "Hopper-v5", "new.key": 1})["counters"]["frames"] == 1
    assert run.load_checkpoint(path)["counters"]["frames"] == 1


def test_replay_buffer_round_trip_and_older_dumps_folders(tmp_path):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    def buffer():
        return TensorDictReplayBuffer(
            storage=LazyTensorStorage(100), batch_size=4, generator=torch.Generator().manual_seed(0)
        )

    rb = buffer()
    rb.extend(TensorDict({"obs": torch.randn(30, 3)}, [30]))
    run = RunDir.create(tmp_path / "run")
    run.save_checkpoint({"counters": {"frames": 30}}, frames=30, replay_buffer=rb)
    assert [p.name for p in (run.checkpoint_dir / "rb-000000000030").iterdir()] == ["buffer.pt"]
    back = buffer()
    assert run.load_replay_buffer(back, frames=30) and len(back) == 30
    assert torch.equal(back.sample()["obs"], rb.sample()["obs"])  # same data, same sampler state
    rb.dumps(str(run.checkpoint_dir / "rb-000000000060"))  # the layout checkpoints had before this release
    old = buffer()
    assert run.load_replay_buffer(old, frames=60) and len(old) == 30


def test_a_kill_between_a_rewrites_two_renames_resumes_from_that_checkpoint(tmp_path, monkeypatch):
    """The run's end writes its checkpoint again at the same frames: the old buffer is renamed aside, then the new
    one into place. A kill between the two used to leave the checkpoint without a buffer, and resume fell back one
    checkpoint; the set-aside buffer is the one that checkpoint was written with, and is used."""
    import warnings

    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from adarl.runtime.run_folder import _checkpoints as _run_checkpoints

    def buffer(n=0):
        rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4)
        if n:
            rb.extend(TensorDict({"obs": torch.arange(n, dtype=torch.float32)[:, None]}, [n]))
        return rb

    run = RunDir.create(tmp_path / "run")
    run.save_checkpoint({"counters": {"frames": 10}, "tag": "earlier"}, frames=10, replay_buffer=buffer(10))
    run.save_checkpoint({"counters": {"frames": 30}, "tag": "end"}, frames=30, replay_buffer=buffer(30))
    real_replace = os.replace

    def killed_at_the_second_rename(src, dst):
        if str(src).endswith("rb-000000000030.tmp"):
            raise SystemExit("killed")  # not an OSError: nothing of save_checkpoint's clean-up runs, as on SIGKILL
        real_replace(src, dst)

    monkeypatch.setattr(_run_checkpoints.os, "replace", killed_at_the_second_rename)
    with pytest.raises(SystemExit):
        run.save_checkpoint({"counters": {"frames": 30}, "tag": "end again"}, frames=30, replay_buffer=buffer(30))
    monkeypatch.undo()
    rb_dir = run.checkpoint_dir / "rb-000000000030"
    assert not rb_dir.exists() and (run.checkpoint_dir / "rb-000000000030.old.tmp").is_dir()  # the window
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback to the checkpoint at 10 frames
        state = RunDir(run.path).load_latest_checkpoint(quarantine=True)
    assert state["tag"] == "end"
    back = buffer()
    assert run.load_replay_buffer(back, frames=30) and len(back) == 30
    assert torch.equal(back.storage[:]["obs"][:, 0], torch.arange(30, dtype=torch.float32))
    run.save_checkpoint({"counters": {"frames": 30}, "tag": "resumed"}, frames=30, replay_buffer=buffer(30))
    assert rb_dir.is_dir() and not (run.checkpoint_dir / "rb-000000000030.old.tmp").exists()
    assert run.load_latest_checkpoint()["tag"] == "resumed"


@pytest.mark.parametrize(
    "payload",
    [
        {"format": "adarl.checkpoint", "version": 1, "state": {"counters": 5}},
        {"format": "adarl.checkpoint", "version": "x", "state": {"counters": {"frames": 1}}},
        {"format": "adarl.checkpoint", "version": 1, "state": [1, 2]},
        {"format": "adarl.checkpoint", "version": 1, "frames": "soon", "state": {"counters": {"frames": 1}}},
    ],
)
def test_malformed_checkpoint_is_refused_not_a_traceback(tmp_path, payload):
    run = RunDir.create(tmp_path / "run")
    run.checkpoint_dir.mkdir()
    path = run.checkpoint_dir / "ckpt-000000000001.pt"
    torch.save(payload, path)  # loads with weights_only=True: only its layout is wrong
    with pytest.raises(CheckpointError, match="not an adarl checkpoint"):
        run.load_checkpoint(path)


def test_a_full_device_names_the_file_it_could_not_write(tmp_path):
    """/dev/full fails every write with ENOSPC, as a full disk does, where a buffered file's flush names no file."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full here")
    import errno
    import types as _types

    run = RunDir.create(tmp_path / "run")
    (run.path / "metrics" / "scalars" / "train").mkdir(parents=True)
    os.symlink("/dev/full", run.path / "metrics" / "scalars" / "train" / "episode_return.csv")
    logger = run.make_logger(
        _types.SimpleNamespace(logging=_types.SimpleNamespace(backends=["csv"], wandb_mode="disabled"))
    )
    with pytest.raises(OSError) as info:
        logger.log_scalar("train/episode_return", 1.0, step=1)
    assert info.value.errno == errno.ENOSPC
    assert info.value.filename.endswith(os.path.join("metrics", "scalars", "train", "episode_return.csv"))
    os.symlink("/dev/full", run.path / "eval.csv")
    result = _types.SimpleNamespace(mean=1.0, std=0.0, ci95=0.0, returns=[1.0])
    with pytest.raises(OSError) as info:
        run.append_eval(1, 1, result, ranks={})
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(run.path / "eval.csv")
    run.close_logger(logger)  # its unwritten row fails again on close, quietly


def test_a_deleted_run_folder_is_not_recreated(tmp_path):
    import shutil

    from adarl.runtime.run_folder.run_dir import RunFolderGone

    run = RunDir.create(tmp_path / "run")
    run.save_checkpoint({"counters": {"frames": 1}}, frames=1)
    run.ensure_present()
    shutil.rmtree(run.path)
    for write in (
        lambda: run.save_checkpoint({"counters": {"frames": 2}}, frames=2),
        lambda: run.write_json("summary.json", {}),
    ):
        with pytest.raises(RunFolderGone, match="deleted or moved"):
            write()
    assert not run.path.exists()
    moved = RunDir.create(tmp_path / "moved")
    os.rename(moved.path, tmp_path / "elsewhere")
    (tmp_path / "moved").mkdir()
    (tmp_path / "moved" / LOCK_FILE).write_text("")  # another folder took its name: not the one this process holds
    with pytest.raises(RunFolderGone):
        moved.ensure_present()


class _Payload:
    """A pickle that runs a command when unpickled: it would create ``marker``."""

    def __init__(self, marker) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


@pytest.mark.parametrize(
    "attack",
    [
        "checkpoint",
        "checkpoint as plain pickle",
        "buffer.pt",
        "prefetch.pkl",
        "transform.t",
        "meta.json class",
        "extra file",
        "symlink",
    ],
)
def test_loading_a_checkpoint_or_its_replay_buffer_runs_nothing(tmp_path, attack):
    """Issue 46: every file a resume reads goes through a weights-only or data-only path. The replay buffer of a
    checkpoint from before buffer.pt is TorchRL's dumps() folder, which TorchRL reads with pickle.load (its
    prefetch.pkl), torch.load (transform.t) and tensordict's load_memmap (pickled non-tensor leaves, classes
    imported by the name in meta.json): such a folder is checked first, and anything but tensors and JSON refused."""
    import pickle
    import shutil

    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    def buffer():
        return TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4)

    marker = tmp_path / "pwned"
    rb = buffer()
    rb.extend(TensorDict({"obs": torch.randn(30, 3)}, [30]))
    run = RunDir.create(tmp_path / "run")
    ckpt = run.save_checkpoint({"counters": {"frames": 30}}, frames=30, replay_buffer=rb)
    folder = run.checkpoint_dir / "rb-000000000030"
    if attack in ("checkpoint", "buffer.pt"):
        target = ckpt if attack == "checkpoint" else folder / "buffer.pt"
        torch.save({"format": "adarl.checkpoint", "version": 1, "frames": 30, "state": _Payload(marker)}, target)
    elif attack == "checkpoint as plain pickle":
        ckpt.write_bytes(pickle.dumps(_Payload(marker)))
    else:  # the layout checkpoints had before buffer.pt (still read), with something that would run
        shutil.rmtree(folder)
        rb.dumps(str(folder))
        if attack == "prefetch.pkl":
            (folder / "prefetch.pkl").write_bytes(pickle.dumps({"version": 1, "queue": (_Payload(marker),)}))
        elif attack == "transform.t":
            torch.save({"t": _Payload(marker)}, folder / "transform.t")
        elif attack == "meta.json class":
            meta = folder / "storage" / "meta.json"
            meta.write_text(meta.read_text().replace("<class 'tensordict._td.TensorDict'>", "antigravity.Fly"))
        elif attack == "extra file":
            (folder / "storage" / "obs.pickle").write_bytes(pickle.dumps(_Payload(marker)))
        else:
            (folder / "storage" / "obs.memmap").unlink()
            (folder / "storage" / "obs.memmap").symlink_to("/dev/zero")
    with pytest.raises(CheckpointError) as info:
        run.load_checkpoint(ckpt)
    assert ckpt.name in str(info.value) and "weights_only" not in str(info.value)
    if attack.startswith("checkpoint"):
        assert "cannot be loaded safely" in str(info.value)
    else:
        assert "has lost its replay buffer" in str(info.value) and "rb-000000000030" in str(info.value)
    if attack not in ("checkpoint", "checkpoint as plain pickle", "buffer.pt"):
        with pytest.raises(CheckpointError, match="rb-000000000030"):
            run.load_replay_buffer(buffer(), frames=30, checkpoint=ckpt)
    assert not marker.exists(), "a file of the checkpoint ran code"
