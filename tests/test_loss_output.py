"""How every TorchRL-path step reads a loss's output (adarl.runtime.update): the ``loss_*`` entries summed, a
loss term's entry added, the scalar entries returned, and a loss that lacks what its loop steps refused by name
before any backward pass."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from adarl.errors import AdaRLValueError
from adarl.runtime.update import DelayedActorStep, LossStep, loss_output, require_losses, scalar_entries


class _Loss(nn.Module):
    """A loss module (TensorDict in, TensorDict out) that returns the ``loss_*`` entries it is given, plus metrics."""

    def __init__(self, *names: str) -> None:
        super().__init__()
        self.names = names
        self.w = nn.Parameter(torch.ones(3))

    def forward(self, td):
        out = {n: (td["x"] * self.w).sum() for n in self.names}
        out |= {"alpha": torch.tensor(0.2), "count": torch.tensor(3), "per_sample": torch.zeros(4)}
        return TensorDict(out, [])


class _Term(nn.Module):
    def wrap_output(self, td):
        td["loss_term"] = torch.tensor(0.5)
        return td


def _buffer() -> TensorDictReplayBuffer:
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(8), batch_size=4)
    rb.extend(TensorDict({"x": torch.randn(8, 3)}, [8]))
    return rb


def test_loss_output_adds_the_terms_entries_and_keeps_every_loss_entry():
    td, losses = loss_output(_Loss("loss_actor", "loss_qvalue"), _buffer().sample(), {"term": _Term()})
    assert sorted(losses) == ["loss_actor", "loss_qvalue", "loss_term"]
    assert all(losses[k] is td[k] for k in losses)  # the output's own tensors: the backward reaches the parameters


def test_scalar_entries_are_the_scalar_floats_detached():
    td, _ = loss_output(_Loss("loss_actor"), _buffer().sample(), {})
    out = scalar_entries(td)
    assert sorted(out) == ["alpha", "loss_actor"]  # no integer counter, no per-sample tensor
    assert not out["loss_actor"].requires_grad and td["loss_actor"].requires_grad


@pytest.mark.parametrize(
    "loop, required", [("SAC", ("loss_actor", "loss_qvalue", "loss_alpha")), ("PPO", ("loss_objective", "loss_critic"))]
)
def test_require_losses_names_the_missing_entries_and_what_the_loop_steps(loop, required):
    with pytest.raises(AdaRLValueError) as err:
        require_losses({required[0]: torch.tensor(1.0)}, required, _Loss(), loop)
    msg = str(err.value)
    assert (
        f"_Loss's output lacks {list(required[1:])}" in msg
        and f"a loss on the {loop} loop returns {list(required)}" in msg
    )
    require_losses({k: torch.tensor(1.0) for k in required}, required, _Loss(), loop)  # complete: accepted


def test_sac_step_refuses_a_loss_without_its_three_losses_before_stepping():
    loss = _Loss("loss_actor")
    before = loss.w.detach().clone()
    step = LossStep(loss, [torch.optim.SGD(loss.parameters(), lr=1.0)], replay_buffer=_buffer(), target_updater=None)
    with pytest.raises(AdaRLValueError, match=r"lacks \['loss_qvalue', 'loss_alpha'\]; a loss on the SAC loop"):
        step()
    assert torch.equal(loss.w, before) and loss.w.grad is None  # refused before any backward or optimiser step


def test_td3_step_refuses_a_loss_without_a_critic_loss():
    loss = _Loss("loss_actor")
    opts = {"actor": torch.optim.SGD(loss.parameters(), lr=1.0), "critic": torch.optim.SGD(loss.parameters(), lr=1.0)}
    step = DelayedActorStep(loss, opts, replay_buffer=_buffer(), target_updater=None)
    with pytest.raises(AdaRLValueError, match=r"output has \['loss_actor'\]; a loss on the td3 loop returns"):
        step()
