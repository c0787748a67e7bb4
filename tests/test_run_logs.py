"""What a run logs, as TorchRL and SB3 users read it (issues 20, 31): SB3's names (`rollout/ep_rew_mean`), human
layer names with the module path kept in the JSON, the resolved recipe as the wandb config, a resume continuing the same
wandb run and TensorBoard step axis, a progress bar that counts every frame the budget counts; and run folders
written with the older dot names still read by every reader (report, aggregate, progress board)."""

from __future__ import annotations

import csv
import importlib.util
import json
import sys
import types
from pathlib import Path

import pytest
import torch
from _helpers import INTERVALS_1200, tiny
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss

from adarl.runtime import metrics

TINY = tiny(*INTERVALS_1200)
ACTOR_PATH = "actor_network.module.0.module.0.0"


# ----------------------------------------------------------------------------------------------- names


def test_metric_names_and_their_legacy_names():
    assert metrics.legacy_name(metrics.TRAIN_RETURN) == "train.episode_return"
    assert metrics.legacy_name(metrics.EVAL_RETURN) == "eval.return_mean"
    assert metrics.legacy_name(metrics.WARM_START_FRAMES) == "rank.warm_start_frames"
    assert metrics.legacy_name("dynamics/torso_length") == "dynamics.torso_length"
    old = {"train.episode_return": [(100, 1.0)]}
    assert metrics.series(old, metrics.TRAIN_RETURN) == [(100, 1.0)]
    both = {**old, "train/episode_return": [(200, 2.0)]}
    assert metrics.series(both, metrics.TRAIN_RETURN) == [(200, 2.0)]
    now = {**both, "rollout/ep_rew_mean": [(300, 3.0)]}
    assert metrics.series(now, metrics.TRAIN_RETURN) == [(300, 3.0)]
    assert metrics.series({}, metrics.TRAIN_RETURN) == []


def test_metric_names_are_sb3s_where_sb3_has_the_quantity():
    """Issue 31, point 2: SB3's groups and names; each name's former names are still read."""
    assert (metrics.TRAIN_RETURN, metrics.TRAIN_LENGTH, metrics.TRAIN_EPISODES) == (
        "rollout/ep_rew_mean",
        "rollout/ep_len_mean",
        "time/episodes",
    )
    assert (metrics.EVAL_RETURN, metrics.TRAIN_UPDATES, metrics.TRAIN_LR, metrics.FPS) == (
        "eval/mean_reward",
        "train/n_updates",
        "train/learning_rate",
        "time/fps",
    )
    sac = {k: metrics.train(k) for k in ("loss_actor", "loss_qvalue", "alpha", "loss_alpha", "entropy")}
    assert sac == {
        "loss_actor": "train/actor_loss",
        "loss_qvalue": "train/critic_loss",
        "alpha": "train/ent_coef",
        "loss_alpha": "train/ent_coef_loss",
        "entropy": "train/entropy",  # SB3's SAC logs no entropy: TorchRL's name
    }
    assert metrics.train("loss_critic") == "train/value_loss" and metrics.train("kl_approx") == "train/approx_kl"
    assert metrics.former_names(metrics.TRAIN_RETURN) == ["train/episode_return", "train.episode_return"]
    assert metrics.former_names(metrics.EVAL_RETURN) == ["eval/return", "eval.return_mean"]
    assert metrics.former_names("train/actor_loss") == ["train/loss_actor", "train.loss_actor"]
    assert metrics.csv_paths(metrics.TRAIN_UPDATES) == (
        "metrics/scalars/train/n_updates.csv",
        "metrics/scalars/train/updates.csv",
        "metrics/scalars/train.updates.csv",
    )


