import imageio.v2 as imageio
import numpy as np
import pytest

from rcvae_torchrl import processes
from rcvae_torchrl.envs import make_pusher_env, render
from rcvae_torchrl.envs.render import (
    gl_unavailable_reason,
    record_episode,
    render_frame,
    save_video,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy

_REASON = gl_unavailable_reason()
needs_gl = pytest.mark.skipif(_REASON is not None, reason=_REASON or "")


@needs_gl
def test_render_one_frame():
    frame = render_frame(make_pusher_env(seed=0), 64, 80)
    assert frame.shape == (64, 80, 3) and frame.dtype.name == "uint8"
    assert frame.std() > 5, "the frame should show a scene, not a flat colour"


@needs_gl
def test_record_episode_gif(tmp_path):
    path = tmp_path / "episode.gif"
    td = record_episode(make_pusher_env(seed=3), make_scripted_policy(), path, height=48, width=48)
    frames = imageio.mimread(path)
    assert len(frames) == td.shape[0] // 2 + 1
    assert td["next", "success"].any()


@pytest.mark.parametrize(
    ("check", "why"),
    [
        ("import os\nos.abort()", "a test render failed: its process was ended by SIGABRT"),
        (
            "raise RuntimeError('no EGL context')",
            "a test render failed: RuntimeError: no EGL context",
        ),
    ],
)
def test_a_backend_that_cannot_render_is_a_reason_not_a_crash(monkeypatch, check, why):
    """The test render runs in a child process (GLFW without a display aborted a GPU
    machine's test run in-process), once per backend."""
    runs, run = [], processes.subprocess.run
    monkeypatch.setattr(processes.subprocess, "run", lambda *a, **k: runs.append(a) or run(*a, **k))
    monkeypatch.setattr(render, "_RENDER_CHECK", check)
    render._render_check.cache_clear()
    try:
        for _ in range(2):
            reason = gl_unavailable_reason()
            assert reason.startswith("offscreen OpenGL unavailable (MUJOCO_GL=")
            assert reason.endswith(why) and len(runs) == 1
    finally:
        render._render_check.cache_clear()


def test_save_video_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match=r"path: expected a \.gif or \.mp4"):
        save_video([], tmp_path / "x.avi", fps=10)
    with pytest.raises(ValueError, match="frames: expected at least one frame"):
        save_video([], tmp_path / "x.gif", fps=10)


@pytest.mark.parametrize("fps", [0, -5, float("nan"), float("inf")])
def test_save_video_names_a_frame_rate_that_is_not_positive(tmp_path, fps):
    frames = [np.zeros((4, 4, 3), dtype=np.uint8)]
    with pytest.raises(ValueError, match=f"fps: expected a positive number, got {fps}"):
        save_video(frames, tmp_path / "x.gif", fps=fps)
    assert not (tmp_path / "x.gif").exists()


@needs_gl
def test_pixels_from_the_torchrl_env():
    from torchrl.envs.utils import check_env_specs

    env = make_pusher_env(seed=0, from_pixels=True)
    check_env_specs(env)
    td = env.rollout(2)
    assert (
        td["next", "pixels"].shape[-1] == 3
        and td["next", "pixels"].dtype.is_floating_point is False
    )
    assert td["next", "observation"].shape == (2, 14)


def _import_in_child(**env_vars: str | None) -> str:
    """``MUJOCO_GL`` after importing the envs in a fresh interpreter with ``env_vars`` (None:
    unset); raises if the import fails."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in env_vars}
    env.update({k: v for k, v in env_vars.items() if v is not None})
    code = "import os, rcvae_torchrl.envs; print(os.environ.get('MUJOCO_GL'))"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1]


def test_an_egl_that_cannot_be_loaded_is_not_chosen():
    """An EGL library that PyOpenGL cannot use made every import of the package fail (MuJoCo
    and dm_control load their EGL backend when imported): here PyOpenGL is pinned to another
    platform. EGL is then not chosen, and the import works."""
    assert _import_in_child(MUJOCO_GL=None, PYOPENGL_PLATFORM="glx") == "None"


def test_a_chosen_backend_is_left_as_it_is():
    assert _import_in_child(MUJOCO_GL="disable") == "disable"
