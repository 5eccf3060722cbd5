"""Robot paths of test episodes (the paper's Figure 5) and MuJoCo videos of them.

:func:`collect_trajectories` runs deterministic test episodes and keeps the robot's
positions, the goal positions and the layout (hazards with their radius, goal,
placement extents). Every episode is played on the layout of the first one (its
goal, hazards and vases are replayed through ``reset(options={"layout": ...})``),
with a fresh random robot start, so all paths of a run fit one picture — on
StaticEnv this is the env's own fixed layout, as in the paper.

:func:`render_episode` renders one such episode with MuJoCo (``MUJOCO_GL=egl`` on a
headless machine) and :func:`write_video` encodes the frames: ``.mp4`` through an
``ffmpeg`` executable (on ``PATH``, or the one the optional ``imageio-ffmpeg``
package ships), ``.gif`` through Pillow (always available: matplotlib needs it).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = [
    "Trajectory",
    "TrajectoryError",
    "VideoError",
    "collect_trajectories",
    "ffmpeg_executable",
    "layout_of",
    "render_episode",
    "write_video",
]

_REPLAYED_KEYS = ("goal_xy", "hazards_xy", "vases_xy")


class TrajectoryError(ValueError):
    """The env cannot give trajectories (no layout) or videos (does not render)."""


class VideoError(RuntimeError):
    """No encoder for the requested video format; the message says what to install."""


@dataclass
class Trajectory:
    """One test episode's path.

    Attributes:
        xy: robot positions, shape ``(length + 1, 2)`` (the start included).
        goals: the goal centres in the order they were active, shape ``(k, 2)``
            (``k > 1`` when reaching a goal re-draws it, as on DynamicEnv).
        in_hazard: per step, whether the step had a cost, shape ``(length,)``.
        ret, cost: episodic return and cost.
        length: steps.
        goals_reached: goals reached during the episode.
    """

    xy: np.ndarray
    goals: np.ndarray
    in_hazard: np.ndarray
    ret: float
    cost: float
    length: int
    goals_reached: int


def _gym_env(env: EnvBase) -> Any:
    """The gymnasium env (unwrapped) under a TorchRL env built by ``make_env``."""
    base = env
    while hasattr(base, "base_env"):
        base = base.base_env
    gym_env = getattr(base, "_env", None)
    if gym_env is None or not hasattr(gym_env.unwrapped, "layout"):
        raise TrajectoryError(
            "trajectory plots need an env built by wcsac_rl.envs.make_env whose gymnasium "
            "env has layout() (the point-goal presets or tiny)"
        )
    return gym_env.unwrapped


def layout_of(env: EnvBase) -> dict[str, Any]:
    """The current layout of ``env`` (``PointGoalEnv.layout()`` format, numpy arrays)."""
    return _gym_env(env).layout()


def _replay_options(layout: dict[str, Any]) -> dict[str, Any]:
    replay = {}
    for key in _REPLAYED_KEYS:
        value = np.asarray(layout.get(key, np.zeros((0, 2))))
        if value.size:
            replay[key] = value.tolist()
    return {"layout": replay}


def _goals(start_goal: np.ndarray, goal_steps: np.ndarray) -> np.ndarray:
    goals = [np.asarray(start_goal, dtype=np.float64)]
    for g in np.asarray(goal_steps, dtype=np.float64):
        if np.linalg.norm(g - goals[-1]) > 1e-9:
            goals.append(g)
    return np.stack(goals)


def _episode(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    max_steps: int,
    options: dict[str, Any] | None,
) -> TensorDictBase:
    td = env.reset(options=options) if options else env.reset()
    return env.rollout(max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=True)


def collect_trajectories(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    num_episodes: int,
    *,
    max_steps: int,
    deterministic: bool = True,
    same_layout: bool = True,
) -> tuple[dict[str, Any], list[Trajectory]]:
    """Run ``num_episodes`` episodes of ``policy`` and record the robot's paths.

    Args:
        env: an unbatched env from :func:`wcsac_rl.envs.make_env` (a point-goal preset
            or tiny); its steps carry ``robot_xy`` and ``goal_xy``.
        policy: the actor; ``None`` acts uniformly at random.
        num_episodes: how many episodes.
        max_steps: bound on an episode's length.
        deterministic: mean actions (the paper's test episodes).
        same_layout: replay the first episode's goal, hazards and vases in the others.

    Returns:
        ``(layout, trajectories)``: the first episode's layout and one
        :class:`Trajectory` per episode.
    """
    if env.batch_size != torch.Size([]):
        raise ValueError(f"collect_trajectories needs an unbatched env, got {env.batch_size}")
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    gym_env = _gym_env(env)
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    layout: dict[str, Any] | None = None
    options = None
    trajectories = []
    with torch.no_grad(), set_exploration_type(exploration):
        for _ in range(num_episodes):
            td = _episode(env, policy, max_steps, options)
            if layout is None:
                layout = gym_env.layout()
                layout["robot_xy"] = td["robot_xy"][0].numpy().astype(np.float64)
                if same_layout:
                    options = _replay_options(layout)
            nxt = td["next"]
            xy = torch.cat([td["robot_xy"][:1], nxt["robot_xy"]]).numpy().astype(np.float64)
            goal = nxt.get("goal_reached", None)
            trajectories.append(
                Trajectory(
                    xy=xy,
                    goals=_goals(td["goal_xy"][0].numpy(), nxt["goal_xy"].numpy()),
                    in_hazard=(nxt["cost"].reshape(-1) > 0).numpy(),
                    ret=float(nxt["reward"].sum()),
                    cost=float(nxt["cost"].sum()),
                    length=int(td.shape[-1]),
                    goals_reached=0 if goal is None else int(goal.sum()),
                )
            )
    assert layout is not None
    return layout, trajectories


def render_episode(
    env_name: str,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    *,
    seed: int,
    max_steps: int,
    width: int = 480,
    height: int = 480,
    camera: str = "top",
    layout: dict[str, Any] | None = None,
    **env_kwargs: Any,
) -> np.ndarray:
    """Render one deterministic test episode with MuJoCo: frames ``(T + 1, H, W, 3)`` uint8.

    Args:
        env_name: a MuJoCo preset (``static``, ``dynamic``, ``point_goal1``, ``point_goal2``).
        policy: the actor (``None``: uniform random actions).
        seed: the env seed.
        max_steps: bound on the episode's length.
        width, height: frame size in pixels.
        camera: ``"top"`` (top-down, like Figure 5) or ``"overview"``.
        layout: replay this layout's goal, hazards and vases (e.g. the one of
            :func:`collect_trajectories`).
        **env_kwargs: further ``make_env`` keywords (e.g. ``max_episode_steps``).

    Raises:
        TrajectoryError: the env does not render (``tiny``) or MuJoCo has no GL context.
    """
    from wcsac_rl.envs import make_env

    try:
        env = make_env(
            env_name,
            seed=seed,
            from_pixels=True,
            width=width,
            height=height,
            camera=camera,
            **env_kwargs,
        )
    except (ValueError, TypeError) as err:
        raise TrajectoryError(
            f"cannot render env {env_name!r} ({err}); videos need a MuJoCo preset "
            "(static, dynamic, point_goal1, point_goal2)"
        ) from None
    try:
        torch.manual_seed(seed)
        options = _replay_options(layout) if layout is not None else None
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            try:
                td = _episode(env, policy, max_steps, options)
            except RuntimeError as err:
                raise TrajectoryError(str(err)) from None
        return torch.cat([td["pixels"][:1], td["next", "pixels"]]).numpy()
    finally:
        env.close()


def ffmpeg_executable() -> str | None:
    """An ``ffmpeg`` executable: ``ffmpeg`` on ``PATH``, else imageio-ffmpeg's, else ``None``."""
    found = shutil.which("ffmpeg")
    if found:
        return found
    try:
        import imageio_ffmpeg  # optional
    except ImportError:
        return None
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError:
        return None