def test_metric_files_have_a_header_and_files_without_one_still_read(tmp_path):
    from adarl.experiments.progress import read_progress
    from adarl.runtime.run_folder._loggers import Fanout as _Fanout
    from adarl.runtime.run_folder.run_dir import RunDir

    run = RunDir(tmp_path)
    import torchrl.record.loggers as loggers

    csv_logger = loggers.CSVLogger(exp_name="metrics", log_dir=str(tmp_path))
    log = _Fanout([csv_logger])
    for step in (100, 200, 300):
        log.log_scalar(metrics.TRAIN_RETURN, step / 10, step=step)
    log.log_scalar(metrics.TRAIN_UPDATES, 50, step=300)
    run.close_logger(log)
    path = tmp_path / "metrics" / "scalars" / "rollout" / "ep_rew_mean.csv"
    assert path.read_text() == "step,value\n100,10.0\n200,20.0\n300,30.0\n"
    assert metrics.series(run.scalars(), metrics.TRAIN_RETURN) == [(100, 10.0), (200, 20.0), (300, 30.0)]
    run.truncate_metrics(200)  # a resume keeps the header
    assert path.read_text() == "step,value\n100,10.0\n200,20.0\n"
    log = _Fanout([loggers.CSVLogger(exp_name="metrics", log_dir=str(tmp_path))])
    log.log_scalar(metrics.TRAIN_RETURN, 25.0, step=250)  # and appends below it, no second header
    run.close_logger(log)
    assert path.read_text() == "step,value\n100,10.0\n200,20.0\n250,25.0\n"
    prog = read_progress("r", tmp_path, "running")
    assert (prog.frames, prog.last_return) == (250, 25.0)
    old = tmp_path / "old"  # a run folder of an earlier version: header-less files with the former names
    (old / "metrics" / "scalars" / "train").mkdir(parents=True)
    (old / "metrics" / "scalars" / "train" / "episode_return.csv").write_text("100,1.0\n200,2.0\n")
    (old / "metrics" / "scalars" / "train" / "updates.csv").write_text("200,10\n")
    assert metrics.series(RunDir(old).scalars(), metrics.TRAIN_RETURN) == [(100, 1.0), (200, 2.0)]
    prog = read_progress("old", old, "running")
    assert (prog.frames, prog.last_return) == (200, 2.0)


def _sac_loss(num_cells=(16, 16)):
    from adarl import low_rank_mlp

    obs, act = 5, 2
    net = nn.Sequential(low_rank_mlp(obs, 2 * act, num_cells, low_rank_layers=(0, 1)), NormalParamExtractor())
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
    )
    critic = ValueOperator(
        low_rank_mlp(obs + act, 1, num_cells, low_rank_layers=(1,)), in_keys=["observation", "action"]
    )
    return SACLoss(actor, critic)


def test_layers_get_human_names_with_the_recipe_layer_index():
    from adarl import EnergyRule, RankAdapter

    loss = _sac_loss()
    adapter = RankAdapter(loss, [torch.optim.Adam(loss.parameters())], EnergyRule(0.9), interval=1)
    assert adapter.names == {
        "actor_network.module.0.module.0.0": "actor.layer0",
        "actor_network.module.0.module.0.2": "actor.layer1",
        "qvalue_network.module.2": "critic.layer1",
    }
    assert adapter.named_ranks == {"actor.layer0": 5, "actor.layer1": 16, "critic.layer1": 16}
    event = adapter.adapt()
    assert [r.name for r in event.layers] == ["actor.layer0", "actor.layer1", "critic.layer1"]
    assert event.layers[0].layer == "actor_network.module.0.module.0.0"  # the module path stays
    # a checkpoint's history from before layers had names gets them back on load
    state = adapter.state_dict()
    for ev in state["history"]:
        for rec in ev["layers"]:
            rec.pop("name")
    adapter.load_state_dict(state)
    assert [r.name for r in adapter.history[0].layers] == ["actor.layer0", "actor.layer1", "critic.layer1"]


def test_two_critics_of_one_loss_are_told_apart():
    from adarl.core.adapter import LowRankSite, _name_sites, layer_indices

    net = MLP(in_features=3, out_features=1, num_cells=[4, 4])
    assert layer_indices(net) == {"0": 0, "2": 1, "4": 2}
    sites = [
        LowRankSite(f"{n}.2", n, "critic", "2", net, None, None, None, None, None, None, None)
        for n in ("qvalue_network", "value_network")
    ]
    _name_sites(sites)
    assert [s.name for s in sites] == ["qvalue.layer1", "value.layer1"]


# ------------------------------------------------------------------------------- an older run folder


