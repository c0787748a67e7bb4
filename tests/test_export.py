"""A trained policy as a deployable file (issue 31, point 7): `adarl export RUN` / `adarl.export_policy` write the
deterministic actor as a TorchScript (or torch.export) program that torch alone loads and that acts as
`adarl.load_policy` does; `adarl.ExportedPolicy` gives it SB3's `predict(obs)` on numpy. Low-rank layers are merged
or factored per layer; truncated ranks, the PPO baselines' observation normalisation and a discrete actor export too;
what cannot be exported, and every bad command line, is one clear line. No timing is asserted here
(benchmarks/export_speed.py measures)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from adarl.cli import main as cli_main

REPO = Path(__file__).resolve().parents[1]
TINY = [  # tests/test_policy.py's tiny run: rank events truncate the actor's second layer
    "collector.total_frames=1600",
    "collector.init_random_frames=300",
    "collector.frames_per_batch=100",
    "algorithm.batch_size=64",
    "rank.interval=400",
    "replay.size=5000",
    "replay.warm_start.frames=100",
    "lr_schedule.warmup_steps=50",
    "eval.interval=800",
    "eval.episodes=2",
    "eval.max_steps=60",
    "checkpoint.interval=500",
]
TINY_PPO = [
    "collector.total_frames=256",
    "collector.frames_per_batch=128",
    "algorithm.ppo.epochs=1",
    "eval.interval=256",
    "eval.episodes=1",
    "eval.max_steps=20",
    "checkpoint.interval=256",
]
ATOL = 1e-5
HEAVY = ("adarl", "torchrl", "tensordict", "gymnasium", "mujoco")


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}


def cli(*args: str, cwd: Path | None = None):
    return subprocess.run(
        [sys.executable, "-m", "adarl.cli", *args], cwd=cwd or REPO, env=_env(), capture_output=True, text=True
    )


def python(code: str, cwd: Path | None = None, pythonpath: bool = True):
    env = _env() if pythonpath else {k: v for k, v in _env().items() if k != "PYTHONPATH"}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], cwd=cwd or REPO, env=env, capture_output=True, text=True
    )


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "run"
    proc = cli("run", "quickstart", *TINY, "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _observations(n: int, dim: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 3.0 * torch.randn(n, dim, generator=g)


def _actor_actions(actor, obs: torch.Tensor) -> torch.Tensor:
    """load_policy's actor as a user calls it: outside set_exploration_type (its deterministic action)."""
    with torch.no_grad():
        return actor(TensorDict(observation=obs, batch_size=obs.shape[:1]))["action"]


def _actor_ranks(actor) -> list[int]:
    from adarl.core.lowrank import iter_low_rank

    return [layer.rank for _, layer in iter_low_rank(actor)]


