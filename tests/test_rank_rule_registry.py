"""Rank rules by name (adarl.plugins): registration, ``rank.rule`` and ``rank.rule_options`` as validated recipe
keys, the builder's rule, and a short training run that truncates with a registered rule (docs/adding-a-component.md).
"""

from __future__ import annotations

import json
import math

import pytest
import torch
from _helpers import tiny
from pydantic import BaseModel, ConfigDict, Field

from adarl import plugins
from adarl.core.rank import EnergyRule, RankRule, make_rule
from adarl.errors import AdaRLValueError, RecipeError
from adarl.runtime.builders.sac import make_rank_rule
from adarl.runtime.config import load_recipe, recipe_to_yaml, save_resolved
from adarl.runtime.run_folder.run_dir import RunDir
from adarl.runtime.trainers import OffPolicyTrainer


class TopKOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    k: int = Field(4, ge=1)


class TopK(RankRule):
    """Keep the ``k`` largest singular values."""

    name = "top_k"

    def __init__(self, k: int = 4, zero_tol: float = 1e-10) -> None:
        super().__init__(zero_tol)
        self.k = k

    def select(self, s, current_rank, min_rank, fit):
        return self.k


FIT_CALLS: list[tuple[int, float]] = []


class FitTopK(TopK):
    """Top-k that also measures ``fit(k)`` (a ``needs_fit`` rule gets it from the adapter, as policy_fit does)."""

    name = "fit_top_k"
    needs_fit = True

    def select(self, s, current_rank, min_rank, fit):
        FIT_CALLS.append((self.k, float(fit(min(self.k, current_rank)))))
        return self.k


class NotARule:
    pass


@pytest.fixture
def registered(monkeypatch):
    """``top_k`` and ``fit_top_k`` registered for one test (the registry is restored afterwards)."""
    monkeypatch.setattr(plugins._rank_rule, "_rank_rules", dict(plugins._rank_rule._rank_rules))
    plugins.register_rank_rule("top_k", TopK, options=TopKOptions, description="keep the k largest")
    plugins.register_rank_rule("fit_top_k", f"{FitTopK.__module__}:FitTopK", options=TopKOptions)  # lazy path
    return plugins


def test_builtins_and_unknown_names():
    assert plugins.rank_rule_names(load=False)[:5] == list(plugins.BUILTIN_RANK_RULES)
    assert all(plugins.rank_rule(n).builtin for n in plugins.BUILTIN_RANK_RULES)
    assert plugins.rank_rule("energy").rule_class() is EnergyRule
    with pytest.raises(
        RecipeError, match=r"rank.rule = 'topk': must be one of 'energy', .*'policy_fit'.*adarl.register_rank_rule"
    ):
        load_recipe("quickstart", ["rank.rule=topk"])
    with pytest.raises(AdaRLValueError, match="adarl's own .* cannot be replaced"):
        plugins.register_rank_rule("energy", TopK, replace=True)
    with pytest.raises(AdaRLValueError, match="must be an identifier"):
        plugins.register_rank_rule("top-k", TopK)
    with pytest.raises(AdaRLValueError, match="options must be a pydantic BaseModel class"):
        plugins.register_rank_rule("top_k", TopK, options=dict)
    assert "top_k" not in plugins.rank_rule_names(load=False)  # nothing half-registered


def test_a_registered_rule_is_a_validated_recipe_key_recorded_in_full(registered):
    assert plugins.rank_rule_names(load=False)[-2:] == ["top_k", "fit_top_k"]
    recipe = load_recipe("quickstart", ["rank.rule=top_k"])
    assert recipe.rank.rule_options == {"k": 4}  # the default, spelled out
    assert "rule: top_k" in recipe_to_yaml(recipe) and "k: 4" in recipe_to_yaml(recipe)
    rule = make_rank_rule(load_recipe("quickstart", ["rank.rule=top_k", "rank.rule_options.k=2"]).rank)
    assert type(rule) is TopK and rule.k == 2
    assert rule(torch.tensor([4.0, 3.0, 2.0, 1.0]), current_rank=4).rank == 2
    assert type(make_rank_rule(load_recipe("quickstart", ["rank.rule=fit_top_k"]).rank)) is FitTopK  # imported now
    # the unknown-name message lists registered rules too
    with pytest.raises(RecipeError, match=r"rank.rule = 'top_kk'.*'fit_top_k'; did you mean 'top_k'"):
        load_recipe("quickstart", ["rank.rule=top_kk"])


