import imageio.v2 as imageio
import pytest

from rcvae_torchrl.envs import make_pusher_env
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


def test_save_video_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match=r"path: expected a \.gif or \.mp4"):
        save_video([], tmp_path / "x.avi", fps=10)
    with pytest.raises(ValueError, match="frames: expected at least one frame"):
        save_video([], tmp_path / "x.gif", fps=10)


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