def _old_style_run(path: Path) -> Path:
    """A run folder as adarl wrote it before issue 20: dotted flat metric files, layers by module path only."""
    from adarl.runtime.config import load_recipe, save_resolved

    save_resolved(
        load_recipe("quickstart", ["collector.total_frames=1000", "collector.init_random_frames=100"]),
        path / "recipe.yaml",
    )
    scalars = path / "metrics" / "scalars"
    scalars.mkdir(parents=True)
    files = {
        "train.episode_return": "100,10.0\n200,12.0\n400,20.0\n500,22.0\n",
        "train.updates": "200,0\n500,300\n",
        "eval.return_mean": "500,30.0\n",
        "rank.warm_start_frames": "300,100\n",
        f"rank.{ACTOR_PATH}": "300,9\n",
        f"rank.{ACTOR_PATH}.error": "300,0.01\n",
    }
    for name, text in files.items():
        (scalars / f"{name}.csv").write_text(text)
    (path / "eval.csv").write_text(
        "frames,updates,mean,std,ci95,episodes,returns,ranks\n"
        f'500,300,30.0,1.0,2.0,2,"[29.0, 31.0]","{{""{ACTOR_PATH}"": 9}}"\n'
    )
    layer = {
        "step": 150,
        "layer": ACTOR_PATH,
        "network": "actor",
        "old_rank": 11,
        "new_rank": 9,
        "singular_values": [1.0] * 11,
        "retained_energy": 0.99,
        "truncation_error": 0.1,
    }
    (path / "ranks.json").write_text(json.dumps([{"step": 150, "index": 0, "layers": [layer]}]))
    (path / "summary.json").write_text(
        json.dumps(
            {
                "name": "quickstart",
                "frames": 1000,
                "updates": 800,
                "episodes": 4,
                "wall_time_s": 5.0,
                "updates_per_s": 160.0,
                "ranks": {ACTOR_PATH: 9},
                "rank_events": 1,
                "final_eval": {"frames": 500, "mean": 30.0},
            }
        )
    )
    return path


def test_reports_aggregates_and_progress_read_an_old_style_run_folder(tmp_path):
    from adarl.experiments.progress import read_progress
    from adarl.experiments.report import event_dips, write_aggregate_report
    from adarl.experiments.report._runs import _load_run
    from adarl.runtime.report import plot_returns, write_report
    from adarl.runtime.run_folder.run_dir import RunDir

    run = _old_style_run(tmp_path / "old")
    report = write_report(run).read_text()
    assert f"| actor | {ACTOR_PATH} |" in report  # no human name was recorded: the module path, as before
    assert (run / "plots" / "return.png").is_file()
    from adarl.runtime.report import _event_frames

    assert _event_frames(RunDir(run)) == [300]
    assert plot_returns(RunDir(run), tmp_path / "r.png") is not None

    rec = _load_run(run, None)
    assert rec.events == [300]
    assert event_dips(rec, window=200) == [(300, 12.0, 21.0)]
    prog = read_progress("old", run, "running")
    assert (prog.frames, prog.last_return) == (500, 30.0)

    # mixed with a run written with the new names
    new = tmp_path / "new"
    new.mkdir()
    for f in run.iterdir():
        if f.is_file():
            (new / f.name).write_bytes(f.read_bytes())
    for name, text in {
        "train/episode_return": "200,10.0\n400,30.0\n",
        "warm_start/frames": "300,100\n",
        "train/updates": "200,0\n400,200\n",
    }.items():
        p = new / "metrics" / "scalars" / f"{name}.csv"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    rec = _load_run(new, None)
    assert rec.events == [300] and event_dips(rec, window=200) == [(300, 10.0, 30.0)]
    assert read_progress("new", new, "running").frames == 500  # eval.csv's frames
    out = write_aggregate_report([run, new], tmp_path / "report")
    assert Path(out).is_file()


# ------------------------------------------------------------------------------- a tiny run, in process


class _Bar:
    """tqdm's interface as the Trainer uses it, recorded."""

    made: list = []

    def __init__(self, total=None, initial=0, **kwargs):
        self.total, self.n, self.postfix, self.closed = total, initial, None, False
        _Bar.made.append(self)

    def update(self, n=1):
        self.n += n

    def reset(self, total=None):
        self.n, self.total = 0, total if total is not None else self.total

    def set_postfix(self, refresh=True, **kwargs):
        self.postfix = kwargs

    def close(self):
        self.closed = True