@pytest.mark.parametrize(
    "bad, words",
    [
        ("rank.rule_options.kk=1", r"rank.rule_options.kk = 1: unknown option of rank rule 'top_k'; allowed: 'k'"),
        ("rank.rule_options.k=0", r"rank.rule_options.k = 0: .*greater than or equal to 1"),
        ("rank.rule_options.k=abc", r"rank.rule_options.k = 'abc': .*integer"),
    ],
)
def test_bad_rule_options_name_the_key(registered, bad, words):
    with pytest.raises(RecipeError, match=words):
        load_recipe("quickstart", ["rank.rule=top_k", bad])


def test_adarl_own_rules_take_no_rule_options():
    with pytest.raises(RecipeError, match=r"rank.rule_options = \{'k': 3\}: must be empty with adarl's own rule "):
        load_recipe("quickstart", ["rank.rule_options.k=3"])
    with pytest.raises(RecipeError, match=r"rank.rule_options.*'fixed'.*rank.beta, rank.target_rank or rank.lam"):
        load_recipe("quickstart", ["rank.rule=fixed", "rank.target_rank=8", "rank.rule_options={rank: 8}"])
    # and they are built from rank.beta / target_rank / lam, as before
    assert make_rank_rule(load_recipe("quickstart", ["rank.rule=ratio", "rank.beta=0.5"]).rank).beta == 0.5
    assert make_rank_rule(load_recipe("quickstart", ["rank.rule=fixed", "rank.target_rank=8"]).rank).target_rank == 8
    assert make_rank_rule(load_recipe("quickstart", ["rank.rule=policy_fit", "rank.lam=0.1"]).rank).lam == 0.1


def test_make_rule_finds_registered_rules_and_refuses_other_classes(registered, monkeypatch):
    assert "top_k" not in plugins.BUILTIN_RANK_RULES
    rule = make_rule("top_k", k=3)
    assert type(rule) is TopK and rule.k == 3
    with pytest.raises(AdaRLValueError, match=r"unknown rank.rule 'nope'; allowed: .*'top_k'"):
        make_rule("nope")

    @plugins.register_rank_rule("not_a_rule")
    class Decorated(NotARule):
        pass

    assert Decorated.__name__ == "Decorated"  # the decorator returns the class
    with pytest.raises(AdaRLValueError, match="not an adarl.core.rank.RankRule subclass"):
        make_rule("not_a_rule")
    with pytest.raises(AdaRLValueError, match="not an adarl.core.rank.RankRule subclass"):
        make_rank_rule(load_recipe("quickstart", ["rank.rule=not_a_rule"]).rank)
    plugins.register_rank_rule("missing", "adarl_no_such_module:Rule")
    with pytest.raises(AdaRLValueError, match=r"rank rule 'missing' .*cannot be imported: ModuleNotFoundError"):
        make_rank_rule(load_recipe("quickstart", ["rank.rule=missing"]).rank)


# Hopper, tiny: 300 frames, 200 updates, one rank event at update 150 (every candidate applied)
TINY = tiny(
    "collector.total_frames=300",
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "rank.accept.mode=always",
    "replay.size=1000",
    "replay.warm_start.frames=50",
    "eval.episodes=1",
    "eval.max_steps=20",
)


def test_a_run_truncates_with_the_registered_rule(registered, tmp_path):
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    FIT_CALLS.clear()
    try:
        recipe = load_recipe("quickstart", [*TINY, "rank.rule=fit_top_k", "rank.rule_options.k=3"])
        run = RunDir.create(tmp_path / "run")
        save_resolved(recipe, run.recipe_path)
        trainer = OffPolicyTrainer(recipe, run, quiet=True)
        assert type(trainer.c.adapter.rule) is FitTopK
        summary = trainer.train()
    finally:
        torch.set_num_threads(n)
    assert summary["rank_events"] == 1
    (event,) = json.loads((tmp_path / "run" / "ranks.json").read_text())
    layers = event["layers"]
    assert layers and all(rec["candidate"] == 3 and rec["new_rank"] == 3 < rec["old_rank"] for rec in layers)
    # needs_fit: the adapter measured fit(k) on replay states for every layer (each critic member included)
    assert len(FIT_CALLS) >= len(layers) and all(k == 3 and math.isfinite(d) for k, d in FIT_CALLS)
    assert "rule: fit_top_k" in recipe_to_yaml(recipe)
    saved = run.recipe_path.read_text()
    assert "fit_top_k" in saved and "k: 3" in saved
