"""Episode collection, exploration policies, episode splits and window sampling."""

import functools
import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase

from rcvae_torchrl.data import (
    TRAJ_KEY,
    GaussianExploration,
    UniformRandomPolicy,
    check_episode_ids,
    collect_episodes,
    episode_spans,
    make_policy_module,
    make_window_buffer,
    resample_episodes,
    sample_windows,
    split_episodes,
)
from rcvae_torchrl.envs import make_pusher_env
from rcvae_torchrl.envs.scripted import ScriptedPusher


@pytest.fixture(scope="module")
def episodes():
    policy = make_policy_module(UniformRandomPolicy(2, hold=3, seed=0))
    make_env = functools.partial(make_pusher_env, "deterministic", time_limit=2.0)
    return collect_episodes(make_env, policy, 6, seed=1, frames_per_batch=50, progress=False)


def test_collect_whole_episodes(episodes):
    ids = episodes[TRAJ_KEY]
    assert torch.equal(torch.unique(ids), torch.arange(6))
    assert episodes.shape == (6 * 40,)  # 2 s episodes of 0.05 s steps, random actions never win
    ends = episodes["next", "done"].squeeze(-1)
    assert ends.sum() == 6 and ends[-1]
    # Within an episode, the next observation is the following step's observation.
    same = ids[1:] == ids[:-1]
    torch.testing.assert_close(
        episodes["next", "observation"][:-1][same], episodes["observation"][1:][same]
    )


def test_collection_is_reproducible():
    make_env = functools.partial(make_pusher_env, "stochastic", time_limit=1.0)

    def run(seed):
        policy = make_policy_module(GaussianExploration(ScriptedPusher(), 0.3, seed=seed))
        return collect_episodes(make_env, policy, 2, seed=seed, frames_per_batch=20, progress=False)

    a, b, c = run(3), run(3), run(4)
    assert torch.equal(a["observation"], b["observation"])
    assert torch.equal(a["action"], b["action"])
    assert not torch.equal(a["observation"][:5], c["observation"][:5])


def test_windows_never_cross_episodes(episodes):
    buffer = make_window_buffer(episodes, window=16)
    windows = sample_windows(buffer, num_windows=32, window=16, members=3)
    assert windows.shape == (3, 32, 16)
    ids = windows[TRAJ_KEY]
    assert (ids == ids[..., :1]).all()
    torch.testing.assert_close(
        windows["observation"][..., 1:, :], windows["next", "observation"][..., :-1, :]
    )
    # Members draw independent windows.
    assert not torch.equal(windows["observation"][0], windows["observation"][1])


def test_a_window_buffer_draws_as_a_lazily_filled_one_and_logs_nothing(episodes):
    import logging

    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    from torchrl.data.replay_buffers.samplers import SliceSampler

    records = []
    handler = logging.Handler()
    handler.emit = records.append
    torchrl_log = logging.getLogger("torchrl")
    torchrl_log.addHandler(handler)
    try:
        buffer = make_window_buffer(episodes, window=16)
    finally:
        torchrl_log.removeHandler(handler)
    assert [r.getMessage() for r in records] == []
    sampler = SliceSampler(
        slice_len=16, traj_key=TRAJ_KEY, strict_length=True, truncated_key=None, cache_values=True
    )
    lazy = TensorDictReplayBuffer(storage=LazyTensorStorage(episodes.shape[0]), sampler=sampler)
    lazy.extend(episodes)
    lazy.episode_starts = buffer.episode_starts
    a = sample_windows(buffer, 8, 16, 2, [torch.Generator().manual_seed(s) for s in (1, 2)])
    b = sample_windows(lazy, 8, 16, 2, [torch.Generator().manual_seed(s) for s in (1, 2)])
    assert (a == b.exclude("index")).all()  # extend writes the frames' indices beside them
    mine = episodes.clone()
    kept = make_window_buffer(mine, window=16)
    mine["observation"].zero_()  # the buffer holds its own copy of the frames
    assert kept.storage[0]["observation"].abs().sum() > 0


def test_windows_of_another_length_than_the_buffers_are_refused(episodes):
    """The sampler keeps windows inside an episode for its own length only: a longer window
    would run into the next episode."""
    buffer = make_window_buffer(episodes, window=16)
    with pytest.raises(ValueError, match="window: expected the buffer's window of 16 steps"):
        sample_windows(buffer, num_windows=4, window=20)
    with pytest.raises(ValueError, match="num_windows: expected a positive integer, got 0"):
        sample_windows(buffer, num_windows=0, window=16)


