"""WarmupCosine: warm-up from zero, global (jagged) cosine, restarts, and checkpointing through LambdaLR."""

import math

import pytest
import torch

from adarl.core.lr_schedule import WarmupCosine, make_lr_scheduler, restart_lr_scheduler
from adarl.errors import AdaRLValueError


def _cos(step, total, floor=0.0):
    return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(step, total) / total))


def _opt(lr=1.0, groups=1):
    params = [torch.nn.Parameter(torch.zeros(2)) for _ in range(groups)]
    return torch.optim.SGD([{"params": [p]} for p in params], lr=lr)


def test_warmup_from_zero_then_constant_without_total():
    f = WarmupCosine(warmup_steps=4)
    assert [f(s) for s in range(7)] == [0.0, 0.25, 0.5, 0.75, 1.0, 1.0, 1.0]


def test_no_warmup_is_plain_cosine():
    f = WarmupCosine(warmup_steps=0, total_steps=10, min_factor=0.1)
    for s in (0, 3, 10, 25):
        assert f(s) == pytest.approx(_cos(s, 10, 0.1))
    assert f(0) == 1.0 and f(25) == pytest.approx(0.1)


def test_jagged_cosine_after_restart():
    f = WarmupCosine(warmup_steps=5, total_steps=100)
    assert f(50) == pytest.approx(_cos(50, 100))  # warm-up long over
    f.restart(50)
    assert f(50) == 0.0
    assert f(52) == pytest.approx(0.4 * _cos(52, 100))  # ramp times the *global* cosine
    assert f(55) == pytest.approx(_cos(55, 100))
    assert f(80) == pytest.approx(_cos(80, 100))
    assert f.restarts == 1 and f.last_restart == 50


def test_lambdalr_values_restart_and_immediate_zero():
    opt = _opt(lr=2.0)
    sch = make_lr_scheduler(opt, warmup_steps=4, total_steps=40)
    assert opt.param_groups[0]["lr"] == 0.0  # LambdaLR applies factor(0) at construction
    lrs = []
    for _ in range(10):
        opt.step()
        sch.step()
        lrs.append(opt.param_groups[0]["lr"])
    assert lrs[:4] == pytest.approx(
        [2 * 0.25 * _cos(1, 40), 2 * 0.5 * _cos(2, 40), 2 * 0.75 * _cos(3, 40), 2 * _cos(4, 40)]
    )
    assert lrs[9] == pytest.approx(2 * _cos(10, 40))
    restart_lr_scheduler(sch)
    assert opt.param_groups[0]["lr"] == 0.0 and sch.get_last_lr() == [0.0]
    sch.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(2 * 0.25 * _cos(11, 40))


def test_state_dict_round_trip_through_lambdalr():
    opt = _opt(lr=1.0, groups=2)
    sch = make_lr_scheduler(opt, warmup_steps=3, total_steps=30, min_factor=0.05)
    for _ in range(7):
        opt.step()
        sch.step()
    restart_lr_scheduler(sch)
    sch.step()
    state = sch.state_dict()
    assert state["lr_lambdas"][0]["last_restart"] == 7

    opt2 = _opt(lr=1.0, groups=2)
    sch2 = make_lr_scheduler(opt2, warmup_steps=3, total_steps=30, min_factor=0.05)
    sch2.load_state_dict(state)
    for fn, fn2 in zip(sch.lr_lambdas, sch2.lr_lambdas):
        assert vars(fn) == vars(fn2)
    for _ in range(5):
        opt.step(), sch.step(), opt2.step(), sch2.step()
        assert sch.get_last_lr() == pytest.approx(sch2.get_last_lr())


@pytest.mark.parametrize(
    "kwargs",
    [{"warmup_steps": -1}, {"warmup_steps": 1.5}, {"total_steps": 0}, {"min_factor": 1.5}, {"min_factor": True}],
)
def test_validation(kwargs):
    with pytest.raises(AdaRLValueError):
        WarmupCosine(**kwargs)


def test_restart_needs_warmup_cosine():
    opt = _opt()
    sch = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    with pytest.raises(AdaRLValueError, match="WarmupCosine"):
        restart_lr_scheduler(sch)
