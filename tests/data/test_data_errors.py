"""Bad input to the data helpers gives errors that name the argument, what was expected and
what was given, instead of data dropped or actions drawn from a wrapped seed."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn

from rcvae_torchrl.data import (
    TRAJ_KEY,
    ActionNoise,
    GaussianExploration,
    ObservationLayout,
    UniformRandomPolicy,
    make_window_buffer,
    sample_windows,
    split_episodes,
)


def _episodes(count: int = 3, length: int = 6) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    parts = []
    for e in range(count):
        x = torch.randn(length + 1, 3, generator=g)
        parts.append(
            TensorDict(
                {
                    "observation": x[:-1],
                    "action": torch.rand(length, 1, generator=g),
                    ("next", "observation"): x[1:],
                    ("next", "done"): torch.zeros(length, 1, dtype=torch.bool),
                    TRAJ_KEY: torch.full((length,), e, dtype=torch.int64),
                },
                [length],
            )
        )
    return torch.cat(parts)


def test_a_buffer_smaller_than_its_data_is_refused():
    """max_size=4 kept the last 4 of 18 frames while the episodes' starts pointed at gone ones."""
    data = _episodes()
    with pytest.raises(ValueError, match=r"max_size: expected at least the 18 frames of data"):
        make_window_buffer(data, 3, max_size=4)
    for bad in (0, -5, 20.5, True):
        with pytest.raises(ValueError, match="max_size: expected a positive integer"):
            make_window_buffer(data, 3, max_size=bad)
    for bad in ("3", None, 2.5):
        with pytest.raises(ValueError, match=r"window: expected >= 2 steps \(an integer\)"):
            make_window_buffer(data, bad)
    assert len(make_window_buffer(data, 3, max_size=40)) == 18


def test_sample_windows_names_its_arguments():
    buffer = make_window_buffer(_episodes(), 3)
    generators = [torch.Generator().manual_seed(i) for i in range(2)]
    with pytest.raises(TypeError, match="buffer: expected a buffer of make_window_buffer"):
        sample_windows(None, 4, 3)
    with pytest.raises(TypeError, match=r"buffer\[1\]: expected a buffer of make_window_buffer"):
        sample_windows([buffer, "x"], 4, 3, members=2, generators=generators)
    for bad in (0, -1, 2.5):
        with pytest.raises(ValueError, match="members: expected a positive integer or None"):
            sample_windows(buffer, 4, 3, members=bad)
    with pytest.raises(TypeError, match=r"generators\[1\]: expected a torch.Generator, got int"):
        sample_windows(buffer, 4, 3, members=2, generators=[generators[0], 2])
    with pytest.raises(ValueError, match=r"start_windows: expected an integer >= 0, got 1.5"):
        sample_windows(buffer, 4, 3, members=2, generators=generators, start_windows=1.5)
    assert sample_windows(buffer, 4, 3, members=2, generators=generators).shape == (2, 4, 3)


def test_layouts_name_their_keys_and_sizes():
    with pytest.raises(ValueError, match=r"keys: expected distinct entries, got \('a', 'a'\)"):
        ObservationLayout(("a", "a"), (1, 2))
    for sizes in ((-1,), (0,), (1.5,)):
        with pytest.raises(ValueError, match="sizes: expected a positive integer per entry"):
            ObservationLayout(("a",), sizes)
    with pytest.raises(TypeError, match=r"keys: expected a tuple .* got the string 'ab'"):
        ObservationLayout("ab", (1, 1))
    with pytest.raises(TypeError, match=r"keys: expected entry names \(str\), got 1"):
        ObservationLayout((1, 2), (1, 1))
    for names in ("abc", [], None):
        with pytest.raises(ValueError, match="names: expected a non-empty sequence"):
            ObservationLayout.from_names(names)
    assert ObservationLayout(("p", ("agent", "v")), (2, 1)).dim == 3