class _FakeWandb:
    """torchrl's WandbLogger as make_logger calls it (wandb itself is an optional extra)."""

    made: list = []

    def __init__(self, exp_name, project=None, offline=False, save_dir=None, id=None, **kwargs):
        self.kwargs = {"exp_name": exp_name, "project": project, "id": id, **kwargs}
        self.logged: list = []
        self.experiment = types.SimpleNamespace(finish=lambda: self.logged.append("finish"))
        _FakeWandb.made.append(self)

    def log_scalar(self, name, value, step=None):
        self.logged.append((name, step))


class _FakeWriter:
    made: list = []

    def __init__(self, log_dir=None, purge_step=None, **kwargs):
        self.log_dir, self.purge_step, self.texts = log_dir, purge_step, {}
        _FakeWriter.made.append(self)

    def add_scalar(self, *args, **kwargs):
        pass

    def add_text(self, tag, text, global_step=None):
        self.texts[tag] = text

    def close(self):
        pass


@pytest.fixture(scope="module")
def logged_run(tmp_path_factory):
    """A tiny AdaRL-SAC run with a progress bar, wandb and TensorBoard (both faked), then a resume of it."""
    from tqdm import auto

    from adarl.runtime.config import load_recipe, save_resolved
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import OffPolicyTrainer

    mp = pytest.MonkeyPatch()
    real_find_spec = importlib.util.find_spec
    mp.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: (
            types.SimpleNamespace(name=name) if name in ("wandb", "tensorboard") else real_find_spec(name, *a)
        ),
    )
    import torchrl.record.loggers as loggers

    mp.setattr(loggers, "WandbLogger", _FakeWandb)
    fake_tb = types.ModuleType("torch.utils.tensorboard")
    fake_tb.SummaryWriter = _FakeWriter
    mp.setitem(sys.modules, "torch.utils.tensorboard", fake_tb)
    mp.setattr(auto, "tqdm", _Bar)
    _Bar.made, _FakeWandb.made, _FakeWriter.made = [], [], []
    try:
        path = tmp_path_factory.mktemp("logs") / "run"
        recipe = load_recipe("quickstart", [*TINY, "logging.backends=[csv,tensorboard,wandb]"])
        assert recipe.replay.warm_start.count_frames
        run = RunDir.create(path)
        save_resolved(recipe, run.recipe_path)
        summary = OffPolicyTrainer(recipe, run, quiet=False).train()
        first = {"bar": _Bar.made[-1], "wandb": _FakeWandb.made[-1], "writer": _FakeWriter.made[-1]}
        # pretend it died after its checkpoint at 800 frames, and resume it
        for ckpt in run.checkpoints():
            if int(ckpt.stem.split("-")[1]) > 800:
                ckpt.unlink()
        resumed = OffPolicyTrainer.resume(path, quiet=False)
        resumed.train()
        second = {"bar": _Bar.made[-1], "wandb": _FakeWandb.made[-1], "writer": _FakeWriter.made[-1], "from": 800}
        writers_before = len(_FakeWriter.made)
        evaluating = OffPolicyTrainer.resume(path, quiet=True, truncate_metrics=False, checkpoint="best")  # adarl eval
        evaluating.close()
        second["eval_writers"] = _FakeWriter.made[writers_before:]
        yield {"path": path, "recipe": recipe, "summary": summary, "first": first, "second": second}
    finally:
        mp.undo()


def test_progress_bar_counts_every_frame_of_the_budget(logged_run):
    bar, summary = logged_run["first"]["bar"], logged_run["summary"]
    assert summary["warm_start_frames"] > 0 and summary["rank_events"] > 0
    assert bar.total == 1200 and bar.closed
    assert bar.n == summary["frames"] >= 1200  # warm-start frames included: the bar ends full
    ranks = bar.postfix["ranks"]
    assert "actor.layer0=" in ranks and "critic.layer1=" in ranks and "module" not in ranks


