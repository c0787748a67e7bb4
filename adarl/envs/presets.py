"""The named perturbation presets: the paper's schedules, its Table 2 boxes, and ours where the paper has none.

Why apart: these are numbers from the paper (and the rules by which we derive ours), read and checked against it on
their own; the registry (:mod:`adarl.envs.registry`) holds which env has which preset and looks them up by name.
Lengths are half-lengths, as MuJoCo capsule sizes and the paper's schedules are.
"""

from __future__ import annotations

from collections.abc import Mapping

from adarl.envs.schedules import FixedSchedule, Schedule, SinusoidSchedule, UniformSchedule

__all__ = ["PRESETS", "generic_presets", "paper_env_presets"]

#: Preset names accepted by :func:`~adarl.envs.registry.make_schedule` (``none``: no perturbation).
PRESETS: tuple[str, ...] = ("paper", "low", "high", "nominal", "none")


def _box(center: Mapping[str, float], half_width: Mapping[str, float]) -> UniformSchedule:
    return UniformSchedule(
        {p: center[p] - half_width[p] for p in center}, {p: center[p] + half_width[p] for p in center}
    )


def _paper_and_boxes(paper: SinusoidSchedule, low_frac: float = 0.5) -> dict[str, Schedule]:
    """Our low/high for the sinusoid envs without a Table 2 box: centre +- half / all of the paper's amplitude."""
    c, a = paper.center, {p: abs(v) for p, v in paper.amplitude.items()}
    return {
        "paper": paper,
        "low": _box(c, {p: low_frac * a[p] for p in c}),
        "high": _box(c, a),
        "nominal": FixedSchedule(c),
    }


def _pole(l0: float) -> dict[str, Schedule]:
    def box(frac: float) -> UniformSchedule:
        return UniformSchedule({"pole_length": (1 - frac) * l0}, {"pole_length": (1 + frac) * l0})

    # paper A.1: l in [0.95 l0, 1.05 l0]; ours: low +-2.5 %, high +-10 %.
    return {"paper": box(0.05), "low": box(0.025), "high": box(0.10), "nominal": FixedSchedule({"pole_length": l0})}


def generic_presets() -> dict[str, Schedule]:
    # Ours (no paper schedule): RRLS-style mass / friction boxes.
    return {
        "low": UniformSchedule({"mass_scale": 0.9, "friction_scale": 0.9}, {"mass_scale": 1.1, "friction_scale": 1.1}),
        "high": UniformSchedule({"mass_scale": 0.7, "friction_scale": 0.7}, {"mass_scale": 1.3, "friction_scale": 1.3}),
        "nominal": FixedSchedule({"mass_scale": 1.0, "friction_scale": 1.0}),
    }


def paper_env_presets() -> dict[str, dict[str, Schedule]]:
    """The presets of the paper's envs (:data:`adarl.envs.registry.PAPER_ENVS`), fresh objects."""
    hopper_paper = SinusoidSchedule(
        {"torso_length": 0.4, "foot_length": 0.39}, {"torso_length": 0.2, "foot_length": 0.2}, 0.2
    )
    walker_paper = SinusoidSchedule(
        {"torso_length": 0.2, "foot_length": 0.1}, {"torso_length": 0.1, "foot_length": 0.05}, 0.3
    )
    out: dict[str, dict[str, Schedule]] = {
        "Hopper-v5": {
            "paper": hopper_paper,
            # paper Table 2
            "low": UniformSchedule(
                {"torso_length": 0.31, "foot_length": 0.305}, {"torso_length": 0.49, "foot_length": 0.485}
            ),
            "high": UniformSchedule(
                {"torso_length": 0.25, "foot_length": 0.245}, {"torso_length": 0.55, "foot_length": 0.545}
            ),
            "nominal": FixedSchedule(hopper_paper.nominal()),
        },
        "Walker2d-v5": {
            "paper": walker_paper,
            # paper Table 2
            "low": UniformSchedule(
                {"torso_length": 0.1, "foot_length": 0.05}, {"torso_length": 0.3, "foot_length": 0.15}
            ),
            "high": UniformSchedule(
                {"torso_length": 0.06, "foot_length": 0.03}, {"torso_length": 0.34, "foot_length": 0.17}
            ),
            "nominal": FixedSchedule(walker_paper.nominal()),
        },
        "Ant-v5": _paper_and_boxes(
            SinusoidSchedule({"gravity": 14.715, "wind": 1.0}, {"gravity": 4.905, "wind": 0.2}, 0.5)
        ),
        "Humanoid-v5": _paper_and_boxes(
            SinusoidSchedule({"gravity": 14.715, "wind": 1.0}, {"gravity": 4.905, "wind": 0.5}, 0.5)
        ),
        "CartPole-v1": _pole(0.5),
        "LinearCartPole-v0": _pole(0.5),
        "InvertedPendulum-v5": _pole(0.3),
    }
    return out
