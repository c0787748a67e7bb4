"""Issue 48, point 4: paper-ready report figures. Every figure is written as PNG, PDF and SVG (valid files; the
report links the PNG), runs that differ only in bookkeeping keys (logging, checkpoints) are seeds of one setting, the
rank figure keeps two layers at the same rank visible, the per-seed panels name their seeds, and the learning
curves' band is described in the same words in the figure, the report and the docs.

Inputs: copies of committed run folders (docs/reports/rank_trajectory-laptop_consistent/runs, read only), no
training."""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
RUNS = REPO / "docs" / "reports" / "rank_trajectory-laptop_consistent" / "runs"


def _copy(seed: int, dest: Path, **changes) -> Path:
    """A committed Walker2d run copied under a name that is not a run id (so it is grouped by recipe name), its
    recipe.yaml changed at ``changes`` (``"logging.backends": [...]``)."""
    shutil.copytree(RUNS / f"env=walker2d__seed={seed}", dest)
    recipe = yaml.safe_load((dest / "recipe.yaml").read_text())
    for key, value in changes.items():
        node = recipe
        *parents, leaf = key.split(".")
        for part in parents:
            node = node[part]
        node[leaf] = value
    (dest / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
    return dest


def _texts(fig) -> list[str]:
    """Every text a figure shows: titles, axis labels, tick labels, legend entries."""
    from matplotlib.text import Text

    return [" ".join(t.get_text().split()) for t in fig.findobj(Text) if t.get_text()]


def _check_formats(folder: Path, names: list[str]) -> None:
    for name in names:
        png = folder / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
        assert png.with_suffix(".pdf").read_bytes()[:5] == b"%PDF-", png
        assert png.with_suffix(".pdf").read_bytes().rstrip().endswith(b"%%EOF"), png
        root = ET.parse(png.with_suffix(".svg")).getroot()
        assert root.tag == "{http://www.w3.org/2000/svg}svg", png


def test_aggregate_figures_formats_variants_ranks_seeds_and_band(tmp_path, monkeypatch):
    from adarl.experiments.report import _figures, aggregate_runs, write_aggregate_report

    # seeds 0 and 1 differ from each other only in bookkeeping keys; seed 2 also in the learning rate
    a = _copy(0, tmp_path / "a")
    b = _copy(
        1,
        tmp_path / "b",
        **{
            "logging.backends": ["csv", "tensorboard"],
            "logging.log_interval": 1000,
            "checkpoint.interval": 20000,
            "checkpoint.keep_last": 1,
            "checkpoint.replay_buffer": False,
            "eval.episodes": 3,
            "output.root": "elsewhere",
        },
    )
    c = _copy(2, tmp_path / "c", **{"algorithm.lr": 0.001, "logging.log_interval": 2000})
    agg = aggregate_runs([a, b])
    assert agg.axes == ["recipe"] and len(agg.groups) == 1 and agg.groups[0].seeds == [0, 1]
    agg = aggregate_runs([a, b, c])
    assert {dict(g.key)["variant"]: g.seeds for g in agg.groups} == {
        "algorithm.lr=0.003": [0, 1],
        "algorithm.lr=0.001": [2],
    }

    drawn: dict[str, object] = {}
    save = _figures.save_figure

    def keep(fig, png, formats):  # the figure's artists, read before it is written and closed
        drawn[png.name] = fig
        return save(fig, png, formats)

    monkeypatch.setattr(_figures, "save_figure", keep)
    out = tmp_path / "report"
    md = write_aggregate_report([a, b], out).read_text()

    figures = ["learning_curves.png", "learning_curves_by_seed.png", "ranks.png", "rliable.png"]
    assert sorted(drawn) == sorted(figures)
    _check_formats(out, figures)
    assert "](learning_curves.png)" in md and ".pdf)" not in md and ".svg)" not in md  # the report links the PNG

    # ranks.png: at the start actor.layer1 and critic.layer1 both have rank 64; both are drawn, each in its own
    # style, the one drawn first (below) wider, and each named once in the figure's legend
    ranks = drawn["ranks.png"]
    lines = {}
    for ax in ranks.axes:
        for line in ax.get_lines():
            lines.setdefault(line.get_label(), []).append(line)
    low, high = lines["actor.layer1"][0], lines["critic.layer1"][0]
    assert low.get_ydata()[0] == high.get_ydata()[0] == 64 and low.get_xdata()[0] == high.get_xdata()[0] == 0
    assert low.get_visible() and high.get_visible() and low.get_alpha() > 0.5 and high.get_alpha() > 0.5
    styles = {name: (ls[0].get_linestyle(), ls[0].get_marker(), ls[0].get_color()) for name, ls in lines.items()}
    layers = ["actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1"]
    assert len({styles[name] for name in layers}) == 4
    assert low.get_zorder() < high.get_zorder() and low.get_linewidth() > high.get_linewidth()
    (legend,) = ranks.legends
    assert [t.get_text() for t in legend.get_texts()][:4] == layers

    # the per-seed panels: one legend entry per seed, in the colour the seed's curves have
    by_seed = drawn["learning_curves_by_seed.png"]
    (legend,) = by_seed.legends
    entries = dict(zip((t.get_text() for t in legend.get_texts()), legend.legend_handles))
    assert {"seed 0", "seed 1", "mean of the seeds"} <= set(entries)
    for ax in by_seed.axes:
        for line in ax.get_lines():
            if line.get_label().startswith("seed "):
                assert line.get_color() == entries[line.get_label()].get_color()

    # the learning curves' band: the same words in the figure, report.md and the docs
    assert _figures.CI_BAND == "shaded: 95% bootstrap CI of the mean over seeds"
    assert _figures.CI_BAND in _texts(drawn["learning_curves.png"])
    assert f"{_figures.CI_BAND} ({_figures.CI_BAND_HOW})" in md
    assert "± std" not in md.split("## Learning curves")[1].split("##")[0]
    docs = " ".join((REPO / "docs" / "evaluation-and-experiments.md").read_text().split())
    assert f"{_figures.CI_BAND} ({_figures.CI_BAND_HOW})" in docs

    # text at a paper's size: nothing above 9 pt, the figure a row of panels at most 7 in wide
    for name, fig in drawn.items():
        assert fig.get_figwidth() <= 7.0, name
        assert max(t.get_fontsize() for t in fig.findobj(lambda o: hasattr(o, "get_fontsize"))) <= 9, name

    # PNG only when asked; a format that is not one is refused naming the allowed ones
    from adarl.errors import AdaRLValueError

    only = write_aggregate_report([a], tmp_path / "png_only", report={"formats": ["png"]})
    assert (only.parent / "ranks.png").is_file() and not list(only.parent.glob("*.pdf"))
    assert "also written as" not in only.read_text()
    with pytest.raises(AdaRLValueError, match=r"allowed: .*'png', 'pdf', 'svg'"):
        write_aggregate_report([a], tmp_path / "bad", report={"formats": ["png", "eps"]})
    assert not (tmp_path / "bad").exists()


def test_single_run_report_writes_every_format_and_keeps_layers_apart(tmp_path, monkeypatch):
    from adarl.errors import RecipeError
    from adarl.experiments.spec import report_options
    from adarl.runtime import report as run_report
    from adarl.runtime.run_folder.run_dir import RunDir

    run = _copy(0, tmp_path / "run")
    drawn = {}
    save = run_report.save_figure

    def keep(fig, png, formats=run_report.FIGURE_FORMATS):
        drawn[png.name] = fig
        return save(fig, png, formats)

    monkeypatch.setattr(run_report, "save_figure", keep)
    md = run_report.write_report(run).read_text()
    _check_formats(run / "plots", ["return.png", "ranks.png"])
    assert "![ranks](plots/ranks.png)" in md and ".pdf" not in md
    assert run_report.EVAL_BARS in md and run_report.EVAL_BARS in _texts(drawn["return.png"])
    again = run_report.plot_ranks(RunDir(run), tmp_path / "again.png")  # the same figure: the same bytes
    for fmt in ("pdf", "svg"):
        assert again.with_suffix(f".{fmt}").read_bytes() == (run / "plots" / f"ranks.{fmt}").read_bytes()
    ax = drawn["ranks.png"].axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert len({(ln.get_linestyle(), ln.get_marker()) for ln in lines.values()}) == len(lines) == 4
    # the report option: checked as the spec checks it
    assert report_options(["formats=[png, svg]"]) == {"formats": ["png", "svg"]}
    with pytest.raises(RecipeError, match="png among them"):
        report_options(["formats=[pdf]"])


def test_training_values_count_bookkeeping_keys_only_where_they_change_training():
    """checkpoint.interval is where a rollback returns to, and a callback may stop a run on an evaluation: there
    those keys make the setting; elsewhere they (and logging, output, names) do not."""
    from adarl.runtime.fingerprint import training_values

    base = {
        "name": "x",
        "seed": 1,
        "algorithm": {"lr": 0.003},
        "logging": {"backends": ["csv"], "log_interval": 1000},
        "output": {"root": "runs"},
        "checkpoint": {"interval": 500, "keep_last": 3},
        "eval": {"interval": 300, "episodes": 2, "max_steps": 50},
        "guards": {"on_nonfinite": "stop"},
    }
    assert training_values(base) == {
        "seed": 1,
        "algorithm.lr": 0.003,
        "eval.max_steps": 50,  # what an evaluation measures: part of the setting
        "guards.on_nonfinite": "stop",
    }
    rollback = training_values({**base, "guards": {"on_nonfinite": "rollback"}})
    assert rollback["checkpoint.interval"] == 500 and "checkpoint.keep_last" not in rollback
    stops = training_values({**base, "callbacks": [{"name": "stop_on_return", "options": {"threshold": 1}}]})
    assert stops["eval.interval"] == 300 and stops["eval.episodes"] == 2
