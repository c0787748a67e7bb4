"""TQC, CrossQ and REDQ from a recipe (issue 48, point 2): ``algorithm.name: tqc``, ``crossq``, ``redq`` run
TorchRL's own TQCLoss, CrossQLoss and REDQLoss on the ``sac`` loop (adarl.runtime.builders.sac_variants).

One tiny ``adarl run`` of each shipped baseline recipe (recipes/baselines/hopper_{tqc,crossq,redq}.yaml, shrunk):
the loss trained is the named one (plugins.json, and the shapes in the checkpoint: TQC's quantile heads, REDQ's
ensemble, CrossQ's running statistics and no target network), rank events happened; CrossQ's policy then goes
through ``adarl eval``, ``load_policy`` and ``adarl export`` (its Batch Renormalization layers included); and a run
resumed from an earlier checkpoint ends exactly as the uninterrupted one. The options' validation errors are
checked without running anything.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from _helpers import REPO, adarl, adarl_calls, tiny

from adarl import plugins
from adarl.errors import RecipeError
from adarl.runtime.config import load_recipe

# Hopper, tiny: updates from frame 100 (batch 32, 16-wide networks), a rank event every 100 updates (three), a
# checkpoint every 200 frames
TINY = tiny(
    "collector.total_frames=400",
    "collector.init_random_frames=100",
    "algorithm.update_after=100",
    "replay.size=1000",
    "replay.warm_start.frames=50",
    "rank.interval=100",
    "eval.interval=200",
    "eval.episodes=1",
    "eval.max_steps=20",
    "checkpoint.interval=200",
    "network.actor.num_cells=[16,16]",
    "network.critic.num_cells=[16,16]",
)
#: each loss, small: its recipe, the loss class, and options that keep the run to seconds
LOSSES = {
    "tqc": (
        "TQCLoss",
        [
            "algorithm.options.num_critics=2",
            "algorithm.options.num_quantiles=5",
            "algorithm.options.top_quantiles_to_drop_per_net=1",
        ],
    ),
    "crossq": ("CrossQLoss", ["algorithm.options.renorm_warmup_steps=50", "algorithm.options.policy_delay=2"]),
    "redq": (
        "REDQLoss",
        [
            "algorithm.options.ensemble_size=3",
            "algorithm.options.utd_ratio=1",
            "algorithm.options.policy_delay=2",
            "collector.total_frames=400",
        ],
    ),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """One tiny run of each baseline recipe (module scope: the tests below read them)."""
    root = tmp_path_factory.mktemp("more_losses")
    out = {}
    for name, (_, overrides) in LOSSES.items():
        run = root / name
        recipe = REPO / "recipes" / "baselines" / f"hopper_{name}.yaml"
        proc = adarl("run", str(recipe), *TINY, *overrides, "-o", str(run), "--quiet")
        assert proc.returncode == 0, proc.stderr[-3000:]
        out[name] = run
    return out


def _loss_state(run: Path) -> dict[str, torch.Tensor]:
    ckpt = sorted((run / "checkpoints").glob("ckpt-*.pt"))[-1]
    return torch.load(ckpt, map_location="cpu", weights_only=False)["state"]["loss"]


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LOSSES))
def test_each_loss_runs_from_its_recipe_with_rank_events(runs, name):
    run, (loss_class, _) = runs[name], LOSSES[name]
    used = json.loads((run / "plugins.json").read_text())["algorithm"]
    assert used == {**used, "name": name, "base": "sac", "loss": f"torchrl.objectives:{loss_class}"}
    summary = json.loads((run / "summary.json").read_text())
    assert summary["frames"] == 400 and summary["rank_events"] >= 2 and summary["warm_start_frames"] > 0, summary
    events = json.loads((run / "ranks.json").read_text())
    assert len(events) == summary["rank_events"]
    assert {r["network"] for e in events for r in e["layers"]} == {"actor", "critic"}
    state = _loss_state(run)
    critic = {k: v for k, v in state.items() if k.startswith("qvalue_network_params.")}
    heads = [v for k, v in critic.items() if k.endswith(".bias") and v.dim() == 2]
    if name == "tqc":  # 2 critics of 5 atoms each
        assert heads[-1].shape == (2, 5)
    elif name == "redq":  # an ensemble of 3 one-output critics, with targets
        assert heads[-1].shape == (3, 1) and any(k.startswith("target_qvalue_network_params.") for k in state)
    else:  # CrossQ: Batch Renormalization's running statistics, trained, and no target network
        stats = [v for k, v in critic.items() if k.endswith("running_mean")]
        assert len(stats) == 3 and all(bool((s != 0).any()) for s in stats)
        assert not any(k.startswith("target_") for k in state)


@pytest.mark.slow
def test_crossq_evaluates_loads_and_exports_with_its_batch_renorm_layers(runs, tmp_path):
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from adarl import ExportedPolicy, load_policy

    run = runs["crossq"]
    out = tmp_path / "policy.pt"
    # `adarl eval` and `adarl export` in one process (each pays the torch import otherwise)
    proc, exported = adarl_calls(("eval", str(run), "--episodes", "1"), ("export", str(run), "-o", str(out)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "eval_nominal.json").read_text())["episodes"] == 1
    policy = load_policy(run)
    norms = [m for m in policy.modules() if type(m).__name__ == "BatchRenormLayer"]
    assert len(norms) == 3 and not policy.training  # evaluation reads the running statistics
    assert all(bool((m.running_var != 1).any()) for m in norms)  # the trained statistics were loaded
    assert exported.returncode == 0, exported.stderr[-3000:]
    obs = torch.randn(5, 11)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        want = policy(TensorDict(observation=obs, batch_size=[5]))["action"]
    got = torch.as_tensor(ExportedPolicy(out).predict(obs.numpy())[0])
    assert float((got - want).abs().max()) <= 1e-5


def _results(run: Path) -> dict[str, str]:
    """Every metric file and the evaluation/rank records, as text (wall-clock fields left out)."""
    root = run / "metrics" / "scalars"
    out = {
        f"metrics/{p.relative_to(root).as_posix()}": p.read_text()
        for p in sorted(root.rglob("*.csv"))
        if p.relative_to(root).parts[0] != "time"
    }
    out["eval.csv"] = (run / "eval.csv").read_text()
    out["ranks.json"] = (run / "ranks.json").read_text()
    summary = json.loads((run / "summary.json").read_text())
    for k in ("wall_time_s", "updates_per_s"):
        summary.pop(k)
    out["summary.json"] = json.dumps(summary, sort_keys=True)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", ["redq"])
def test_a_run_resumed_from_an_earlier_checkpoint_ends_as_the_uninterrupted_one(runs, name, tmp_path):
    """REDQ draws its M critics from torch's global generator: the checkpoint must carry it."""
    ref, resumed = runs[name], tmp_path / name
    shutil.copytree(ref, resumed)
    ckpts = sorted((resumed / "checkpoints").glob("ckpt-*.pt"))
    middle = [c for c in ckpts if 0 < int(c.stem[5:]) < 400]
    assert middle, [c.name for c in ckpts]
    for path in (resumed / "checkpoints").iterdir():  # everything after the middle checkpoint is gone
        frames = path.stem.rpartition("-")[2]
        if path.name == "best.pt" or (frames.isdigit() and int(frames) > int(middle[-1].stem[5:])):
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    (resumed / "summary.json").unlink()
    proc = adarl("resume", str(resumed), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    want, got = _results(ref), _results(resumed)
    assert sorted(got) == sorted(want)
    for key in want:
        assert got[key] == want[key], f"{key} differs from the uninterrupted run"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["algorithm.name=redq", "algorithm.options.subset_size=10"], "must be < ensemble_size (10)"),
        (["algorithm.name=redq", "algorithm.options.ensemble_size=1"], "greater than or equal to 2"),
        (["algorithm.name=redq", "algorithm.utd_ratio=5"], "is set by algorithm.options.utd_ratio (20.0)"),
        (["algorithm.name=redq", "algorithm.options.G=5"], "unknown option of algorithm 'redq'; allowed:"),
        (["algorithm.name=tqc", "algorithm.options.top_quantiles_to_drop_per_net=25"], "must be < num_quantiles"),
        (["algorithm.name=tqc", "algorithm.num_qvalue_nets=3"], "is set by algorithm.options.num_critics (5)"),
        (["algorithm.name=tqc", "algorithm.loss_function=l1"], "quantile Huber loss"),
        (["algorithm.name=tqc", "algorithm.fused=true"], "computes SACLoss only"),
        (["algorithm.name=crossq", "algorithm.options.adam_beta1=1"], "less than 1"),
        (["algorithm.name=crossq", "algorithm.lr=0.01"], "is set by algorithm.options.lr (0.001)"),
        (["algorithm.name=crossq", "algorithm.polyak=product"], "CrossQ has none"),
        (["algorithm.name=crossq", "algorithm.tau=0.01"], "moves target critics, and CrossQ has none"),
        (["algorithm.name=crossq", "algorithm.options.policy_delay=0"], "greater than or equal to 1"),
        (["algorithm.name=crossq", "env.id=CartPole-v1"], "needs a continuous-action env"),
    ],
)
def test_the_options_are_validated_with_errors_naming_the_key(overrides, message):
    with pytest.raises(RecipeError) as err:
        load_recipe("quickstart", overrides)
    assert message in str(err.value), str(err.value)