def write_video(frames: np.ndarray, out: str | os.PathLike, *, fps: float = 50.0) -> Path:
    """Encode ``frames`` (``T x H x W x 3`` uint8) to ``out`` by its suffix (``.mp4`` or ``.gif``).

    Raises:
        VideoError: ``.mp4`` without an ffmpeg (install ``imageio-ffmpeg`` or the
            system's ``ffmpeg``, or ask for ``.gif``), or another suffix.
    """
    out = Path(out)
    frames = np.ascontiguousarray(frames, dtype=np.uint8)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise ValueError(f"frames must have shape (T, H, W, 3) with T > 0, got {frames.shape}")
    suffix = out.suffix.lower()
    if suffix == ".gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        images[0].save(
            out,
            save_all=True,
            append_images=images[1:],
            duration=max(20, round(1000 / fps)),
            loop=0,
        )
        return out
    if suffix != ".mp4":
        raise VideoError(f"unsupported video format {out.suffix!r}; use .mp4 or .gif")
    ffmpeg = ffmpeg_executable()
    if ffmpeg is None:
        raise VideoError(
            "writing .mp4 needs ffmpeg, which is not installed: `pip install imageio-ffmpeg` "
            "(it ships an ffmpeg binary) or install the system's ffmpeg, or use --video-format gif"
        )
    height, width = frames.shape[1:3]
    if height % 2 or width % 2:  # yuv420p needs even sizes
        frames = frames[:, : height - height % 2, : width - width % 2]
        height, width = frames.shape[1:3]
    raw = f"-y -loglevel error -f rawvideo -pix_fmt rgb24 -s {width}x{height} -r {fps:g} -i -"
    cmd = [ffmpeg, *raw.split(), *"-an -vcodec libx264 -pix_fmt yuv420p".split(), str(out)]
    proc = subprocess.run(cmd, input=frames.tobytes(), capture_output=True, check=False)
    if proc.returncode != 0:
        raise VideoError(f"ffmpeg failed: {proc.stderr.decode(errors='replace').strip()}")
    return out
