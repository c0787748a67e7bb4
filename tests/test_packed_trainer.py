"""Seeds packed in one process (adarl.runtime.trainers.packed): each seed trains as its solo run does, in a run folder
of its own, file for file; a diverging seed stops alone; a signal and a kill -9 leave a pack that resumes; an
experiment packs an arm's seeds (adarl.experiments.packing) into the run folders it plans."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import re
import signal

import pytest
import torch
import yaml
from _helpers import adarl, start_adarl, tiny, wait_for

from adarl.errors import AdaRLError, AdaRLValueError
from adarl.experiments.execute import read_attempts
from adarl.experiments.packing import PlannedPack, check_packable_launch, members, plan_packs
from adarl.experiments.spec import load_experiment, plan_runs
from adarl.runtime.config import load_recipe
from adarl.runtime.guards import NonFiniteError
from adarl.runtime.run_folder.run_dir import RunDir
from adarl.runtime.trainers.off_policy import OffPolicyTrainer
from adarl.runtime.trainers.pack_folder import create_pack, finish, resume_pack

#: 800 frames, updates from 200, rank events at updates 200 and 400 (both change ranks), checkpoints every 200
OVERRIDES = tiny(
    "collector.total_frames=800",
    "logging.log_interval=100",
    "rank.interval=200",
    "checkpoint.interval=200",
    "algorithm.fused=true",
)


def _recipe():
    return load_recipe("quickstart", OVERRIDES)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Seeds 0 and 1 alone, and packed with a seed 2 that diverges at its 120th update."""
    root = tmp_path_factory.mktemp("packed")
    recipe = _recipe()
    torch.set_num_threads(1)
    for s in (0, 1):
        OffPolicyTrainer(recipe.model_copy(update={"seed": s}), RunDir.create(root / f"solo{s}"), quiet=True).train()
    pack = create_pack(recipe, [0, 1, 2], root / "pack", quiet=True)
    poisoned = pack.trainers[2]

    def poison(_losses):
        if poisoned.updates == 120:
            with torch.no_grad():
                next(iter(poisoned.c.update.fused.actor_params.values())).view(-1)[0] = float("nan")

    poisoned.register_op("post_optim", poison)
    return root, pack.train()


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _close(a: str, b: str) -> bool:
    """Equal, numbers within fp noise (also inside ``rank:value;...`` lists, JSON lists and maps)."""
    ta, tb = re.split(r"[;:,\[\]{}\"\s]+", a), re.split(r"[;:,\[\]{}\"\s]+", b)
    if len(ta) != len(tb):
        return False
    for x, y in zip(ta, tb, strict=True):
        try:
            fx, fy = float(x), float(y)
        except ValueError:
            if x != y:
                return False
            continue
        if abs(fx - fy) > 1e-4 * max(1.0, abs(fx), abs(fy)):
            return False
    return True


def _same_run(solo, packed, *, checkpoints: bool = True) -> None:
    """A packed seed's run folder against its solo run's: the same files; the same ranks at every event and the same
    evaluations and training losses, up to the fp noise of the batched update (rounding, not chaos: 500 updates)."""

    def files(p):
        out = (str(f.relative_to(p)) for f in p.rglob("*") if f.is_file() and f.name != ".adarl.lock")
        return sorted(f for f in out if checkpoints or not f.startswith("checkpoints"))

    assert files(packed) == files(solo)
    for name in (
        "ranks.csv",
        "eval.csv",
        "metrics/scalars/train/critic_loss.csv",
        "metrics/scalars/train/actor_loss.csv",
    ):
        want, got = _rows(solo / name), _rows(packed / name)
        assert len(got) == len(want) > 0, name
        for w, g in zip(want, got, strict=True):
            assert w.keys() == g.keys()
            bad = {k: (w[k], g[k]) for k in w if not _close(w[k], g[k]) and k not in ("reason", "candidates")}
            assert not bad, (name, bad)
    solo_summary = json.loads((solo / "summary.json").read_text())
    packed_summary = json.loads((packed / "summary.json").read_text())
    assert set(packed_summary) - set(solo_summary) == {"packed_with"}
    assert packed_summary["ranks"] == solo_summary["ranks"] and packed_summary["rank_events"] == 2


