"""Offscreen rendering of the Pusher and saving episodes as GIF or MP4."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rcvae_torchrl._checks import check_positive
from rcvae_torchrl.io import atomic_write
from rcvae_torchrl.processes import try_in_a_child

__all__ = ["gl_unavailable_reason", "record_episode", "render_frame", "save_video"]


def _physics(env: EnvBase):
    base = getattr(env, "base_env", env)
    dm_env = getattr(base, "_env", None)
    physics = getattr(dm_env, "physics", None)
    if physics is None:
        raise TypeError(
            f"env: expected a Pusher env from make_pusher_env (a DMControlWrapper inside), "
            f"got {type(env).__name__}"
        )
    return physics


def render_frame(
    env: EnvBase, height: int = 240, width: int = 240, camera: str = "fixed"
) -> np.ndarray:
    """The current scene as a uint8 RGB image ``[height, width, 3]`` (MuJoCo offscreen)."""
    return _physics(env).render(height=height, width=width, camera_id=camera)


#: Renders one small frame of a one-geom MuJoCo scene through dm_control (the backend the
#: Pusher renders with: ``MUJOCO_GL`` as this process has it).
_RENDER_CHECK = (
    "from dm_control import mujoco\n"
    'xml = \'<mujoco><worldbody><light pos="0 0 1"/><geom size=".1"/></worldbody></mujoco>\'\n'
    "mujoco.Physics.from_xml_string(xml).render(height=16, width=16)"
)
_RENDER_CHECK_S = 120


def gl_unavailable_reason() -> str | None:
    """None when offscreen rendering works here, else why it does not.

    Tried in a child process, once per ``MUJOCO_GL`` value: where no OpenGL context can be
    made, a backend may end the process rather than raise (GLFW without a display aborted a
    GPU machine's test run), which no ``except`` can catch."""
    return _render_check(os.environ.get("MUJOCO_GL"))


@functools.cache
def _render_check(backend: str | None) -> str | None:
    head = f"offscreen OpenGL unavailable (MUJOCO_GL={backend})"
    try:
        outcome = try_in_a_child(_RENDER_CHECK, timeout=_RENDER_CHECK_S)
    except OSError as err:
        return f"{head}: no process could be started for a test render: {err}"
    return None if outcome.problem is None else f"{head}: a test render failed: {outcome.problem}"


def save_video(frames: list[np.ndarray], path: str | Path, fps: float) -> Path:
    """Write uint8 frames ``[H, W, 3]`` to a .gif (or .mp4, with imageio-ffmpeg), atomically;
    ``fps``: frames per second, a positive finite number."""
    check_positive("fps", fps)
    path = Path(path)
    if path.suffix not in (".gif", ".mp4"):
        raise ValueError(f"path: expected a .gif or .mp4 file name, got {str(path)!r}")
    if not frames:
        raise ValueError("frames: expected at least one frame, got none")
    options = {"duration": 1000.0 / fps, "loop": 0} if path.suffix == ".gif" else {"fps": fps}
    data = iio.imwrite("<bytes>", np.stack(frames), extension=path.suffix, **options)
    return atomic_write(path, lambda f: f.write(data))


def record_episode(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    path: str | Path,
    max_steps: int = 600,
    every: int = 2,
    height: int = 240,
    width: int = 240,
) -> TensorDictBase:
    """Roll ``policy`` out in ``env`` until done, save every ``every``-th frame to ``path``.

    Returns the rollout tensordict; the video plays in real time.
    """
    frames = [render_frame(env, height, width)]

    def grab(env_: EnvBase, td: TensorDictBase) -> None:
        if len(frames) * every <= grab.step:
            frames.append(render_frame(env_, height, width))
        grab.step += 1

    grab.step = 1
    with torch.no_grad():
        rollout = env.rollout(max_steps, policy, callback=grab, break_when_any_done=True)
    dt = float(_physics(env).timestep()) * _n_sub_steps(env)
    save_video(frames, path, fps=1.0 / (dt * every))
    return rollout


def _n_sub_steps(env: EnvBase) -> int:
    return int(getattr(env, "base_env", env)._env._n_sub_steps)