def test_progress_bar_shows_updates_as_an_integer():
    """tqdm writes an int postfix value as a float (``upd=1e+4``); the trainers give it the digits (issue 31)."""
    import io

    from tqdm import tqdm

    from adarl.runtime.trainers.base import BaseTrainer
    from adarl.runtime.trainers.off_policy import OffPolicyTrainer
    from adarl.runtime.trainers.ppo import PPOTrainer

    state = types.SimpleNamespace(last_return=1.0, updates=10000, c=types.SimpleNamespace(adapter=None))
    for cls in (BaseTrainer, OffPolicyTrainer, PPOTrainer):
        bar = tqdm(total=1, file=io.StringIO())
        bar.set_postfix(refresh=False, **cls._postfix(state))
        assert "upd=10000" in str(bar), (cls.__name__, str(bar))
        bar.close()


def test_metrics_have_conventional_names(logged_run):
    root = logged_run["path"] / "metrics" / "scalars"
    names = {p.relative_to(root).with_suffix("").as_posix() for p in root.rglob("*.csv")}
    for name in (
        "rollout/ep_rew_mean",
        "rollout/ep_len_mean",
        "time/episodes",
        "train/actor_loss",
        "train/critic_loss",
        "train/ent_coef",
        "train/ent_coef_loss",
        "train/n_updates",
        "train/learning_rate",
        "eval/mean_reward",
        "eval/std_reward",
        "warm_start/frames",
        "rank/actor.layer0",
        "rank/actor.layer1",
        "rank/critic.layer0",
        "rank/critic.layer1",
        "rank_error/actor.layer0",
        "dynamics/torso_length",
        "time/fps",
        "time/updates_per_s",
    ):
        assert name in names, name
    assert not [n for n in names if "." in n.split("/")[0] or "module" in n], names
    lengths = [float(line.split(",")[1]) for line in (root / "rollout" / "ep_len_mean.csv").read_text().split()[1:]]
    assert lengths and all(1 <= v <= 1000 for v in lengths)
    fps = [float(line.split(",")[1]) for line in (root / "time" / "fps.csv").read_text().split()[1:]]
    assert fps and all(v > 0 for v in fps)


def test_human_layer_names_in_csv_report_and_plots_with_paths_in_json(logged_run):
    path = logged_run["path"]
    history = json.loads((path / "ranks.json").read_text())
    layers = history[0]["layers"]
    assert layers[0]["layer"] == ACTOR_PATH and layers[0]["name"] == "actor.layer0"
    with (path / "ranks.csv").open() as fh:
        reader = csv.DictReader(fh)
        header = reader.fieldnames
        rows = list(reader)
    assert header[header.index("layer") + 1] == "name"  # beside the module path, nothing renamed
    assert {r["name"] for r in rows} == {"actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1"}
    report = (path / "report.md").read_text()
    assert "| actor.layer0 |" in report and "final ranks: {'actor.layer0'" in report
    summary = json.loads((path / "summary.json").read_text())
    assert summary["ranks"][ACTOR_PATH] >= 1 and summary["layer_names"][ACTOR_PATH] == "actor.layer0"
    from adarl.experiments.report._runs import _load_run, _rank_series

    labels = sorted(_rank_series(_load_run(path, None)))  # the legends of plots/ranks.png and the aggregate's
    assert labels == ["actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1"]