def test_a_members_windows_come_from_its_generator_alone(episodes):
    buffer = make_window_buffer(episodes, window=16)

    def draw(seeds):
        generators = [torch.Generator().manual_seed(s) for s in seeds]
        return sample_windows(buffer, 8, 16, len(seeds), generators)

    three, alone = draw([5, 6, 7]), draw([6])
    assert three.shape == (3, 8, 16) and alone.shape == (1, 8, 16)
    for key in ("observation", "action", ("next", "observation"), TRAJ_KEY):
        assert torch.equal(three[key][1], alone[key][0])


def test_a_bootstrap_resample_holds_whole_episodes_drawn_with_replacement(episodes):
    first, lengths = episode_spans(episodes)
    boot = resample_episodes(episodes, torch.Generator().manual_seed(3))
    b_first, b_lengths = episode_spans(boot)
    assert len(b_first) == len(first) == 6  # as many episodes, ids 0..5 in order
    assert torch.equal(torch.unique_consecutive(boot[TRAJ_KEY]), torch.arange(6))
    originals = [episodes["observation"][f : f + n] for f, n in zip(first, lengths)]
    drawn = []
    for f, n in zip(b_first.tolist(), b_lengths.tolist()):
        copy = boot[f : f + n]
        match = [i for i, o in enumerate(originals) if torch.equal(o, copy["observation"])]
        assert len(match) == 1  # a whole episode of the data, its frames in order
        assert torch.equal(copy["action"], episodes["action"][first[match[0]] :][:n])
        drawn.append(match[0])
    assert len(set(drawn)) < 6  # drawn with replacement: some twice, so some not at all
    again = resample_episodes(episodes, torch.Generator().manual_seed(3))
    assert torch.equal(again["observation"], boot["observation"])
    # about 1 - 1/e of the episodes are in a resample
    ids = torch.arange(3000).repeat_interleave(2)
    many = TensorDict({TRAJ_KEY: ids, "x": ids.float()}, batch_size=[6000])
    kept = torch.unique(resample_episodes(many, torch.Generator().manual_seed(0))["x"]).numel()
    assert 0.60 < kept / 3000 < 0.66


def test_each_member_draws_from_its_own_buffer(episodes):
    first, lengths = episode_spans(episodes)
    own = [episodes[f : f + n] for f, n in zip(first[:2], lengths[:2])]  # one episode each
    buffers = [make_window_buffer(e, window=16) for e in own]
    generators = [torch.Generator().manual_seed(s) for s in (1, 2)]
    windows = sample_windows(buffers, 8, 16, 2, generators, start_windows=2)
    for m in range(2):
        rows = windows["observation"][m].reshape(-1, windows["observation"].shape[-1])
        assert (rows[:, None, :] == own[m]["observation"]).all(-1).any(-1).all()
    generator = [torch.Generator().manual_seed(2)]
    alone = sample_windows(buffers[1:], 8, 16, 1, generator, start_windows=2)
    assert torch.equal(alone["observation"][0], windows["observation"][1])
    with pytest.raises(ValueError, match="buffer: expected one buffer, or one per member"):
        sample_windows(buffers, 8, 16, 2)


def test_episode_spans(episodes):
    first, lengths = episode_spans(episodes)
    assert torch.equal(first, torch.arange(6) * 40) and torch.equal(lengths, torch.full((6,), 40))