def test_packed_seeds_train_as_their_solo_runs_and_a_diverging_seed_stops_alone(runs):
    root, report = runs
    outcome = {os.path.basename(k): v for k, v in report.items()}
    assert isinstance(outcome["seed=2"], NonFiniteError)
    for s in (0, 1):
        assert isinstance(outcome[f"seed={s}"], dict), outcome[f"seed={s}"]
        _same_run(root / f"solo{s}", root / "pack" / f"seed={s}")
        summary = json.loads((root / "pack" / f"seed={s}" / "summary.json").read_text())
        assert [os.path.basename(p) for p in summary["packed_with"]] == ["seed=0", "seed=1", "seed=2"]
    # the diverged seed stopped at its own divergence, with its last good checkpoint kept; the pack says which failed
    assert "training diverged" in str(outcome["seed=2"])
    assert not (root / "pack" / "seed=2" / "summary.json").exists()
    with pytest.raises(
        AdaRLError, match=r"1 of 3 packed seeds failed \(the others finished\): .*seed=2: NonFiniteError"
    ):
        finish(report)


def test_a_packed_run_stopped_by_a_signal_and_killed_resumes_to_its_solo_runs(runs, tmp_path):
    """From the user's side: `adarl run --pack-seeds` stopped by SIGTERM (every seed saves a checkpoint, exit 143),
    resumed, killed with -9 mid-run, resumed again: each seed ends as its solo run does."""
    root, _ = runs
    pack = tmp_path / "pack"

    def checkpoints_at(frames):
        return all((pack / f"seed={s}" / "checkpoints" / f"ckpt-{frames:012d}.pt").exists() for s in (0, 1))

    # checkpoints fall at 0, 200, 400, 700 (the warm start of the event at update 400 adds 100 frames), 800
    proc = start_adarl("run", "quickstart", *OVERRIDES, "--pack-seeds", "0", "1", "-o", str(pack), "--quiet")
    assert wait_for(lambda: checkpoints_at(200), proc), proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert f"adarl resume {pack}" in err
    assert json.loads((pack / "pack.json").read_text())["runs"] == ["seed=0", "seed=1"]

    proc = start_adarl("resume", str(pack), "--quiet")
    assert wait_for(lambda: checkpoints_at(400), proc), proc.communicate()[1]
    proc.kill()
    proc.wait(timeout=60)
    assert not any((pack / f"seed={s}" / "summary.json").exists() for s in (0, 1))

    done = adarl("resume", str(pack), "--quiet")
    assert done.returncode == 0, done.stderr
    for s in (0, 1):
        _same_run(root / f"solo{s}", pack / f"seed={s}", checkpoints=False)
    again = adarl("resume", str(pack))
    assert again.returncode == 0 and again.stdout.count("already complete") == 2, again.stdout + again.stderr


def test_pack_input_is_checked_before_anything_runs(tmp_path):
    bad = adarl("run", "quickstart", *OVERRIDES, "--pack-seeds", "1", "1", "-o", str(tmp_path / "p"))
    assert bad.returncode != 0 and "distinct seeds" in bad.stderr
    assert not (tmp_path / "p" / "seed=1").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    refused = adarl("run", "quickstart", *OVERRIDES, "--pack-seeds", "0", "-o", str(tmp_path / "full"))
    assert refused.returncode != 0 and "not empty" in refused.stderr
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"
    ppo = adarl(
        "run", "quickstart", *OVERRIDES, "algorithm.fused=false", "--pack-seeds", "0", "1", "-o", str(tmp_path / "q")
    )
    assert ppo.returncode != 0 and "packing runs the fused SAC update" in ppo.stderr
    assert not (tmp_path / "q" / "seed=0").exists() and not (tmp_path / "q" / "pack.json").exists()


def _spec(tmp_path, **extra):
    spec = tmp_path / "packed.yaml"
    spec.write_text(
        yaml.safe_dump(
            {"kind": "experiment", "name": "packed", "recipe": "quickstart", "overrides": list(OVERRIDES), **extra}
        )
    )
    return spec


