"""A trained policy as a deployable file (issue 31, point 7): `adarl export RUN` / `adarl.export_policy` write the
deterministic actor as a TorchScript (or torch.export) program that torch alone loads and that acts as
`adarl.load_policy` does; `adarl.ExportedPolicy` gives it SB3's `predict(obs)` on numpy. Low-rank layers are merged
or factored per layer; truncated ranks, the PPO baselines' observation normalisation and a discrete actor export too;
what cannot be exported, and every bad command line, is one clear line. No timing is asserted here
(benchmarks/export_speed.py measures)."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from _helpers import RANK_EVENTS, tiny, tiny_ppo
from tensordict import TensorDict

from adarl.cli import main as cli_main

REPO = Path(__file__).resolve().parents[1]
# tests/test_policy.py's tiny run: rank events truncate the actor's second layer
TINY = tiny(*RANK_EVENTS)
TINY_PPO = tiny_ppo("eval.max_steps=20")
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
def tiny(rank_events_run):
    """``adarl run quickstart TINY -o OUT --quiet``: conftest's rank_events_run (made once for this file,
    test_cli_e2e.py and test_policy.py)."""
    out, proc = rank_events_run
    assert proc.args[3:] == ["run", "quickstart", *TINY, "-o", str(out), "--quiet"], proc.args
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


# --- loading never executes (issue 46, points 1 and 7) ---------------------------------------------------------
# An export is a zip archive; ExportedPolicy checks it before torch reads a byte of it: CRCs, the sha256 of every
# member recorded at export, and (a .pt2) that nothing in it is code in disguise (torch.export.load would otherwise
# unpickle its sample inputs with weights_only=False, eval its shape expressions with sympy and exec its guards).


class _Evil:
    """A pickle that runs a command when unpickled: it would create ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


@pytest.fixture(scope="module")
def small_exports(tmp_path_factory) -> dict[str, Path]:
    """A .pt2 and a .pt of quickstart's actor (low-rank layers, TanhNormal), written by adarl's exporter."""
    from adarl.runtime.export import export_actor

    actor = _recipe_actor(
        "quickstart",
        {"observation_dim": 11, "action_kind": "box", "action_low": -torch.ones(3), "action_high": torch.ones(3)},
    )
    folder = tmp_path_factory.mktemp("small_exports")
    return {
        "export": export_actor(actor, folder / "policy.pt2", format="export").path,
        "torchscript": export_actor(actor, folder / "policy.pt").path,
    }


def _members(path: Path) -> tuple[str, dict[str, bytes]]:
    """The archive's root folder and its members (names relative to it), in order."""
    with zipfile.ZipFile(path) as z:
        root = z.namelist()[0].split("/")[0]
        return root, {n.split("/", 1)[1]: z.read(n) for n in z.namelist()}