def test_windows_from_episode_starts(episodes):
    """The first ``start_windows`` windows of each member begin at an episode's first frame,
    drawn from the member's own generator; the others are the sampler's."""
    buffer = make_window_buffer(episodes, window=16)
    first = torch.cat(
        [torch.ones(1, dtype=torch.bool), episodes[TRAJ_KEY][1:] != episodes[TRAJ_KEY][:-1]]
    )
    firsts = episodes["observation"][first]

    def draw(seeds, starts):
        generators = [torch.Generator().manual_seed(s) for s in seeds]
        return sample_windows(buffer, 40, 16, len(seeds), generators, start_windows=starts)

    windows = draw([5, 6], 10)
    begins = windows["observation"][..., 0, :]  # [E, W, S]
    at_start = (begins[..., None, :] == firsts).all(-1).any(-1)
    assert at_start[:, :10].all()
    assert at_start[:, 10:].float().mean() < 0.3  # uniform positions: 1 in 25 here
    assert (windows[TRAJ_KEY] == windows[TRAJ_KEY][..., :1]).all()
    assert len(set(windows[TRAJ_KEY][:, :10, 0].flatten().tolist())) > 2
    assert torch.equal(draw([6], 10)["observation"][0], windows["observation"][1])
    assert torch.equal(draw([5, 6], 0)["observation"], draw([5, 6], 0)["observation"])
    with pytest.raises(ValueError, match=r"start_windows: expected 0\.\.num_windows=40, got 41"):
        draw([5], 41)
    with pytest.raises(ValueError, match="start_windows: expected generators"):
        sample_windows(buffer, 4, 16, start_windows=1)


def test_split_by_episode(episodes):
    train, val = split_episodes(episodes, 0.34, seed=0)
    assert train.shape[0] + val.shape[0] == episodes.shape[0]
    train_ids, val_ids = set(train[TRAJ_KEY].tolist()), set(val[TRAJ_KEY].tolist())
    assert not train_ids & val_ids and len(val_ids) == 2


def test_bad_inputs(episodes):
    with pytest.raises(ValueError, match="window: expected >= 2"):
        make_window_buffer(episodes, window=1)
    with pytest.raises(ValueError, match="window: expected at most the longest episode"):
        make_window_buffer(episodes, window=41)
    with pytest.raises(ValueError, match=r"val_fraction: expected a fraction in \(0, 1\)"):
        split_episodes(episodes, 1.0)
    with pytest.raises(ValueError, match="data: expected a flat TensorDict"):
        split_episodes(episodes.reshape(6, 40), 0.5)
    with pytest.raises(ValueError, match="noise_std"):
        GaussianExploration(ScriptedPusher(), -1.0)
    with pytest.raises(ValueError, match="num_episodes"):
        collect_episodes(make_pusher_env, None, 0)


def test_collections_get_unique_ids_and_duplicates_are_refused(episodes):
    from rcvae_torchrl.data import merge_episodes

    twice = torch.cat([episodes, episodes])  # ids 0..5 twice: stitched episodes
    with pytest.raises(ValueError, match=r"ids \[0, 1, 2, 3, 4\] tag several blocks of frames"):
        split_episodes(twice, 0.2)
    with pytest.raises(ValueError, match="merge_episodes"):
        make_window_buffer(twice, 8)
    # the same episodes twice: renumbered apart, and said to repeat (they would count twice)
    with pytest.warns(UserWarning, match=r"^datasets: 6 of the 12 merged episodes repeat another"):
        merged = merge_episodes(episodes, episodes)
    assert torch.equal(torch.unique(merged[TRAJ_KEY]), torch.arange(12))
    assert torch.equal(merged[TRAJ_KEY][: episodes.shape[0]], episodes[TRAJ_KEY])
    split_episodes(merged, 0.2)  # accepted
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # other episodes: nothing to say
        shifted = episodes.clone()
        shifted["observation"] = shifted["observation"] + 1.0
        shifted["next", "observation"] = shifted["next", "observation"] + 1.0
        assert len(merge_episodes(episodes, shifted)) == 2 * len(episodes)
    fewer = episodes.exclude("action")
    with pytest.raises(
        ValueError,
        match=r"datasets\[1\]: expected the entries of datasets\[0\], but it lacks "
        r"\['action'\]; keep the entries all share with data.select\(\*keys\)",
    ):
        merge_episodes(episodes, fewer)
    with pytest.raises(TypeError, match=r"datasets\[1\]: expected a TensorDict of episodes"):
        merge_episodes(episodes, [episodes])
    policy = make_policy_module(UniformRandomPolicy(2, hold=3, seed=0))
    make_env = functools.partial(make_pusher_env, "deterministic", time_limit=1.0)
    more = collect_episodes(make_env, policy, 2, first_id=6, progress=False)
    assert torch.unique(more[TRAJ_KEY]).tolist() == [6, 7]
    with pytest.raises(ValueError, match="first_id: expected an integer >= 0"):
        collect_episodes(make_env, policy, 1, first_id=-1, progress=False)