def test_exploration_noise_seeds_and_bounds_are_checked():
    """A negative seed wrapped to 2**64 - 1; an infinite std gave bang-bang actions; NaN bounds
    sent NaN actions to the env."""
    policy = nn.Linear(3, 2)
    for seed in (-1, 1.5, "0", True):
        with pytest.raises(ValueError, match="seed: expected an integer seed >= 0"):
            GaussianExploration(policy, 0.1, seed=seed)
        with pytest.raises(ValueError, match="seed: expected an integer seed >= 0"):
            UniformRandomPolicy(2, seed=seed)
        with pytest.raises(ValueError, match="seed: expected an integer seed >= 0"):
            ActionNoise(0.1, seed=seed)
        with pytest.raises(ValueError, match="seed: expected an integer seed >= 0"):
            split_episodes(_episodes(), 0.5, seed=seed)
    for std in (math.inf, math.nan, -0.1, "0.1"):
        with pytest.raises(ValueError, match="noise_std: expected a finite std >= 0"):
            GaussianExploration(policy, std)
    with pytest.raises(TypeError, match="policy: expected a module mapping observations"):
        GaussianExploration(5, 0.1)
    with pytest.raises(ValueError, match=r"low, high: expected low <= high \(and no NaN\)"):
        ActionNoise(0.0, low=1.0, high=-1.0)
    with pytest.raises(ValueError, match=r"low: expected low <= high \(and no NaN\)"):
        ActionNoise(0.1, low=math.nan)
    with pytest.raises(TypeError, match="high: expected a number, a tensor or None, got '1'"):
        ActionNoise(0.1, high="1")
    with pytest.raises(ValueError, match=r"val_fraction: expected a fraction in \(0, 1\)"):
        split_episodes(_episodes(), "0.5")
    # NumPy integers are seeds too
    a, b = GaussianExploration(policy, 0.1, seed=np.int64(3)), GaussianExploration(policy, 0.1, 3)
    x = torch.zeros(4, 3)
    assert torch.equal(a(x), b(x))


def test_envs_policies_ids_and_keys_are_named():
    """A None policy collected at random; data without episode ids or actions, and objects
    that are not envs, failed as NoneType or attribute errors."""
    from torchrl.envs import GymLikeEnv  # noqa: F401  (only to be sure TorchRL is importable)

    from rcvae_torchrl.data import (
        AngleAsCosSin,
        action_bounds,
        check_actions,
        check_episode_ids,
        collect_episodes,
        control_step,
        episode_ids,
        merge_episodes,
        observation_layout,
        prepare_env,
        seed_env,
    )
    from rcvae_torchrl.data.replay import episode_spans

    no_ids = _episodes().exclude(TRAJ_KEY)
    for call in (
        lambda: episode_ids(no_ids),
        lambda: episode_spans(no_ids),
        lambda: check_episode_ids(no_ids),
        lambda: merge_episodes(no_ids),
    ):
        with pytest.raises(KeyError, match=r"expected episode ids under \('collector', 'traj_i"):
            call()
    with pytest.raises(TypeError, match="data: expected a TensorDict of episodes, got dict"):
        episode_ids({})
    with pytest.raises(TypeError, match=r"policy: expected a TorchRL policy .* got NoneType"):
        collect_episodes(lambda: None, None, 1)
    with pytest.raises(TypeError, match=r"desc: expected the progress bar's label \(a str\)"):
        collect_episodes(lambda: None, lambda td: td, 1, desc=5)
    with pytest.raises(TypeError, match="make_env: expected it to return a TorchRL env, got int"):
        collect_episodes(lambda: 5, lambda td: td, 1)
    for call in (
        lambda: seed_env(5, 0),
        lambda: control_step(5),
        lambda: observation_layout(5),
        lambda: prepare_env(5),
        lambda: action_bounds(5),
        lambda: check_actions(5, _episodes()),
    ):
        with pytest.raises(TypeError, match=r"env: expected a TorchRL env \(an EnvBase\), got int"):
            call()
    with pytest.raises(TypeError, match=r"in_keys: expected keys \(str or tuples of str\), got 5"):
        AngleAsCosSin([5])


def test_acting_generators_and_a_noise_std_string_are_named():
    from rcvae_torchrl.data import acting

    with pytest.raises(TypeError, match=r"generators\[0\]: expected a torch.Generator, got 5"):
        with acting(seed=0, generators=[5]):
            pass
    with pytest.raises(TypeError, match=r"std: expected a number or a tensor, got '0\.1'"):
        ActionNoise("0.1")
