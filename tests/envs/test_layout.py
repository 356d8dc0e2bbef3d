import pytest
import torch

from rcvae_torchrl.envs import (
    OBSERVATION_DIM,
    OBSERVATION_LAYOUT,
    OBSERVATION_NAMES,
    OBSERVATION_PARTS,
    OBSERVATION_RESOLUTION,
    make_pusher_env,
    obs_indices,
    obs_slice,
    resolution_tensor,
)


def test_layout_is_complete_and_consistent():
    assert OBSERVATION_DIM == 14 == len(OBSERVATION_LAYOUT)
    assert sorted(OBSERVATION_LAYOUT.values()) == list(range(14))
    assert set(OBSERVATION_RESOLUTION) == set(OBSERVATION_NAMES)
    assert obs_indices("ball", "target_y") == [8, 9, 13]
    res = resolution_tensor()
    assert res.shape == (14,) and (res > 0).all()


def test_unknown_name():
    with pytest.raises(KeyError, match="unknown observation name 'elbow'"):
        obs_indices("elbow")


def test_layout_matches_the_physics():
    env = make_pusher_env(seed=2)
    obs = env.reset()["observation"]
    physics = env.base_env._env.physics
    q = torch.as_tensor(physics.arm_angles(), dtype=torch.float32)
    torch.testing.assert_close(obs[obs_indices("shoulder_cos", "wrist_cos")], q.cos())
    torch.testing.assert_close(obs[obs_indices("shoulder_sin", "wrist_sin")], q.sin())
    for name, value in [
        ("finger", physics.finger_xy()),
        ("ball", physics.ball_xy()),
        ("target", physics.target_xy()),
    ]:
        torch.testing.assert_close(obs[obs_indices(name)], torch.tensor(value, dtype=torch.float32))
    # Fingertip at the end of two 0.12 m links.
    c1, s1, c2, s2 = obs[obs_indices("shoulder_cos", "shoulder_sin", "wrist_cos", "wrist_sin")]
    fx = 0.12 * c1 + 0.12 * (c1 * c2 - s1 * s2)
    fy = 0.12 * s1 + 0.12 * (s1 * c2 + c1 * s2)
    torch.testing.assert_close(obs[obs_indices("finger")], torch.stack([fx, fy]), atol=1e-6, rtol=0)


def test_obs_slice_views_what_obs_indices_gathers():
    obs = torch.randn(3, 14)
    for names in (("shoulder_cos", "wrist_cos"), ("shoulder_sin", "wrist_sin"), ("ball",)):
        span = obs_slice(*names)
        assert isinstance(span, slice)
        assert torch.equal(obs[..., span], obs[..., obs_indices(*names)])
        assert obs[..., span].data_ptr() == obs[..., span.start].data_ptr()  # a view


def test_obs_slice_refuses_uneven_dimensions():
    with pytest.raises(ValueError, match=r"names: \('ball_x', 'target'\) are not evenly spaced"):
        obs_slice("ball_x", "target")


def test_observation_parts_cover_the_layout_once():
    covered = [i for part in OBSERVATION_PARTS.values() for i in range(OBSERVATION_DIM)[part]]
    assert sorted(covered) == list(range(OBSERVATION_DIM))
    assert OBSERVATION_PARTS["cos"] == obs_slice("shoulder_cos", "wrist_cos")
    assert OBSERVATION_PARTS["target"] == obs_slice("target")


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, "float32"])
def test_resolution_tensor_takes_floating_dtypes_only(dtype):
    assert resolution_tensor(torch.float64).dtype == torch.float64
    with pytest.raises(TypeError, match=r"dtype: expected a floating-point torch\.dtype, got "):
        resolution_tensor(dtype)