def test_exploration_respects_the_action_bounds():
    from rcvae_torchrl.data import action_bounds

    low, high = torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 0.5])
    uniform = UniformRandomPolicy(2, hold=1, seed=0, low=low, high=high)
    actions = torch.stack([uniform(torch.zeros(100, 3)) for _ in range(5)])
    assert (actions >= low).all() and (actions <= high).all()
    assert actions[..., 0].min() < -1.5 and actions[..., 0].max() > 1.5  # the whole range
    base = torch.nn.Linear(3, 2)
    noisy = GaussianExploration(base, 10.0, seed=0, low=low, high=high)(torch.randn(200, 3))
    assert (noisy >= low).all() and (noisy <= high).all()
    assert (noisy[:, 0] == 2.0).any() and (noisy[:, 1] == 0.0).any()  # clipped, not [-1, 1]
    far = torch.tensor([[5.0, -5.0]])
    clipped = GaussianExploration(lambda obs: far, 0.0, low=low, high=high)(torch.zeros(1, 3))
    assert clipped.tolist() == [[2.0, 0.0]]  # clipped without noise too
    wide = torch.tensor([-1.0, -1.0, -1.0])
    for kwargs, name in (({"low": wide}, "low"), ({"high": -wide}, "high")):
        exploration = GaussianExploration(base, 0.0, **kwargs)  # the action width is not known yet
        with pytest.raises(
            ValueError,
            match=rf"^{name}: expected a bound that broadcasts to the policy's actions \(4, 2\), "
            r"got shape \(3,\)",
        ):
            exploration(torch.randn(4, 3))
    bounds = action_bounds(make_pusher_env())
    assert torch.equal(bounds[0], -torch.ones(2)) and torch.equal(bounds[1], torch.ones(2))
    with pytest.raises(ValueError, match="low, high: expected finite bounds with low <= high"):
        UniformRandomPolicy(2, low=1.0, high=-1.0)
    for args, name in (((0,), "action_dim"), ((2, 0), "hold"), ((2.0,), "action_dim")):
        with pytest.raises(ValueError, match=rf"^{name}: expected a positive integer"):
            UniformRandomPolicy(*args)


def _pendulum():
    """TorchRL's pendulum: a torque in [-2, 2]; 5-step episodes."""
    from torchrl.envs import PendulumEnv, StepCounter, TransformedEnv

    from rcvae_torchrl.data import prepare_env

    return prepare_env(TransformedEnv(PendulumEnv(), StepCounter(5)), ["th", "thdot"])[0]


def test_exploration_narrower_than_the_env_is_warned():
    import warnings

    from rcvae_torchrl.data import action_bounds

    args = dict(num_episodes=1, frames_per_batch=5, progress=False)
    with pytest.warns(
        UserWarning,
        match=r"UniformRandomPolicy draws actions in \[-1, 1\], less "
        r"than the env's action range \[-2, 2\].*action_bounds\(env\)",
    ):
        narrow = collect_episodes(_pendulum, make_policy_module(UniformRandomPolicy(1)), **args)
    assert narrow["action"].abs().max() <= 1.0
    low, high = action_bounds(_pendulum())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the env's whole range: no warning
        whole = UniformRandomPolicy(1, low=low, high=high)
        collect_episodes(_pendulum, make_policy_module(whole), **args)
        base = make_policy_module(GaussianExploration(_Constant(0.0, dims=1), 1.0))
        with pytest.warns(UserWarning, match="GaussianExploration draws actions in"):
            collect_episodes(_pendulum, base, **args)
    # the agent's own episodes warn as the collection does, pointing at the caller's line
    from rcvae_torchrl.agent import run_episodes

    with pytest.warns(UserWarning, match="GaussianExploration draws actions in") as caught:
        run_episodes(_pendulum(), base, seeds=[0], max_steps=5, success=lambda o: o[:, 0] > 9)
    assert caught[0].filename == __file__


class _Constant(torch.nn.Module):
    def __init__(self, value: float, dtype: torch.dtype = torch.float32, dims: int = 2) -> None:
        super().__init__()
        self.value, self.dtype, self.dims = value, dtype, dims

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.full((*observation.shape[:-1], self.dims), self.value, dtype=self.dtype)