def test_the_options_are_the_authors_defaults_and_set_the_loops_keys():
    redq = load_recipe("baselines/hopper_redq")
    assert redq.algorithm.options == {"ensemble_size": 10, "subset_size": 2, "utd_ratio": 20.0, "policy_delay": 20}
    assert (redq.algorithm.num_qvalue_nets, redq.algorithm.utd_ratio) == (10, 20.0)
    tqc = load_recipe("quickstart", ["algorithm.name=tqc"]).algorithm
    assert tqc.options == {"num_critics": 5, "num_quantiles": 25, "top_quantiles_to_drop_per_net": 2}
    assert tqc.num_qvalue_nets == 5
    crossq = load_recipe("quickstart", ["algorithm.name=crossq"]).algorithm
    assert (crossq.options["adam_beta1"], crossq.options["policy_delay"], crossq.lr, crossq.alpha_lr) == (
        0.5,
        3,
        1e-3,
        1e-3,
    )
    assert [plugins.sac_variant(n) for n in ("tqc", "crossq", "redq", "sac")] == [
        "TQCLoss",
        "CrossQLoss",
        "REDQLoss",
        None,
    ]


def test_an_option_override_on_a_resolved_recipe_carries_the_keys_it_sets(tmp_path):
    """A resolved recipe (`adarl show ... > my.yaml`) spells out both CrossQ's `options.lr` and the `algorithm.lr`
    it sets: an override of the option carries the keys with it; one of the key alone is still refused by name."""
    from adarl.errors import RecipeError
    from adarl.runtime.config import load_recipe, save_resolved

    mine = tmp_path / "my_crossq.yaml"
    save_resolved(load_recipe("baselines/hopper_crossq"), mine)
    alg = load_recipe(str(mine), ["algorithm.options.lr=0.002"]).algorithm
    assert (alg.options["lr"], alg.lr, alg.alpha_lr) == (0.002, 0.002, 0.002)
    with pytest.raises(RecipeError, match=r"algorithm\.lr.*set by algorithm\.options\.lr"):
        load_recipe(str(mine), ["algorithm.lr=0.002"])
    both = load_recipe(str(mine), ["algorithm.options.lr=0.002", "algorithm.lr=0.002"]).algorithm
    assert both.lr == 0.002
