"""``adarl play RUN``: watch a trained policy act, on the nominal dynamics or on dynamics you choose, and record
it to a video.

The policy comes from :func:`adarl.load_policy`; the env is the run's (same id, time limit and perturbation mode)
with its dynamics fixed at the centre of the training schedule (what the evaluations use), each ``--perturb
PARAM=V`` replacing one parameter. Rendering is headless (MuJoCo's ``MUJOCO_GL=egl``, or ``osmesa``) and the video
is written by gymnasium's ``RecordVideo`` wrapper (moviepy, which brings its own ffmpeg: ``pip install
'adarl[video]'``); one file holds every episode.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
from gymnasium.error import DependencyNotInstalled
from gymnasium.wrappers import RecordVideo
from torchrl.envs import Compose, DoubleToFloat, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.libs.gym import GymWrapper

from adarl.envs.factory import make_env, resolve_schedule
from adarl.envs.linear_cartpole import LINEAR_CARTPOLE_ID
from adarl.envs.perturbation import PerturbedDynamicsEnvTransform
from adarl.envs.registry import is_mujoco, quiet_mujoco, validate_values
from adarl.envs.schedules import FixedSchedule
from adarl.errors import AdaRLError, AdaRLValueError, MissingExtraError
from adarl.runtime.evaluation import evaluate_policy
from adarl.runtime.policy import load_policy_with_info

__all__ = ["PlayResult", "parse_perturb", "play"]


@dataclass
class PlayResult:
    """Per-episode returns and lengths, the dynamics they ran under and the video written (if any)."""

    returns: list[float]
    lengths: list[int]
    dynamics: dict[str, float]
    frames: int
    checkpoint: Path
    video: Path | None = None
    notes: list[str] = field(default_factory=list)


def parse_perturb(items) -> dict[str, float]:
    """``["torso_length=0.5", ...]`` -> ``{"torso_length": 0.5}``."""
    out: dict[str, float] = {}
    for text in items or ():
        name, sep, value = str(text).partition("=")
        name = name.strip()
        try:
            v = float(value)
        except ValueError:
            v = math.nan
        if not sep or not name or not math.isfinite(v):
            raise AdaRLValueError(
                f"--perturb {text!r} must look like PARAM=VALUE with a finite number, e.g. torso_length=0.5"
            )
        out[name] = v
    return out


def _dynamics(recipe, perturb: dict[str, float]) -> dict[str, float]:
    """The nominal values of the run's schedule (the evaluations' dynamics), with ``perturb`` applied."""
    p = recipe.env.perturbation
    sched = resolve_schedule(recipe.env.id, p.preset, p.schedule) if recipe.eval.nominal else None
    values = dict(sched.nominal()) if sched is not None else {}
    values.update(perturb)
    return validate_values(recipe.env.id, values, recipe.env.declared()) if values else {}


def _recording_env(recipe, values: dict[str, float], folder: Path, size: tuple[int, int]):
    """gymnasium env (rgb_array) -> RecordVideo -> TorchRL GymWrapper -> the run's transforms."""
    env_id = recipe.env.id
    if env_id == LINEAR_CARTPOLE_ID:
        raise AdaRLValueError(f"{env_id} is adarl's linearised CartPole and has no renderer; play it without --video")
    kwargs = {"render_mode": "rgb_array"}
    if recipe.env.max_episode_steps is not None:
        kwargs["max_episode_steps"] = recipe.env.max_episode_steps
    if is_mujoco(env_id):  # MuJoCo's renderer takes a size; gymnasium's other renderers do not
        kwargs.update(width=size[0], height=size[1])
    with quiet_mujoco():
        base = gym.make(env_id, **kwargs)
    try:
        base.reset(seed=0)
        frame = base.render()
    except DependencyNotInstalled as err:  # CartPole draws with pygame
        base.close()
        raise AdaRLError(f"rendering {env_id} needs a package that is not installed: {err}") from None
    except Exception as err:  # noqa: BLE001 - any GL failure: say how to render headless
        base.close()
        gl = os.environ.get("MUJOCO_GL", "(unset)")
        raise AdaRLError(
            f"headless rendering of {env_id} failed with MUJOCO_GL={gl}: {type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''}; MuJoCo renders without a display through "
            f"MUJOCO_GL=egl (libEGL: Debian's libegl1 and libegl-mesa0) or MUJOCO_GL=osmesa "
            f"(libosmesa6)"
        ) from None
    if frame is None:
        base.close()
        raise AdaRLError(f"{env_id} rendered no frame (render_mode='rgb_array')")
    try:
        recorder = RecordVideo(
            base,
            str(folder),
            episode_trigger=lambda i: False,
            video_length=10**9,
            name_prefix="play",
            disable_logger=True,
        )
    except DependencyNotInstalled:
        base.close()
        raise MissingExtraError(
            "--video needs moviepy (gymnasium's RecordVideo writes with it): pip install 'adarl[video]'"
        ) from None
    transforms = []
    if values:
        p = recipe.env.perturbation
        transforms.append(
            PerturbedDynamicsEnvTransform(
                env_id, FixedSchedule(values), mode=p.mode, out_key=p.key, parameters=recipe.env.declared()
            )
        )
    env = TransformedEnv(GymWrapper(recorder), Compose(*transforms, DoubleToFloat(), StepCounter(), RewardSum()))
    return env, recorder


def _plain_env(recipe, values: dict[str, float]):
    p = recipe.env.perturbation
    common = dict(
        mode=p.mode,
        dynamics_key=p.key,
        max_episode_steps=recipe.env.max_episode_steps,
        parameters=recipe.env.declared(),
    )
    if values:
        return make_env(recipe.env.id, schedule=FixedSchedule(values), **common)
    return make_env(recipe.env.id, perturb=False, **common)


def play(
    run: str | os.PathLike,
    *,
    which: str = "latest",
    episodes: int = 1,
    video: str | os.PathLike | None = None,
    perturb: dict[str, float] | None = None,
    max_steps: int | None = None,
    seed: int = 0,
    size: tuple[int, int] = (480, 480),
) -> PlayResult:
    """Run ``episodes`` deterministic episodes of the policy of ``run`` (a run folder or checkpoint file) and,
    with ``video``, write them to that MP4 file."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise AdaRLValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    if video is not None and Path(video).suffix.lower() != ".mp4":
        raise AdaRLValueError(f"--video {str(video)!r}: the video is an MP4 file; allowed: a path ending in .mp4")
    loaded = load_policy_with_info(run, which)
    recipe = loaded.recipe
    values = _dynamics(recipe, perturb or {})
    steps = max_steps if max_steps is not None else recipe.eval.max_steps
    with tempfile.TemporaryDirectory(prefix="adarl-play-") as tmp:
        if video is not None:
            env, recorder = _recording_env(recipe, values, Path(tmp) / "video", size)
        else:
            env, recorder = _plain_env(recipe, values), None
        try:
            env.set_seed(seed)
            if recorder is not None:
                recorder.start_recording("play")
            result = evaluate_policy(loaded.actor, env, episodes=episodes, max_steps=steps)
            out = None
            if recorder is not None:
                recorder.stop_recording()
                out = Path(video)
                out.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(str(Path(tmp) / "video" / "play.mp4"), out)
        finally:
            env.close()
    return PlayResult(result.returns, result.lengths, values, loaded.frames, loaded.checkpoint, out)