@pytest.mark.parametrize("num_envs", [1, 2])
def test_collection_refuses_actions_out_of_the_spec_and_too_few_frames(num_envs):
    make_env = functools.partial(make_pusher_env, "deterministic", time_limit=2.0)
    args = {"num_envs": num_envs, "frames_per_batch": 20, "progress": False}
    data = collect_episodes(make_env, make_policy_module(_Constant(-1.0)), 2, **args)
    assert data["action"].eq(-1.0).all()  # on the bound: kept as the env applied it
    with pytest.raises(
        ValueError,
        match=r"^policy: expected actions inside the env's action_spec: 80 of 80 actions fall "
        r"outside \[\[-1\.0, -1\.0\], \[1\.0, 1\.0\]\], by up to 0\.25",
    ):
        collect_episodes(make_env, make_policy_module(_Constant(1.25)), 2, **args)
    with pytest.raises(TypeError, match=r"expected actions of the env's action_spec dtype"):
        collect_episodes(make_env, make_policy_module(_Constant(0.0, torch.float64)), 1, **args)
    # the simulator fails inside its own step on another width: the policy is named
    wanted = (2,) if num_envs == 1 else (num_envs, 2)
    with pytest.raises(ValueError) as info:
        collect_episodes(make_env, make_policy_module(_Constant(0.0, dims=3)), 1, **args)
    assert str(info.value).startswith(f"policy: expected actions of shape {wanted}")
    assert f"got {(*wanted[:-1], 3)}; the env failed on them" in str(info.value)
    reads_position = TensorDictModule(_Constant(0.0), in_keys=["position"], out_keys=["action"])
    with pytest.raises(
        KeyError,
        match=r"policy: reads .+position.+, which \w+Env does not write .+"
        r"rcvae_torchrl.data.prepare_env\(env, observation_keys",
    ):
        collect_episodes(make_env, reads_position, 1, **args)
    writes_act = TensorDictModule(_Constant(0.0), in_keys=["observation"], out_keys=["act"])
    with pytest.raises(KeyError, match=r"policy: writes \['act'\], not the env's action 'action'"):
        collect_episodes(make_env, writes_act, 1, **args)
    with pytest.raises(
        TypeError,
        match=r"^make_env: expected a function that makes the env .*"
        r"got the env TransformedEnv",
    ):
        collect_episodes(make_env(), make_policy_module(_Constant(0.0)), 1, **args)
    for name, bad in (("num_episodes", 2.5), ("frames_per_batch", 0), ("max_frames", "10")):
        counts = {"num_episodes": 1, **args, name: bad}
        with pytest.raises(ValueError, match=rf"^{name}: expected a positive integer"):
            collect_episodes(make_env, make_policy_module(_Constant(0.0)), **counts)
    with pytest.raises(
        ValueError,
        match=r"^max_frames: 20 frames were collected and only 0 of the 1 episodes asked for ended",
    ):
        collect_episodes(make_env, make_policy_module(_Constant(0.0)), 1, max_frames=10, **args)


class _Integrator(EnvBase):
    """A 2-D point that always resets to 0 and moves by ``gain`` times its action, 5 steps an
    episode; its observation turns NaN at step ``nan_at`` (never: ``None``)."""

    gain, nan_at = 1.0, None

    def __init__(self):
        super().__init__()
        self.observation_spec = Composite(observation=Unbounded((2,)))
        self.action_spec = Bounded(-1.0, 1.0, (2,))
        self.reward_spec = Unbounded((1,))

    def _reset(self, tensordict):
        self.t, self.p = 0, torch.zeros(2)
        return TensorDict({"observation": self.p.clone()})

    def _step(self, tensordict):
        self.t += 1
        self.p = self.p + self.gain * tensordict["action"]
        if self.t == self.nan_at:
            self.p = torch.full((2,), float("nan"))
        done = torch.tensor([self.t >= 5])
        return TensorDict(
            {
                "observation": self.p.clone(),
                "reward": torch.zeros(1),
                "done": done,
                "terminated": done,
            }
        )

    def _set_seed(self, seed):
        pass


class _NanAtStep(_Integrator):
    """Its observation turns NaN at step 3 of every episode."""

    gain, nan_at = 0.1, 3


def test_an_env_that_gives_nan_observations_is_named_at_collection():
    policy = make_policy_module(UniformRandomPolicy(2, seed=0))
    with pytest.raises(
        ValueError,
        match=r"^env: _NanAtStep gave non-finite \('next', 'observation'\) \(NaN or inf\) in 6 of "
        r"10 frames, first in episode 0 at step 2; a world model cannot learn from them",
    ):
        collect_episodes(_NanAtStep, policy, 2, frames_per_batch=10, progress=False)