def test_an_experiment_packs_an_arms_seeds_stops_on_sigterm_and_resumes_to_their_solo_runs(runs, tmp_path):
    """From the user's side: `adarl experiment` with the spec's `pack: 2` trains seeds 0 and 1 in one process, each in
    the run folder the experiment plans; SIGTERM to the driver stops the pack at a checkpoint (exit 143, both runs
    interrupted); the same command through the ray launcher resumes it as one Ray task; each run ends as its solo run
    does, and says the pack it trained in."""
    root, _ = runs
    spec, out = _spec(tmp_path, seeds=[0, 1], pack=2), tmp_path / "exp"
    cmd = ("experiment", str(spec), "-o", str(out), "--no-live", "--progress", "0", "--no-report")

    def checkpoints_at(frames):
        return all((out / f"seed={s}" / "checkpoints" / f"ckpt-{frames:012d}.pt").exists() for s in (0, 1))

    proc = start_adarl(*cmd)
    assert wait_for(lambda: checkpoints_at(200), proc), proc.communicate()
    proc.send_signal(signal.SIGTERM)
    said, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, said + err
    pack_id = re.search(r"\[pack\] (pack-[0-9a-f]+): recipe quickstart, seeds 0, 1", said).group(1)
    state = {r["run_id"]: r for r in json.loads((out / "experiment.json").read_text())["runs"]}
    assert {k: (r["status"], r["pack"]) for k, r in state.items()} == {
        "seed=0": ("interrupted", pack_id),
        "seed=1": ("interrupted", pack_id),
    }

    done = adarl(*cmd, "--launcher", "ray") if importlib.util.find_spec("ray") else adarl(*cmd)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "[finished] seed=0" in done.stdout and "[finished] seed=1" in done.stdout
    for s in (0, 1):
        run = out / f"seed={s}"
        _same_run(root / f"solo{s}", run, checkpoints=False)
        assert json.loads((run / "summary.json").read_text())["packed_with"] == [
            str(out / "seed=0"),
            str(out / "seed=1"),
        ]
        attempts = [(e["event"], e.get("action"), e.get("status"), e["pack"]) for e in read_attempts(out, f"seed={s}")]
        assert attempts == [
            ("start", "ran", None, pack_id),
            ("end", "ran", "interrupted", pack_id),
            ("start", "resumed", None, pack_id),
            ("end", "resumed", "finished", pack_id),
        ]
    assert json.loads((out / "packs" / pack_id / "pack.json").read_text())["runs"] == ["../../seed=0", "../../seed=1"]


def test_an_arm_that_cannot_pack_runs_solo_said_by_name_and_what_packing_does_not_run_is_refused(tmp_path):
    """Packs are planned per arm (recipes equal but for the seed), `pack` seeds at a time, in seed order; an arm of
    TorchRL's update path runs solo, said why; an output at a URL is refused before anything is written."""
    spec = _spec(
        tmp_path,
        seeds=[0, 1, 2],
        axes={"path": [{"name": "fused"}, {"name": "torchrl", "overrides": ["algorithm.fused=false"]}]},
    )
    runs = plan_runs(load_experiment(spec), str(tmp_path / "exp"))
    recipes = {r.run_id: load_recipe(r.recipe, r.overrides) for r in runs}
    said = []
    units = plan_packs(runs, recipes, 2, str(tmp_path / "exp"), said.append)
    assert [[m.run_id for m in members(u)] for u in units] == [
        ["path=fused__seed=0", "path=fused__seed=1"],
        ["path=fused__seed=2"],
        ["path=torchrl__seed=0"],
        ["path=torchrl__seed=1"],
        ["path=torchrl__seed=2"],
    ]
    assert isinstance(units[0], PlannedPack) and units[0].path == str(tmp_path / "exp" / "packs" / units[0].run_id)
    assert said[0] == f"[pack] {units[0].run_id}: path=fused, seeds 0, 1"
    assert said[1].startswith("[solo] path=torchrl: 3 runs, each in its own process (cannot pack: LossStep")
    assert plan_packs(runs, recipes, 1, str(tmp_path / "exp"), said.append) == runs
    with pytest.raises(AdaRLValueError, match=">= 1, got 0"):
        check_packable_launch(0)
    bad = adarl("experiment", str(spec), "-o", str(tmp_path / "exp"), "--pack", "-2")
    assert bad.returncode != 0 and "--pack takes a number of seeds per process >= 1, got -2" in bad.stderr, bad.stderr
    units = plan_packs(runs, recipes, 2, "file:///bucket/exp", said.append)  # a pack's stop file sits at the URL
    assert units[0].path == f"file:///bucket/exp/packs/{units[0].run_id}"


