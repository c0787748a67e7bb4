"""Schedules: the paper's formulas, boxes, lists, JSON round trips and validation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from adarl.envs import (
    FixedSchedule,
    ListSchedule,
    Schedule,
    SinusoidSchedule,
    UniformSchedule,
    grid_schedule,
    make_schedule,
    schedule_from_dict,
    validate_schedule,
    validate_values,
)
from adarl.errors import AdaRLValueError


def test_sinusoid_is_the_paper_formula():
    s = make_schedule("Hopper-v5", "paper")
    for i in (0, 1, 7, 100):
        v = s.sample(i, None)
        assert v["torso_length"] == pytest.approx(0.4 + 0.2 * math.sin(0.2 * i))
        assert v["foot_length"] == pytest.approx(0.39 + 0.2 * math.sin(0.2 * i))
    w = make_schedule("Walker2d-v5", "paper").sample(3, None)
    assert w == pytest.approx({"torso_length": 0.2 + 0.1 * math.sin(0.9), "foot_length": 0.1 + 0.05 * math.sin(0.9)})
    assert s.nominal() == {"torso_length": 0.4, "foot_length": 0.39}
    assert s.bounds()["torso_length"] == pytest.approx((0.2, 0.6))
    per_param = SinusoidSchedule(
        {"a": 1.0, "b": 2.0}, {"a": 1.0, "b": 1.0}, {"a": 0.5, "b": 1.0}, phase={"a": 0.0, "b": 1.0}
    )
    assert per_param.sample(2, None)["b"] == pytest.approx(2.0 + math.sin(3.0))


def test_uniform_draws_in_the_box_and_depends_only_on_the_rng():
    s = UniformSchedule({"x": 0.25, "y": -1.0}, {"x": 0.55, "y": 1.0})
    draws = [s.sample(i, np.random.default_rng(0)) for i in range(3)]
    assert draws[0] == draws[1] == draws[2]  # the episode index does not matter, the generator does
    rng = np.random.default_rng(1)
    many = [s.sample(i, rng) for i in range(200)]
    assert all(0.25 <= d["x"] <= 0.55 and -1 <= d["y"] <= 1 for d in many)
    assert len({d["x"] for d in many}) == 200
    assert s.nominal() == pytest.approx({"x": 0.4, "y": 0.0})
    assert s.is_random and not SinusoidSchedule({"x": 1}, {"x": 1}, 1).is_random


def test_fixed_and_list_schedules():
    f = FixedSchedule({"pole_length": 0.5})
    assert f.sample(9, None) == f.nominal() == {"pole_length": 0.5}
    lst = ListSchedule([{"x": 1.0}, {"x": 2.0}, {"x": 6.0}])
    assert [lst.sample(i, None)["x"] for i in range(5)] == [1, 2, 6, 1, 2]
    once = ListSchedule([{"x": 1.0}, {"x": 2.0}], cycle=False)
    assert [once.sample(i, None)["x"] for i in range(4)] == [1, 2, 2, 2]
    assert lst.nominal() == {"x": 3.0} and lst.bounds() == {"x": (1.0, 6.0)}
    grid = grid_schedule({"torso_length": [0.3, 0.5], "foot_length": [0.2, 0.4, 0.6]})
    assert len(grid) == 6 and grid.sample(5, None) == {"foot_length": 0.6, "torso_length": 0.5}
    validate_schedule("Hopper-v5", grid)


@pytest.mark.parametrize(
    "schedule",
    [
        make_schedule("Hopper-v5", "paper"),
        make_schedule("Walker2d-v5", "low"),
        FixedSchedule({"gravity": 12.0}),
        ListSchedule([{"x": 1.0}, {"x": 2.0}], cycle=False),
        SinusoidSchedule({"a": 1.0}, {"a": 0.5}, {"a": 0.3}, phase=0.25),
    ],
)
def test_json_round_trip(schedule):
    data = json.loads(json.dumps(schedule.to_dict()))
    again = schedule_from_dict(data)
    assert again == schedule and type(again) is type(schedule)
    assert Schedule.from_dict(data) == schedule
    assert type(schedule).from_dict({k: v for k, v in data.items() if k != "kind"}) == schedule


def test_schedule_errors_name_the_allowed_values():
    with pytest.raises(AdaRLValueError, match=r"'gaussian'.*fixed.*list.*sinusoid.*uniform"):
        schedule_from_dict({"kind": "gaussian"})
    with pytest.raises(AdaRLValueError, match=r"kind"):
        schedule_from_dict({"low": {}})
    with pytest.raises(AdaRLValueError, match=r"unknown key.*'lo'.*allowed keys.*'low'"):
        schedule_from_dict({"kind": "uniform", "lo": {}, "high": {}})
    with pytest.raises(AdaRLValueError, match=r"missing key.*'amplitude'"):
        schedule_from_dict({"kind": "sinusoid", "center": {"x": 1.0}, "frequency": 1.0})
    with pytest.raises(AdaRLValueError, match="finite"):
        SinusoidSchedule({"x": 1.0}, {"x": float("nan")}, 1.0)
    with pytest.raises(AdaRLValueError, match="finite"):
        FixedSchedule({"x": "1.0"})
    with pytest.raises(AdaRLValueError, match="non-empty list"):
        ListSchedule([])
    with pytest.raises(AdaRLValueError, match="same parameters"):
        ListSchedule([{"x": 1.0}, {"y": 1.0}])
    with pytest.raises(AdaRLValueError, match=r"'pole_length'.*allowed: \['torso_length'"):
        validate_values("Hopper-v5", {"pole_length": 1.0})
    with pytest.raises(AdaRLValueError, match=r"pole_length.*-0.5.*>= 0.05 and <= 5"):
        validate_values("CartPole-v1", {"pole_length": -0.5})
    with pytest.raises(AdaRLValueError, match=r"gravity.*>= 0"):
        validate_schedule("Ant-v5", UniformSchedule({"gravity": -1.0}, {"gravity": 1.0}))
    with pytest.raises(AdaRLValueError, match="expected a number"):
        validate_values("Ant-v5", {"wind": None})
