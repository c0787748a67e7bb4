"""Algorithms by name (adarl.plugins): registration, ``algorithm.options`` as validated recipe keys, the base
loop's trainer, the TD-target hook that keeps the fused update (exactly), and the one-line fallback otherwise."""

from __future__ import annotations

import warnings

import pytest
import torch
from _helpers import BUILT
from pydantic import BaseModel, ConfigDict, Field

from adarl import plugins
from adarl.core.target_shift import TargetShiftSACLoss
from adarl.errors import AdaRLValueError, FusedFallbackWarning, RecipeError
from adarl.fast.sac import FusedSACUpdate, fused_fallback_reason, wants_fused
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe, recipe_to_yaml
from adarl.runtime.trainers import OffPolicyTrainer, trainer_class
from adarl.runtime.update import FusedStep, LossStep


class ShiftOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kappa: float = Field(0.5, ge=0)


class ShiftedSAC(TargetShiftSACLoss):
    def __init__(self, *args, kappa: float = 0.5, **kwargs):
        super().__init__(*args, **kwargs)
        self.kappa = kappa

    def target_shift(self) -> torch.Tensor:
        params = self.qvalue_network_params.flatten_keys().values()
        return self.kappa * torch.stack([p.detach().pow(2).sum() for p in params]).sum().sqrt()


class OwnForward(ShiftedSAC):
    def forward(self, tensordict):
        out = super().forward(tensordict)
        out.set("my_metric", torch.tensor(1.0))
        return out


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setattr(plugins._algorithm, "_algorithms", dict(plugins._algorithm._algorithms))
    plugins.register_algorithm("shifted_sac", ShiftedSAC, options=ShiftOptions)
    plugins.register_algorithm("own_forward_sac", OwnForward, options=ShiftOptions)
    return plugins


def test_builtins_and_unknown_names():
    assert {"sac", "ppo"} <= set(plugins.algorithm_names())
    with pytest.raises(RecipeError, match=r"algorithm.name.*'sca'.*allowed: .*'sac'.*adarl.plugins"):
        load_recipe("quickstart", ["algorithm.name=sca"])
    with pytest.raises(RecipeError, match=r"algorithm.options.kappa.*unknown option of algorithm 'sac'"):
        load_recipe("quickstart", ["algorithm.options.kappa=1"])
    with pytest.raises(AdaRLValueError, match="base 'dqn'; allowed"):
        plugins.register_algorithm("x", "a:B", base="dqn")
    with pytest.raises(AdaRLValueError, match="already registered"):
        plugins.register_algorithm("sac", ShiftedSAC)


def test_options_are_validated_recipe_keys_recorded_in_full(registered):
    recipe = load_recipe("quickstart", [*BUILT, "algorithm.name=shifted_sac"])
    assert recipe.algorithm.options == {"kappa": 0.5}  # the default, spelled out
    assert "kappa: 0.5" in recipe_to_yaml(recipe)
    assert trainer_class(recipe) is OffPolicyTrainer
    for bad, words in (
        ("algorithm.options.kapa=1", r"algorithm.options.kapa.*allowed: 'kappa'"),
        ("algorithm.options.kappa=-1", r"algorithm.options.kappa = -1.*greater than or equal to 0"),
        ("algorithm.options.kappa=abc", r"algorithm.options.kappa.*number"),
    ):
        with pytest.raises(RecipeError, match=words):
            load_recipe("quickstart", [*BUILT, "algorithm.name=shifted_sac", bad])


def test_a_target_shift_keeps_the_fused_update_and_computes_what_the_loss_computes(registered):
    recipe = load_recipe("quickstart", [*BUILT, "algorithm.name=shifted_sac", "algorithm.options.kappa=0.3"])
    c = build_sac_components(recipe)
    assert isinstance(c.update, FusedStep) and type(c.modules.loss) is ShiftedSAC and c.modules.loss.kappa == 0.3
    torch.manual_seed(3)
    c.replay_buffer.extend(c.env.rollout(200, break_when_any_done=False).reshape(-1))
    batch = c.replay_buffer.sample()
    loss = c.modules.loss
    torch.manual_seed(11)
    ref = loss(batch.clone())
    fu = FusedSACUpdate(loss, [], tau=0.005, backward="manual")
    torch.manual_seed(11)
    out = fu(batch)
    assert float(out["target_shift"]) > 0
    torch.testing.assert_close(out["target_shift"], ref["target_shift"])
    for name in ("loss_actor", "loss_qvalue", "loss_alpha"):
        torch.testing.assert_close(out[name], ref[name].detach(), rtol=1e-5, atol=1e-6, msg=name)
    # the shift did change the critic loss
    loss.kappa = 0.0
    torch.manual_seed(11)
    assert not torch.allclose(loss(batch.clone())["loss_qvalue"], ref["loss_qvalue"])
    c.close()


def test_another_override_falls_back_in_one_line_and_its_metrics_are_returned(registered, tmp_path):
    recipe = load_recipe("quickstart", [*BUILT, "algorithm.name=own_forward_sac"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        c = build_sac_components(recipe)
    msgs = [str(w.message) for w in caught if issubclass(w.category, FusedFallbackWarning)]
    assert len(msgs) == 1 and "OwnForward overrides ['forward']" in msgs[0] and "3x" in msgs[0]
    assert "\n" not in msgs[0]
    assert isinstance(c.update, LossStep)
    assert "forward" in fused_fallback_reason(c.modules.loss)
    with pytest.raises(AdaRLValueError, match="algorithm.fused: true cannot run this loss"):
        wants_fused(True, c.modules.loss)
    c.replay_buffer.extend(c.env.rollout(100, break_when_any_done=False).reshape(-1))
    out = c.update()
    assert {"loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy", "target_shift", "my_metric"} <= set(out)
    c.close()
    # loaded to evaluate (`adarl eval`, `adarl play`: read-only, no update runs): not said (issue 48.6)
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import OffPolicyTrainer

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        OffPolicyTrainer(recipe, RunDir(tmp_path / "run"), quiet=True, _read_only=True).close()
    assert not [w for w in caught if issubclass(w.category, FusedFallbackWarning)]


def test_a_plugin_that_fails_to_load_is_named(monkeypatch):
    from importlib.metadata import EntryPoint

    broken = EntryPoint("broken", "adarl_no_such_plugin_module", plugins.ENTRY_POINT_GROUP)
    monkeypatch.setattr(plugins._registry, "entry_points", lambda group: [broken])
    monkeypatch.setattr(plugins._registry, "_loaded", set())
    with pytest.raises(RecipeError, match=r"plugin 'broken' \(adarl_no_such_plugin_module.*ModuleNotFoundError"):
        load_recipe("quickstart", ["algorithm.name=anything"])