def test_a_pack_at_a_url_trains_in_scratch_folders_and_resumes_on_another_machines(runs, tmp_path):
    """``--pack`` with an fsspec URL output (``file://``, the protocol of adarl.runtime.run_folder.results):
    the pack trains its runs in a local scratch folder and uploads each after its checkpoints; SIGTERM stops it (exit
    143, each run's checkpoint at the URL, no summary); the same command on another scratch folder (another machine)
    downloads both and finishes them in one pack, each as its solo run, ``packed_with`` naming the runs' URLs."""
    root, _ = runs
    bucket, first, second = tmp_path / "bucket", tmp_path / "scratch-a", tmp_path / "scratch-b"
    url = f"file://{bucket}/exp"
    spec = _spec(tmp_path, seeds=[0, 1], pack=2)
    cmd = ("experiment", str(spec), "-o", url, "--no-live", "--progress", "0", "--no-report")

    def checkpointed():
        return all(list(first.glob(f"*/seed={s}/checkpoints/ckpt-{200:012d}.pt")) for s in (0, 1))

    proc = start_adarl(*cmd, "--scratch", str(first))
    assert wait_for(checkpointed, proc), proc.communicate()
    proc.send_signal(signal.SIGTERM)
    said, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, said + err
    pack_id = re.search(r"\[pack\] (pack-[0-9a-f]+): recipe quickstart, seeds 0, 1", said).group(1)
    for s in (0, 1):
        at_url = bucket / "exp" / f"seed={s}"
        assert json.loads((at_url / "checkpoints" / "LATEST").read_text())["frames"] >= 200
        assert not (at_url / "summary.json").exists()

    done = adarl(*cmd, "--scratch", str(second))
    assert done.returncode == 0, done.stdout + done.stderr
    for s in (0, 1):
        run = bucket / "exp" / f"seed={s}"
        _same_run(root / f"solo{s}", run, checkpoints=False)
        assert json.loads((run / "summary.json").read_text())["packed_with"] == [f"{url}/seed=0", f"{url}/seed=1"]
        attempts = read_attempts(url, f"seed={s}")
        assert [(e["event"], e.get("action"), e.get("status"), e["pack"]) for e in attempts] == [
            ("start", "ran", None, pack_id),
            ("end", "ran", "interrupted", pack_id),
            ("start", "resumed", None, pack_id),
            ("end", "resumed", "finished", pack_id),
        ]
        assert attempts[2]["scratch"].startswith(str(second))
    # finished runs leave nothing in the scratch folder (the pack folder included); the URL no temporary name
    assert not [p for p in second.rglob("*") if p.is_file()]
    assert not [p for p in bucket.rglob("*") if ".part-" in p.name]


def test_a_pack_killed_before_its_first_checkpoint_starts_its_seeds_afresh(tmp_path):
    """A seed with a recipe.yaml and no checkpoint (the pack was killed while it built) starts afresh on resume; a
    pack.json that names a folder outside the pack (or an experiment's runs) is refused by name."""
    pack = create_pack(_recipe(), [3, 4], tmp_path / "p", quiet=True)
    for t in pack.trainers:  # as a kill before the first checkpoint leaves them (locks released with the process)
        t.close()
    again, said = resume_pack(tmp_path / "p")
    try:
        assert said == [] and [(t.recipe.seed, t.frames) for t in again.trainers] == [(3, 0), (4, 0)]
    finally:
        for t in again.trainers:
            t.close()
    (tmp_path / "p" / "pack.json").write_text(json.dumps({"seeds": [3], "runs": ["../elsewhere"]}))
    with pytest.raises(AdaRLValueError, match="neither inside the pack folder nor an experiment's run"):
        resume_pack(tmp_path / "p")
    (tmp_path / "p" / "pack.json").write_text(
        json.dumps({"seeds": [3, 4], "runs": ["seed=3", "seed=4"], "names": ["a"]})
    )
    with pytest.raises(
        AdaRLValueError, match="one seed \\(and start, name\\) each: 2 runs, 2 seeds, 2 starts, 1 names"
    ):
        resume_pack(tmp_path / "p")
    (tmp_path / "p" / "pack.json").write_text(json.dumps({"seeds": [3], "runs": ["seed=3"], "names": [""]}))
    with pytest.raises(AdaRLValueError, match="names must be non-empty strings"):
        resume_pack(tmp_path / "p")