def test_rank_events_record_their_frames_and_ranks_png_is_on_frames(logged_run):
    """Issue 31, point 3: the rank plot's x axis is return.png's (frames), from each event's recorded frames."""
    from adarl.runtime.report import rank_axis
    from adarl.runtime.run_folder.run_dir import RunDir

    path = logged_run["path"]
    history = json.loads((path / "ranks.json").read_text())
    frames = [ev["frames"] for ev in history]
    assert frames == sorted(frames) and frames[0] > 0
    warm_starts = {f for f, _ in metrics.series(RunDir(path).scalars(), metrics.WARM_START_FRAMES)}
    assert warm_starts and warm_starts <= set(frames)  # the same frames return.png marks events at
    with (path / "ranks.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {int(r["frames"]) for r in rows} == set(frames)
    label, xs, end = rank_axis(RunDir(path), history)
    assert (label, xs, end) == ("environment frames", frames, logged_run["summary"]["frames"])
    assert (path / "plots" / "ranks.png").read_bytes()[:4] == b"\x89PNG"


def test_speed_png_and_the_aggregate_rank_figure_are_on_frames_too(logged_run, tmp_path, monkeypatch):
    """Issue 31, point 3: one x axis (frames) across a run's plots and the experiment report's rank figure."""
    import matplotlib.axes

    from adarl.experiments.report import write_aggregate_report
    from adarl.runtime.report import plot_speed
    from adarl.runtime.run_folder.run_dir import RunDir

    path = logged_run["path"]
    frames = [ev["frames"] for ev in json.loads((path / "ranks.json").read_text())]
    drawn: dict[str, list] = {"xlabel": [], "vlines": []}
    monkeypatch.setattr(matplotlib.axes.Axes, "set_xlabel", lambda ax, label, **kw: drawn["xlabel"].append(label))
    real_axvline = matplotlib.axes.Axes.axvline
    monkeypatch.setattr(
        matplotlib.axes.Axes, "axvline", lambda ax, x=0, *a, **kw: drawn["vlines"].append(x) or real_axvline(ax, x)
    )
    assert plot_speed(RunDir(path), tmp_path / "speed.png") is not None
    assert drawn["xlabel"] == ["environment frames"] and drawn["vlines"] == sorted(set(frames))

    report = write_aggregate_report([path], tmp_path / "report")
    with (Path(report).parent / "ranks.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {int(r["frames"]) for r in rows} == {0, *frames, logged_run["summary"]["frames"]}
    assert "over environment frames" in Path(report).read_text()


def test_rank_plot_of_an_older_history_converts_or_says_steps(tmp_path):
    from adarl.runtime.report import plot_ranks, rank_axis
    from adarl.runtime.run_folder.run_dir import RunDir

    layer = {"layer": ACTOR_PATH, "name": "actor.layer0", "old_rank": 64, "new_rank": 11}
    history = [{"step": 150, "index": 0, "layers": [layer]}]  # written before events recorded their frames
    (tmp_path / "ranks.json").write_text(json.dumps(history))
    (tmp_path / "summary.json").write_text(json.dumps({"frames": 500, "updates": 300}))
    run = RunDir(tmp_path)
    assert rank_axis(run, history) == ("optimisation steps", [150], 300)  # nothing to convert with: said so
    updates = tmp_path / "metrics" / "scalars" / "train" / "updates.csv"  # the former name, no header
    updates.parent.mkdir(parents=True)
    updates.write_text("200,0\n300,100\n400,200\n")
    label, xs, end = rank_axis(run, history)
    assert label.startswith("environment frames (") and xs == [350] and end == 500
    assert plot_ranks(run, tmp_path / "ranks.png") is not None


def test_wandb_gets_the_recipe_and_a_resume_continues_its_run(logged_run):
    first, second, path = logged_run["first"], logged_run["second"], logged_run["path"]
    run_id = (path / "wandb_run_id").read_text().strip()
    assert first["wandb"].kwargs["id"] == second["wandb"].kwargs["id"] == run_id
    assert first["wandb"].kwargs["config"] == logged_run["recipe"].model_dump(mode="json")
    assert first["wandb"].kwargs["config"]["collector"]["total_frames"] == 1200
    assert any(x[0] == "rollout/ep_rew_mean" for x in first["wandb"].logged if isinstance(x, tuple))
    assert first["wandb"].logged[-1] == "finish"
    resumed_steps = [x[1] for x in second["wandb"].logged if isinstance(x, tuple)]
    assert min(resumed_steps) > second["from"]  # the same step axis (frames), continued


def test_tensorboard_hides_the_steps_a_resume_logs_again(logged_run):
    first, second = logged_run["first"]["writer"], logged_run["second"]["writer"]
    assert first.purge_step is None and "collector" in first.texts["recipe"]
    assert second.purge_step == logged_run["second"]["from"] + 1
    # an evaluation opens the run read-only: no TensorBoard writer at all, so it can hide no training step
    assert logged_run["second"]["eval_writers"] == []