def test_collection_seeds_each_envs_action_noise():
    """A trial's pendulum, always reset hanging down with ``ActionNoise``: ``seed=0`` and
    ``seed=123`` gave the same episodes (the noise's own stream was never restarted), and two
    envs stepped together gave pairs of copies (each env's noise from one seed)."""
    from torchrl.envs import TransformedEnv

    from rcvae_torchrl.data import ActionNoise

    def make_env():
        return TransformedEnv(_Integrator(), ActionNoise(0.5))

    policy = make_policy_module(_Constant(0.0))  # all the motion is the noise

    def run(seed, envs=1):
        args = dict(seed=seed, num_envs=envs, frames_per_batch=10, progress=False)
        return collect_episodes(make_env, policy, 2, **args)["next", "observation"]

    a, b, c = run(0), run(0), run(123)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert not torch.equal(a[:5], a[5:])  # one env's episodes: the noise runs on
    two = run(0, envs=2)
    assert not torch.equal(two[:5], two[5:])  # the two envs' noise differs
    assert torch.equal(two, run(0, envs=2))


def test_frames_of_one_episode_in_several_blocks_are_told_to_be_sorted(episodes):
    """A TorchRL collector over 4 envs gives its batches' frames env by env: an episode that
    runs across two batches lies in two blocks. The message says so, and how to sort them; ids
    reused by several episodes keep the message about joining collections."""
    order = torch.arange(episodes.shape[0])
    cut = torch.cat([order[:20], order[40:60], order[20:40], order[60:]])  # two episodes cut
    with pytest.raises(ValueError, match=r"join up step by step once sorted by id") as caught:
        check_episode_ids(episodes[cut], "train_data")
    assert str(caught.value).startswith("train_data: expected one contiguous block")
    fixed = episodes[cut][torch.argsort(episodes[cut][TRAJ_KEY], stable=True)]
    check_episode_ids(fixed)
    reused = episodes.clone()
    reused[TRAJ_KEY] = reused[TRAJ_KEY] % 3  # episodes 0 and 3 share an id, apart in time
    with pytest.raises(ValueError, match=r"several episodes under one id \(join collections"):
        check_episode_ids(reused)
    # frames shuffled: the same message names the other cause, and how to sort them
    shuffled = episodes[
        torch.randperm(episodes.shape[0], generator=torch.Generator().manual_seed(0))
    ]
    with pytest.raises(ValueError, match=r"or frames out of time order \(shuffled, .*step_count"):
        check_episode_ids(shuffled)


def test_frames_drawn_from_a_replay_buffer_and_sorted_by_id_are_not_episodes(episodes):
    """A Reacher trial: frames drawn with a replay buffer's ``sample()`` and sorted by id pass
    as one block per id, but their frames do not follow each other in time; training on them
    was silent. The frames as collected (the buffer's ``rb[:]``) pass, and the buffer itself,
    given as the data, is named with the way to its frames."""
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    drawn = torch.randperm(episodes.shape[0], generator=torch.Generator().manual_seed(0))[:150]
    sampled = episodes[drawn]
    sampled = sampled[torch.argsort(sampled[TRAJ_KEY], stable=True)]
    with pytest.raises(
        ValueError,
        match=r"^data: expected each episode's frames in time order \(a frame's \('next', "
        r"'observation'\) is the 'observation' of the frame after it under the same id\), but "
        r"\d+ of \d+ such pairs do not join \(the first: frames \d+ and \d+, id \d\): frames "
        r"drawn from a replay buffer by sample\(\)",
    ):
        split_episodes(sampled, 0.2)
    rb = ReplayBuffer(storage=LazyTensorStorage(episodes.shape[0]))
    rb.extend(episodes)
    train, val = split_episodes(rb[:], 0.2)  # the stored frames, as collected
    assert train.shape[0] + val.shape[0] == episodes.shape[0]
    with pytest.raises(TypeError, match=r"^data: expected a flat TensorDict .* got ReplayBuffer;"):
        split_episodes(rb, 0.2)
    # a copy through float32 arithmetic still joins (within rounding)
    nudged = episodes.clone()
    nudged["next", "observation"] = nudged["next", "observation"] * (1 + 1e-7)
    check_episode_ids(nudged)