def test_cli_export_loads_with_torch_alone_and_acts_as_load_policy(tiny, tmp_path):
    import adarl

    proc = cli("export", str(tiny))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr == ""
    path = tiny / "policy.pt"
    assert proc.stdout.startswith("exported the policy of ") and str(path) in proc.stdout
    pt2 = tmp_path / "policy.bin"  # any name: the .pt2 archive is written and read through a buffer
    proc = cli("export", str(tiny), "--format", "export", "-o", str(pt2))
    assert proc.returncode == 0, proc.stderr[-3000:]

    obs = _observations(2000, 11)
    torch.save(obs, tmp_path / "obs.pt")
    # a process that imports torch and nothing of adarl, TorchRL or tensordict (no PYTHONPATH to the repo either)
    proc = python(
        f"""
        import io, json, sys, torch
        obs = torch.load({str(tmp_path / "obs.pt")!r})
        extra = {{"adarl.json": ""}}
        program = torch.jit.load({str(path)!r}, _extra_files=extra)
        meta = json.loads(extra["adarl.json"])
        with torch.no_grad():
            ts, ts_one = program(obs), program(obs[0])
            ep = torch.export.load(io.BytesIO(open({str(pt2)!r}, "rb").read())).module()
            pt2 = ep(obs)
        torch.save({{"ts": ts, "ts_one": ts_one, "pt2": pt2}}, {str(tmp_path / "actions.pt")!r})
        print(json.dumps({{"meta": meta, "modules": sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})}}))
        """,
        cwd=tmp_path,
        pythonpath=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    answer = json.loads(proc.stdout.strip().splitlines()[-1])
    assert answer["modules"] == [], f"loading the export imported {answer['modules']}"
    got = torch.load(tmp_path / "actions.pt")

    actor = adarl.load_policy(tiny)
    want = _actor_actions(actor, obs)
    assert got["ts"].shape == want.shape == (2000, 3) and got["ts"].dtype == torch.float32
    assert float((got["ts"] - want).abs().max()) <= ATOL
    assert float((got["pt2"] - want).abs().max()) <= ATOL
    # one observation without a batch dimension (a matrix-vector product: rounding may differ from the batch's)
    assert torch.allclose(got["ts_one"], got["ts"][0], atol=1e-6, rtol=0)
    assert bool((want.abs() < 1).all()) and float(want.abs().max()) > 0.5  # saturating actions are compared too

    meta = answer["meta"]
    summary = json.loads((tiny / "summary.json").read_text())
    names = summary["layer_names"]
    want_ranks = {names[p].split(".", 1)[1]: summary["ranks"][p] for p in names if names[p].startswith("actor.")}
    assert {x["name"]: x["rank"] for x in meta["layers"]} == want_ranks
    assert _actor_ranks(actor) == [x["rank"] for x in meta["layers"]]
    assert want_ranks["layer1"] < 64, "the tiny run should have truncated the actor"
    assert {x["form"] for x in meta["layers"]} <= {"merged", "factored"}
    assert meta["observation_shape"] == [11] and meta["action_shape"] == [3] and meta["action_kind"] == "box"
    assert meta["action_low"] == [-1.0] * 3 and meta["action_high"] == [1.0] * 3
    assert meta["run_dir"] == str(tiny.resolve()) and meta["env_id"] == "Hopper-v5" and meta["recipe"] == "quickstart"
    assert meta["adarl_version"] == adarl.__version__ and meta["format"] == "torchscript"
    assert meta["observation_normalisation"] is None and meta["deterministic"] is True
    assert meta["check"]["max_abs_diff"] <= ATOL
    assert adarl.read_export_metadata(path) == meta


def test_exported_policy_predicts_like_sb3_without_torchrl(tiny, tmp_path):
    import adarl

    path = tmp_path / "policy.pt"
    adarl.export_policy(tiny, path)
    obs = _observations(64, 11, seed=2).numpy().astype(np.float64)  # gymnasium's observations are float64
    np.save(tmp_path / "obs.npy", obs)
    proc = python(
        f"""
        import json, sys
        import numpy as np
        from adarl import ExportedPolicy
        policy = ExportedPolicy({str(path)!r})
        obs = np.load({str(tmp_path / "obs.npy")!r})
        batch, state = policy.predict(obs)
        one, _ = policy.predict(obs[0], state=None, episode_start=np.array([True]), deterministic=True)
        np.save({str(tmp_path / "batch.npy")!r}, batch)
        np.save({str(tmp_path / "one.npy")!r}, one)
        print(json.dumps({{"state": state, "modules": sorted({{m.split(".")[0] for m in sys.modules}} & {{"torchrl",
              "tensordict", "gymnasium", "mujoco"}}), "repr": repr(policy)}}))
        """,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    answer = json.loads(proc.stdout.strip().splitlines()[-1])
    assert answer["state"] is None and answer["modules"] == []
    assert "policy.pt" in answer["repr"] and "layer1: rank" in answer["repr"]
    batch, one = np.load(tmp_path / "batch.npy"), np.load(tmp_path / "one.npy")
    assert batch.shape == (64, 3) and batch.dtype == np.float32 and one.shape == (3,)
    want = _actor_actions(adarl.load_policy(tiny), torch.as_tensor(obs, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(batch, want, atol=ATOL, rtol=0)
    np.testing.assert_allclose(one, batch[0], atol=1e-6, rtol=0)

    policy = adarl.ExportedPolicy(path)
    with pytest.raises(ValueError, match="deterministic actor"):
        policy.predict(obs, deterministic=False)
    with pytest.raises(ValueError, match=r"takes \(11,\)"):
        policy.predict(np.zeros(5))
    with pytest.raises(ValueError, match="takes"):
        policy.predict(np.zeros((2, 3, 11)))
    assert torch.allclose(policy(torch.as_tensor(obs[:4], dtype=torch.float32)), torch.as_tensor(batch[:4]), atol=1e-6)


def test_truncated_ranks_merged_and_factored_give_the_actors_actions(tiny, tmp_path):
    from adarl.core.lowrank import iter_low_rank
    from adarl.runtime.export import export_actor
    from adarl.runtime.exported import ExportedPolicy
    from adarl.runtime.policy import load_policy

    actor = load_policy(tiny)
    for (_, layer), rank in zip(iter_low_rank(actor), (3, 5)):
        layer.truncate_(rank)
    obs = _observations(1000, 11, seed=3)
    want = _actor_actions(actor, obs)
    sizes = {}
    for layers in ("auto", "merged", "factored"):
        result = export_actor(actor, tmp_path / f"{layers}.pt", layers=layers)
        meta = result.metadata
        assert [(x["name"], x["rank"], x["max_rank"]) for x in meta["layers"]] == [("layer0", 3, 11), ("layer1", 5, 64)]
        forms = [x["form"] for x in meta["layers"]]
        assert forms == (["merged", "merged"] if layers == "auto" else [layers] * 2)  # 64 wide: merged is cheaper
        got = ExportedPolicy(result.path)(obs)
        assert float((got - want).abs().max()) <= ATOL, layers
        sizes[layers] = meta["parameters"]
    # factored: W2 (r x in) and W1 (out x r) per layer, the loc rows of the head; merged: the dense product
    assert sizes["factored"] == (3 * 11 + 64 * 3 + 64) + (5 * 64 + 64 * 5 + 64) + (64 * 3 + 3)
    assert sizes["merged"] == (11 * 64 + 64) + (64 * 64 + 64) + (64 * 3 + 3)


def test_auto_factors_wide_layers_at_low_rank_only():
    from adarl.core.lowrank import iter_low_rank
    from adarl.runtime.builders.common import spec_env
    from adarl.runtime.builders.sac import make_recipe_actor
    from adarl.runtime.config import load_recipe
    from adarl.runtime.export import CALL_COST_MACS, deterministic_program

    box = {"observation_dim": 11, "action_kind": "box", "action_low": -torch.ones(3), "action_high": torch.ones(3)}
    actor = make_recipe_actor(load_recipe("quickstart", ["network.actor.num_cells=[256,256]"]), spec_env(box, "cpu"))
    actor.requires_grad_(False)
    forms = lambda: [(c.rank, c.form) for c in deterministic_program(actor).layers]  # noqa: E731
    assert forms() == [(11, "merged"), (256, "merged")]
    layers = [layer for _, layer in iter_low_rank(actor)]
    layers[1].truncate_(64)  # 64 * 512 + 16384 < 65536
    layers[0].truncate_(2)  # 11 -> 256: 2 * 267 + 16384 > 2816, two calls cost more than they save
    assert forms() == [(2, "merged"), (64, "factored")]
    assert 96 * 512 + CALL_COST_MACS >= 256 * 256 > 95 * 512 + CALL_COST_MACS  # the 256x256 crossover is at 96


def test_ppo_run_exports_with_its_observation_normalisation_baked_in(tmp_path):
    import adarl
    from adarl.runtime.policy import load_policy_with_info

    out = tmp_path / "run"
    proc = cli("run", "baselines/hopper_rnac_ipm", *TINY_PPO, "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    loaded = load_policy_with_info(out)
    norm = loaded.actor.module[0].module[0][0]
    assert type(norm).__name__ == "RunningObsNorm" and int(norm.count) > 0
    result = adarl.export_policy(out, tmp_path / "ppo.pt")
    meta = result.metadata
    assert meta["policy"] == "clipped_gaussian" and meta["observation_normalisation"]["count"] == int(norm.count)
    obs = norm.mean.float() + norm.std.float() * _observations(1000, 11, seed=4)
    want = _actor_actions(loaded.actor, obs)
    got = adarl.ExportedPolicy(result.path)(obs)
    assert float((got - want).abs().max()) <= ATOL
    # without the statistics the actions would differ: the normalisation is really inside the program
    raw = _actor_actions(loaded.actor, (obs - norm.mean.float()) / (norm.std.float() + norm.eps))
    assert float((got - raw).abs().max()) > 1e-3


def _recipe_actor(recipe: str, specs: dict, overrides=()):
    from adarl.runtime.builders.common import spec_env
    from adarl.runtime.builders.sac import make_recipe_actor
    from adarl.runtime.config import load_recipe

    torch.manual_seed(0)
    return make_recipe_actor(load_recipe(recipe, list(overrides)), spec_env(specs, "cpu")).requires_grad_(False)


def test_discrete_actor_exports_its_one_hot_action_and_predict_gives_indices(tmp_path):
    from adarl.runtime.export import export_actor
    from adarl.runtime.exported import ExportedPolicy

    actor = _recipe_actor("cartpole_adarl", {"observation_dim": 4, "action_kind": "one_hot", "action_n": 2})
    result = export_actor(actor, tmp_path / "cartpole.pt")
    assert result.metadata["action_kind"] == "one_hot" and result.metadata["action_shape"] == [2]
    obs = _observations(500, 4, seed=5)
    want = _actor_actions(actor, obs)
    policy = ExportedPolicy(result.path)
    got = policy(obs)
    assert got.dtype == want.dtype == torch.long and torch.equal(got, want)
    index, _ = policy.predict(obs.numpy())
    assert index.shape == (500,) and np.array_equal(index, want.argmax(-1).numpy())
    assert int(policy.predict(obs[0].numpy())[0]) == int(want[0].argmax())


@pytest.mark.parametrize(
    "recipe, overrides",
    [
        ("baselines/hopper_parseval", []),  # diagonal and input scale layers, dense
        ("baselines/hopper_sparse", []),  # the 1024-wide k-winners-take-all layer
        ("quickstart", ["network.actor.activation=tanh"]),
    ],
)
def test_baseline_networks_and_an_asymmetric_box_export(recipe, overrides, tmp_path):
    from adarl.runtime.export import export_actor
    from adarl.runtime.exported import ExportedPolicy

    box = {
        "observation_dim": 11,
        "action_kind": "box",
        "action_low": torch.tensor([-0.4, -2.0, 0.0]),
        "action_high": torch.tensor([0.4, 1.0, 3.0]),
    }
    actor = _recipe_actor(recipe, box, overrides)
    for fmt in ("torchscript", "export"):
        result = export_actor(actor, tmp_path / f"policy.{fmt}", format=fmt)
        assert result.metadata["action_low"] == pytest.approx([-0.4, -2.0, 0.0])
        obs = _observations(300, 11, seed=6)
        want = _actor_actions(actor, obs)
        policy = ExportedPolicy(result.path)
        got = policy(obs)
        assert float((got - want).abs().max()) <= ATOL, fmt
        assert bool((got >= box["action_low"]).all()) and bool((got <= box["action_high"]).all())
        one, _ = policy.predict(obs[0].numpy())  # the .pt2 program takes batches only: predict adds the dimension
        batch, _ = policy.predict(obs[:5].numpy())
        assert one.shape == (3,) and batch.shape == (5, 3)
        np.testing.assert_allclose(batch, want[:5].numpy(), atol=ATOL, rtol=0)


@pytest.mark.parametrize("clamp", [False, True])
def test_a_td3_actor_exports_its_tanh_action_on_an_asymmetric_box(clamp, tmp_path):
    """TD3's and DDPG's actor (network -> ``param`` -> TorchRL's ``TanhModule`` -> ``action``), truncated, exports
    the action the actor gives, inside the box; ``clamp=True`` (a user's TanhModule) clamps as TorchRL does."""
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torch import nn
    from torchrl.modules import TanhModule

    from adarl.core.lowrank import iter_low_rank
    from adarl.errors import AdaRLValueError
    from adarl.runtime.builders.common import spec_env
    from adarl.runtime.builders.td3 import make_recipe_td3_actor
    from adarl.runtime.config import load_recipe
    from adarl.runtime.export import export_actor
    from adarl.runtime.exported import ExportedPolicy

    box = {
        "observation_dim": 11,
        "action_kind": "box",
        "action_low": torch.tensor([-0.4, -2.0, 0.0]),
        "action_high": torch.tensor([0.4, 1.0, 3.0]),
    }
    torch.manual_seed(0)
    env = spec_env(box, "cpu")
    actor = make_recipe_td3_actor(load_recipe("quickstart", ["algorithm.name=td3"]), env).requires_grad_(False)
    for _, layer in iter_low_rank(actor):
        layer.truncate_(layer.rank // 2)
    net, head = actor.module
    if clamp:
        actor = TensorDictSequential(
            net, TanhModule(in_keys=head.in_keys, out_keys=head.out_keys, spec=head.spec["action"], clamp=True)
        )
    obs = _observations(300, 11, seed=7)
    obs[:3] *= 1e3  # saturated: tanh(x) = +-1 up to the clamp
    want = _actor_actions(actor, obs)
    for fmt in ("torchscript", "export"):
        result = export_actor(actor, tmp_path / f"td3.{fmt}", format=fmt)
        assert result.metadata["policy"] == "deterministic_tanh" and result.metadata["action_kind"] == "box"
        assert result.metadata["action_high"] == pytest.approx([0.4, 1.0, 3.0])
        assert [layer["rank"] for layer in result.metadata["layers"]] == [5, 32]
        got = ExportedPolicy(result.path)(obs)
        assert float((got - want).abs().max()) <= ATOL, fmt
        assert bool((got >= box["action_low"]).all()) and bool((got <= box["action_high"]).all())
    # a TanhModule actor whose network reads another key is refused by name
    odd = TensorDictSequential(TensorDictModule(nn.Linear(11, 3), in_keys=["pixels"], out_keys=["param"]), head)
    with pytest.raises(AdaRLValueError, match="its network reads \\['pixels'\\]"):
        export_actor(odd, tmp_path / "odd.pt")


def test_what_cannot_be_exported_is_refused_by_name(tmp_path):
    from tensordict.nn import NormalParamExtractor, TensorDictModule
    from torch import nn
    from torchrl.modules import ProbabilisticActor, TanhNormal
    from torchrl.modules.distributions import IndependentNormal

    from adarl.errors import AdaRLValueError
    from adarl.runtime.export import export_actor

    def actor(dist, **kwargs):
        net = TensorDictModule(
            nn.Sequential(nn.Linear(4, 4), NormalParamExtractor()), in_keys=["observation"], out_keys=["loc", "scale"]
        )
        return ProbabilisticActor(net, in_keys=["loc", "scale"], distribution_class=dist, distribution_kwargs=kwargs)

    with pytest.raises(AdaRLValueError, match="distribution IndependentNormal"):
        export_actor(actor(IndependentNormal), tmp_path / "a.pt")
    with pytest.raises(AdaRLValueError, match="tanh_loc"):
        export_actor(actor(TanhNormal, tanh_loc=True), tmp_path / "a.pt")
    with pytest.raises(AdaRLValueError, match="ProbabilisticActor"):
        export_actor(nn.Linear(2, 2), tmp_path / "a.pt")
    with pytest.raises(AdaRLValueError, match="format must be one of"):
        export_actor(actor(TanhNormal), tmp_path / "a.pt", format="tflite")
    assert not (tmp_path / "a.pt").exists()


def test_cli_errors_are_one_line_and_nothing_is_overwritten(tiny, tmp_path, capsys):
    def run(*args: str) -> tuple[int, str]:
        code = cli_main(["export", *args])
        err = capsys.readouterr().err
        return code, err

    # a missing, an empty and a corrupt run folder
    empty = tmp_path / "empty"
    empty.mkdir()
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "recipe.yaml").write_text((tiny / "recipe.yaml").read_text())
    (corrupt / "checkpoints").mkdir()
    (corrupt / "checkpoints" / "ckpt-000000001700.pt").write_bytes(b"PK\x03\x04 not a checkpoint")
    for folder, words in (
        (tmp_path / "missing", ["neither a run folder nor a checkpoint"]),
        (empty, ["not an adarl run folder"]),
        (corrupt, ["corrupt"]),
    ):
        code, err = run(str(folder))
        assert code != 0, folder
        assert err.startswith("adarl: error: ") and len(err.strip().splitlines()) == 1, err
        assert "Traceback" not in err
        for word in words:
            assert word in err, (word, err)
        assert not (folder / "policy.pt").exists()

    # an existing file is kept unless --overwrite
    target = tmp_path / "p.pt"
    target.write_bytes(b"keep me")
    code, err = run(str(tiny), "-o", str(target))
    assert code == 2 and "exists; pass --overwrite" in err and target.read_bytes() == b"keep me"
    assert cli_main(["export", str(tiny), "-o", str(target), "--overwrite"]) == 0
    assert zipfile.is_zipfile(target) and "exported the policy of" in capsys.readouterr().out

    code, err = run(str(tiny), "-o", str(tmp_path / "nowhere" / "p.pt"))
    assert code == 2 and "no such folder" in err
    code, err = run(str(tiny), "-o", str(tmp_path))
    assert code == 2 and "is a folder" in err
    if importlib_missing("onnx") or importlib_missing("onnxscript"):
        code, err = run(str(tiny), "--format", "onnx", "-o", str(tmp_path / "p.onnx"))
        assert code == 2 and "pip install" in err and not (tmp_path / "p.onnx").exists()
    proc = cli("export", str(tiny), "--format", "tflite")
    assert proc.returncode == 2 and "invalid choice: 'tflite'" in proc.stderr


def importlib_missing(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is None


def test_onnx_when_its_packages_are_installed(tiny, tmp_path):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    import adarl

    result = adarl.export_policy(tiny, tmp_path / "policy.onnx", format="onnx")
    assert result.path.is_file() and result.metadata["format"] == "onnx"
    ort = pytest.importorskip("onnxruntime")
    obs = _observations(100, 11, seed=7)
    (got,) = ort.InferenceSession(str(result.path)).run(None, {"observation": obs.numpy()})
    want = _actor_actions(adarl.load_policy(tiny), obs).numpy()
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)


def test_import_adarl_stays_light_and_names_the_export_api():
    proc = python(
        "import sys, adarl\n"
        "heavy = sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'torchrl', 'numpy'})\n"
        "from adarl import ExportedPolicy, export_policy, read_export_metadata\n"
        "print(heavy, ExportedPolicy.__module__, export_policy.__module__)\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'torchrl', 'tensordict'}))"
    )
    assert proc.returncode == 0, proc.stderr
    first, second = proc.stdout.strip().splitlines()
    assert first == "[] adarl.runtime.exported adarl.runtime.export"
    assert second == "['tensordict', 'torchrl']"  # export_policy itself needs TorchRL (load_policy); the loader not