def _write_members(path: Path, root: str, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        for name, data in members.items():
            z.writestr(f"{root}/{name}", data)
    return path


def _tampered(src: Path, dst: Path, change, *, reseal: bool) -> Path:
    """``src`` with ``change(members)`` applied (members: name -> bytes, edited in place); ``reseal``: the sha256
    manifest recomputed as an attacker who knows the format would (so only the content checks stand)."""
    import hashlib

    root, members = _members(src)
    change(members)
    if reseal:
        meta = json.loads(members["extra/adarl.json"])
        meta["sha256"] = {n: hashlib.sha256(d).hexdigest() for n, d in members.items() if n != "extra/adarl.json"}
        members["extra/adarl.json"] = json.dumps(meta).encode()
    return _write_members(dst, root, members)


def _program_json(members: dict[str, bytes], edit) -> None:
    program = json.loads(members["models/model.json"])
    edit(program)
    members["models/model.json"] = json.dumps(program).encode()


def _refused(path: Path, *words: str):
    """ExportedPolicy and read_export_metadata refuse ``path`` with one ExportFileError naming it and ``words``."""
    from adarl.errors import ExportFileError
    from adarl.runtime.exported import ExportedPolicy

    with pytest.raises(ExportFileError) as info:
        ExportedPolicy(path)
    message = str(info.value)
    assert str(path) in message and info.value.path is not None, message
    for word in words:
        assert word in message, (word, message)
    assert "weights_only" not in message and "Traceback" not in message
    return info.value


def _sample_inputs_payload(marker):
    return lambda m: m.__setitem__("data/sample_inputs/model.pt", pickle.dumps(_Evil(marker)))


@pytest.mark.parametrize("reseal", [False, True], ids=["as-tampered", "manifest-recomputed"])
def test_a_pickle_payload_in_a_pt2_export_runs_nothing_and_is_refused_by_name(small_exports, tmp_path, reseal):
    """The attack of issue 46, point 1: torch.export.load retries the sample inputs with weights_only=False."""
    marker = tmp_path / "pwned"
    evil = _tampered(small_exports["export"], tmp_path / "evil.pt2", _sample_inputs_payload(marker), reseal=reseal)
    err = _refused(evil, "data/sample_inputs/model.pt", *(["Python object", "posix.system"] if reseal else ["sha256"]))
    assert "nothing in it ran" in str(err) or not reseal
    assert not marker.exists(), "the pickle in the export ran"


@pytest.mark.parametrize(
    "attack", ["guards", "shape expression", "operation", "parameter name", "aoti library", "object constant"]
)
def test_nothing_else_in_a_pt2_export_runs_at_load_either(small_exports, tmp_path, attack):
    """What torch's deserialiser would execute besides pickles, each in a resealed file (the sha256 manifest is an
    integrity check, not a signature: whoever can rewrite the file can rewrite it), each refused by name."""
    marker = tmp_path / "pwned"
    run = f"__import__('os').system('touch {marker}')"

    def guards(p):  # exec'd by ExportedProgram.module() into a _guards_fn
        p["guards_code"] = [f"{run} == 0"]

    def shape_expression(p):  # sympy.sympify (eval) of every symbolic size
        text = json.dumps(p).replace("Symbol('s", f"0*{run} + Symbol('s", 1)
        p.clear(), p.update(json.loads(text))

    def operation(p):  # any callable under torch becomes a node of the program
        p["graph_module"]["graph"]["nodes"][0]["target"] = "torch.serialization.os.system"

    def parameter_name(p):  # an attribute name is pasted into the GraphModule's generated code
        spec = next(s for s in p["graph_module"]["signature"]["input_specs"] if "parameter" in s)
        spec["parameter"]["parameter_name"] = f'x"), {run}, getattr(self, "y'

    def object_constant(m):  # a constant torch.export.load gives to pickle.loads
        m["data/constants/opaque_obj_0"] = pickle.dumps(_Evil(marker))
        config = json.loads(m["data/constants/model_constants_config.json"])
        config["config"]["c"] = {
            "path_name": "opaque_obj_0",
            "is_param": False,
            "use_pickle": True,
            "tensor_meta": None,
        }
        m["data/constants/model_constants_config.json"] = json.dumps(config).encode()

    changes = {
        "guards": lambda m: _program_json(m, guards),
        "shape expression": lambda m: _program_json(m, shape_expression),
        "operation": lambda m: _program_json(m, operation),
        "parameter name": lambda m: _program_json(m, parameter_name),
        "aoti library": lambda m: m.__setitem__("data/aotinductor/model/model.so", b"\x7fELF not really"),
        "object constant": object_constant,
    }
    words = {
        "guards": ["guards_code"],
        "shape expression": ["symbolic expression", "__import__"],
        "operation": ["torch.serialization.os.system"],
        "parameter name": ['x"), __import__'],
        "aoti library": ["data/aotinductor/model/model.so"],
        "object constant": ["data/constants/opaque_obj_0"],
    }[attack]
    evil = _tampered(small_exports["export"], tmp_path / "evil.pt2", changes[attack], reseal=True)
    _refused(evil, *words)
    assert not marker.exists()


@pytest.mark.parametrize("fmt, weights", [("export", "data/weights/weight_0"), ("torchscript", "data/0")])
def test_a_flipped_byte_in_the_weights_is_refused(small_exports, tmp_path, fmt, weights):
    """Issue 46, point 7: bit flips in the weights loaded silently (actions differed on 479 of 1000 observations)."""
    src = small_exports[fmt]
    root, members = _members(src)
    flipped = bytearray(members[weights])
    flipped[5] ^= 0x10
    # in place, as a disk or a copy damages it: the zip's CRC no longer matches
    raw = bytearray(src.read_bytes())
    at = raw.index(members[weights])
    raw[at + 5] ^= 0x10
    (tmp_path / "crc").mkdir()
    damaged = tmp_path / "crc" / src.name
    damaged.write_bytes(bytes(raw))
    _refused(damaged, weights, "CRC")
    # rewritten with a consistent CRC (a tool that re-zips, or on purpose): the sha256 recorded at export refuses it
    members[weights] = bytes(flipped)
    edited = _write_members(tmp_path / src.name, root, members)
    _refused(edited, weights, "sha256", "modified or corrupted after export")


@pytest.mark.parametrize("fmt", ["export", "torchscript"])
def test_truncated_and_empty_exports_are_refused_with_an_adarl_error(small_exports, tmp_path, fmt):
    from adarl.errors import ExportFileError
    from adarl.runtime.exported import read_export_metadata

    data = small_exports[fmt].read_bytes()
    empty = tmp_path / f"empty{small_exports[fmt].suffix}"
    empty.write_bytes(b"")
    _refused(empty, "empty")
    for n, keep in enumerate((len(data) - 10, len(data) // 2, 100, 4)):
        cut = tmp_path / f"cut{n}{small_exports[fmt].suffix}"
        cut.write_bytes(data[:keep])
        _refused(cut, "truncated")
        with pytest.raises(ExportFileError, match="truncated"):
            read_export_metadata(cut)


@pytest.mark.parametrize("fmt", ["export", "torchscript"])
def test_exports_name_their_sha256_and_load_with_torch_alone(small_exports, fmt):
    import hashlib

    from adarl.runtime.exported import ExportedPolicy, read_export_metadata

    umask = os.umask(0o022)
    os.umask(umask)
    assert small_exports[fmt].stat().st_mode & 0o777 == 0o666 & ~umask  # was 0600 (mkstemp): issue 48.6
    root, members = _members(small_exports[fmt])
    meta = read_export_metadata(small_exports[fmt])
    assert meta["sha256"] == {n: hashlib.sha256(d).hexdigest() for n, d in members.items() if n != "extra/adarl.json"}
    with zipfile.ZipFile(small_exports[fmt]) as z:
        assert z.testzip() is None
    obs = _observations(50, 11, seed=9)
    if fmt == "export":  # torch alone still reads it, metadata included
        extra = {"adarl.json": ""}
        program = torch.export.load(small_exports[fmt], extra_files=extra).module()
    else:
        extra = {"adarl.json": ""}
        program = torch.jit.load(str(small_exports[fmt]), _extra_files=extra)
    assert json.loads(extra["adarl.json"]) == meta
    policy = ExportedPolicy(small_exports[fmt])
    with torch.no_grad():
        assert torch.equal(program(obs), policy(obs))
    # one observation gives one action, other leading dimensions theirs (a .pt2 raised IndexError on one: issue 48.6)
    assert torch.allclose(policy(obs[0]), policy(obs)[0], atol=1e-6) and policy(obs.reshape(5, 10, 11)).shape == (
        5,
        10,
        3,
    )
    with pytest.raises(ValueError, match=r"observation of shape \(4,\): this policy takes \(\.\.\., 11\)"):
        policy(torch.zeros(4))


def test_a_pickle_payload_in_a_torchscript_export_runs_nothing(small_exports, tmp_path):
    marker = tmp_path / "pwned"

    def payload(m):
        m["data.pkl"] = pickle.dumps(_Evil(marker))

    for reseal in (False, True):
        evil = _tampered(small_exports["torchscript"], tmp_path / f"evil{reseal}.pt", payload, reseal=reseal)
        _refused(evil, "sha256" if not reseal else "cannot be loaded")
    assert not marker.exists()


def test_an_export_from_before_the_sha256_still_loads_with_a_warning(small_exports, tmp_path):
    from adarl.errors import AdaRLWarning
    from adarl.runtime.exported import ExportedPolicy

    def strip(m):
        meta = json.loads(m["extra/adarl.json"])
        del meta["sha256"]
        m["extra/adarl.json"] = json.dumps(meta).encode()

    obs = _observations(50, 11, seed=10)
    marker = tmp_path / "pwned"
    for fmt, path in small_exports.items():
        old = _tampered(path, tmp_path / f"old{path.suffix}", strip, reseal=False)
        with pytest.warns(AdaRLWarning, match="sha256") as record:
            policy = ExportedPolicy(old)
        assert str(old) in str(record[0].message)
        assert torch.equal(policy(obs), ExportedPolicy(path)(obs))
        if fmt == "export":  # still through the safe path: a payload in an unsealed file is refused as well
            evil = _tampered(old, tmp_path / "old-evil.pt2", _sample_inputs_payload(marker), reseal=False)
            with pytest.warns(AdaRLWarning, match="sha256"):
                _refused(evil, "data/sample_inputs/model.pt", "Python object")
    assert not marker.exists()


def test_the_cli_names_a_bad_export_in_one_line(small_exports, tmp_path, capsys):
    """eval, play and export take a run folder or a checkpoint: an export given to them is named as one, in one line,
    and a tampered one runs nothing there either."""
    marker = tmp_path / "pwned"
    evil = _tampered(small_exports["export"], tmp_path / "evil.pt2", _sample_inputs_payload(marker), reseal=True)
    cut = tmp_path / "cut.pt2"
    cut.write_bytes(small_exports["export"].read_bytes()[:500])
    for path in (small_exports["export"], small_exports["torchscript"], evil, cut):
        for command in (["play", str(path), "--episodes", "1"], ["export", str(path), "-o", str(tmp_path / "x.pt")]):
            code = cli_main(command)
            err = capsys.readouterr().err
            assert code != 0 and err.startswith("adarl: error: ") and len(err.strip().splitlines()) == 1, err
            assert str(path) in err and "Traceback" not in err
        assert "exported policy" in err or path == cut
    assert not marker.exists()
