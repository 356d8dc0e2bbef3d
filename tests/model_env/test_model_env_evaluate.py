"""evaluate_action_sequences: shapes, particle layout, equality with env.rollout, success, NaN."""

from __future__ import annotations

import pytest
import torch
from model_env_utils import E, Replay, at_target
from tensordict import TensorDict

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.model_env import make_rcvae_env
from rcvae_torchrl.rollout import alive_mask


def _start(starts, batch=(2,)):
    n = torch.Size(batch).numel()
    return TensorDict({"observation": starts[:n].reshape(*batch, 14)}, batch_size=batch)


@pytest.mark.parametrize(
    ("mode", "particles", "expected"),
    [
        ("ts_inf", 1, 1),  # one particle per candidate, candidates split over members
        ("ts_inf", 4, 2 * E),
        ("ts_inf", 2 * E, 2 * E),
        ("ts1", 4, 4),
        ("mean", 4, 4),
    ],
)
@pytest.mark.parametrize("batch", [(), (2,), (2, 3)])
def test_shapes_and_particle_rounding(make_env, starts, mode, particles, expected, batch):
    env = make_env(trajectory_sampling=mode)
    actions = torch.rand(*batch, 7, 4, 2) * 2 - 1
    returns, success = env.evaluate_action_sequences(
        _start(starts, batch), actions, particles, return_success=True
    )
    assert returns.shape == (*batch, 7, expected) == success.shape
    assert success.dtype == torch.bool and torch.isfinite(returns).all()
    assert env.evaluate_action_sequences(_start(starts, batch), actions, particles).shape == (
        *batch,
        7,
        expected,
    )


@pytest.mark.parametrize("mode", ["ts_inf", "ts1", "mean"])
@pytest.mark.parametrize("terminate", [False, True])
def test_fast_path_equals_env_rollout_under_the_same_seed(
    ensemble, real_env, starts, mode, terminate
):
    """Particle p of row r (start × candidate) is the rollout of the tensordict [G, R] at (p, r);
    TS-∞ particle p follows member p // ⌈P/E⌉. Success: ball past x = 0.3 (some particles)."""
    env = make_rcvae_env(
        ensemble,
        real_env,
        pusher_reward,
        lambda observation: observation[..., 8] > 0.3,
        trajectory_sampling=mode,
        terminate_on_success=terminate,
        seed=0,
    )
    c, h, p = 4, 6, 4
    groups = {"ts_inf": 2 * E, "ts1": p, "mean": 1}[mode]
    actions = torch.rand(1, c, h, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    td_start = _start(starts, (1,))
    env.set_seed(3)
    returns, success = env.evaluate_action_sequences(td_start, actions, p, return_success=True)

    state = {"observation": td_start["observation"].expand(groups, c, 14)}
    if mode == "ts_inf":
        k = groups // E
        state["member"] = (torch.arange(groups) // k)[:, None].expand(groups, c)
    env.set_seed(3)
    td = env.reset(TensorDict(state, batch_size=[groups, c]))
    rollout = env.rollout(
        h,
        Replay(actions[0].expand(groups, c, h, 2)),
        tensordict=td,
        auto_reset=False,
        break_when_any_done=False,
    )
    done = rollout["next", "done"].squeeze(-1)
    alive = alive_mask(done)
    expected = (rollout["next", "reward"].squeeze(-1) * alive).sum(-1).T  # [c, groups]
    reached = (rollout["next", "success"].squeeze(-1) & alive).any(-1).T
    if mode == "mean":
        expected, reached = expected.expand(c, p), reached.expand(c, p)
    torch.testing.assert_close(returns[0], expected)
    assert torch.equal(success[0], reached)
    assert bool(success.any())  # the test exercises the success bookkeeping
    if mode != "mean":
        assert not bool(success.all())


def test_task_functions_score_the_whole_horizon_in_one_call(ensemble, real_env, starts):
    """Eager scoring calls the reward and the success function once per scoring call, on every
    step's states ``[H, n, S]`` (and actions ``[H, n, A]``), not once per step."""
    shapes: dict[str, list[tuple[int, ...]]] = {"reward": [], "success": []}

    def reward(observation, action):
        shapes["reward"].append((*observation.shape, *action.shape[-1:]))
        return pusher_reward(observation=observation, action=action)

    def success(observation):
        shapes["success"].append(tuple(observation.shape))
        return pusher_success(observation)

    env = make_rcvae_env(ensemble, real_env, reward, success, terminate_on_success=True, seed=0)
    # made, the env called each once on a batch of two states (a check of their shapes)
    assert shapes == {"reward": [(2, 14, 2)], "success": [(2, 14)]}
    shapes["reward"].clear()
    shapes["success"].clear()
    c, h, p = 3, 5, 2 * E
    actions = torch.rand(1, c, h, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    env.evaluate_action_sequences(_start(starts, (1,)), actions, p)
    assert shapes == {"reward": [(h, p * c, 14, 2)], "success": [(h, p * c, 14)]}


def test_success_detected_and_later_rewards_dropped(still_ball_env, starts):
    env = still_ball_env()
    obs = torch.stack([at_target(starts[0]), starts[1]])
    assert not pusher_success(starts[1])
    td_start = TensorDict({"observation": obs}, batch_size=[2])
    actions = torch.rand(2, 5, 4, 2) * 2 - 1
    env.set_seed(0)
    returns, success = env.evaluate_action_sequences(td_start, actions, E, return_success=True)
    assert success[0].all() and not success[1].any()
    env.set_seed(0)
    first = env.evaluate_action_sequences(td_start, actions[:, :, :1], E)
    torch.testing.assert_close(returns[0], first[0])  # only the success step's reward counts
    full = still_ball_env(terminate_on_success=False)
    full_returns, full_success = full.evaluate_action_sequences(
        td_start, actions, E, return_success=True
    )
    assert torch.equal(full_success, success)
    assert (full_returns[0] < returns[0]).all()  # every reward is < 0, four more of them


def test_non_finite_start_gives_nan_returns_for_that_start_only(make_env, starts):
    env = make_env()
    obs = starts[:3].clone()
    obs[1, 4] = float("nan")
    obs[2, 0] = float("inf")
    td_start = TensorDict({"observation": obs}, batch_size=[3])
    returns, success = env.evaluate_action_sequences(
        td_start, torch.zeros(3, 5, 4, 2), 3, return_success=True
    )
    assert torch.isfinite(returns[0]).all()
    assert torch.isnan(returns[1:]).all()
    assert not success[1:].any()


@pytest.mark.parametrize(
    ("actions", "particles", "match"),
    [
        (torch.zeros(2, 5, 4, 3), 2, "actions: expected shape"),
        (torch.zeros(5, 4, 2), 2, "actions: expected shape"),
        (torch.zeros(3, 5, 4, 2), 2, "actions: expected shape"),
        (torch.zeros(2, 5, 0, 2), 2, "horizon H >= 1"),
        (torch.zeros(2, 0, 4, 2), 2, "C >= 1"),
        (torch.full((2, 5, 4, 2), float("nan")), 2, "actions: expected finite"),
        (torch.zeros(2, 5, 4, 2), 0, "particles"),
        (torch.zeros(2, 5, 4, 2), 2.0, "particles"),
        (torch.zeros(2, 5, 4, 2), True, "particles"),
    ],
)
def test_bad_input_is_a_clear_error(make_env, starts, actions, particles, match):
    with pytest.raises(ValueError, match=match):
        make_env().evaluate_action_sequences(_start(starts), actions, particles)


def test_bad_start_is_a_clear_error(make_env, starts):
    env = make_env()
    with pytest.raises(KeyError, match="observation"):
        env.evaluate_action_sequences(TensorDict(batch_size=[2]), torch.zeros(2, 5, 4, 2), 1)
    with pytest.raises(TypeError, match="dtype"):
        env.evaluate_action_sequences(
            TensorDict({"observation": starts[:2].double()}, [2]), torch.zeros(2, 5, 4, 2), 1
        )
    with pytest.raises(TypeError, match="dtype"):
        env.evaluate_action_sequences(_start(starts), torch.zeros(2, 5, 4, 2).double(), 1)


@pytest.mark.slow  # compiles the model step (tens of seconds on a CPU)
@pytest.mark.parametrize("particles", [1, 2 * E])
def test_compiled_scoring_matches_eager_under_the_same_seed(ensemble, real_env, starts, particles):
    """compile_scoring draws the same noise in the same order as the eager step, so the returns
    agree up to the float rounding of the fused kernels, and successes (ball past x = 0.0,
    reached by some particles) exactly unless a state lies at the threshold."""
    kwargs = {"trajectory_sampling": "ts_inf", "seed": 0}
    success = lambda observation: observation[..., 8] > 0.0  # noqa: E731
    eager = make_rcvae_env(ensemble, real_env, pusher_reward, success, **kwargs)
    compiled = make_rcvae_env(
        ensemble, real_env, pusher_reward, success, compile_scoring=True, **kwargs
    )
    actions = torch.rand(2, 9, 6, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    td_start = _start(starts, (2,))
    for env in (eager, compiled):
        env.set_seed(3)
    want = eager.evaluate_action_sequences(td_start, actions, particles, return_success=True)
    got = compiled.evaluate_action_sequences(td_start, actions, particles, return_success=True)
    torch.testing.assert_close(got[0], want[0], rtol=1e-4, atol=1e-5)
    assert torch.equal(got[1], want[1])
    # the generator advanced by the same draws
    assert torch.equal(eager.generator.get_state(), compiled.generator.get_state())


@pytest.mark.slow  # compiles the model step (tens of seconds on a CPU)
def test_compiled_scoring_compiles_once_for_every_number_of_candidates(ensemble, real_env, starts):
    """The particle count is a dynamic size: after the first compile, new numbers of
    candidates and particles reuse the same graph, and each still matches the eager rollout."""
    from torch._dynamo.utils import counters

    kwargs = {"trajectory_sampling": "ts_inf", "seed": 0}
    eager = make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, **kwargs)
    compiled = make_rcvae_env(
        ensemble, real_env, pusher_reward, pusher_success, compile_scoring=True, **kwargs
    )
    graphs = []
    for candidates, particles in ((6, 2 * E), (11, 2 * E), (17, 3 * E)):
        actions = torch.rand(2, candidates, 6, 2, generator=torch.Generator().manual_seed(1))
        for env in (eager, compiled):
            env.set_seed(3)
        args = (_start(starts, (2,)), actions * 2 - 1, particles)
        want = eager.evaluate_action_sequences(*args)
        got = compiled.evaluate_action_sequences(*args)
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
        graphs.append(int(counters["stats"]["unique_graphs"]))
    assert graphs[1] == graphs[2] == graphs[0], f"graphs compiled after each shape: {graphs}"


def test_compiled_scoring_equals_the_eager_reference(ensemble, real_env, starts):
    """The default suite's check of the compiled (inductor-fused) scoring against the eager
    rollout: a 2-step horizon keeps the compile short (about 20 s on a CPU with a cold cache);
    two numbers of candidates, one graph."""
    from torch._dynamo.utils import counters

    kwargs = {"trajectory_sampling": "ts_inf", "seed": 0}
    eager = make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, **kwargs)
    compiled = make_rcvae_env(
        ensemble, real_env, pusher_reward, pusher_success, compile_scoring=True, **kwargs
    )
    graphs = []
    for candidates in (4, 7):
        actions = torch.rand(2, candidates, 2, 2, generator=torch.Generator().manual_seed(1))
        for env in (eager, compiled):
            env.set_seed(3)
        args = (_start(starts, (2,)), actions * 2 - 1, 2 * E)
        want = eager.evaluate_action_sequences(*args, return_success=True)
        got = compiled.evaluate_action_sequences(*args, return_success=True)
        torch.testing.assert_close(got[0], want[0], rtol=1e-4, atol=1e-5)
        assert torch.equal(got[1], want[1])
        graphs.append(int(counters["stats"]["unique_graphs"]))
    assert graphs[0] == graphs[1], f"graphs compiled after each shape: {graphs}"


def test_aot_scoring_equals_the_eager_reference(ensemble, real_env, starts):
    """``compile_scoring="aot"``: the package compiled ahead of time (built once per session's
    cache for this architecture, task and 2-step horizon, shared with tests/rollout/test_aot.py)
    against the eager rollout, for several numbers of candidates and particles."""
    kwargs = {"trajectory_sampling": "ts_inf", "seed": 0}
    eager = make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, **kwargs)
    aot = make_rcvae_env(
        ensemble, real_env, pusher_reward, pusher_success, compile_scoring="aot", **kwargs
    )
    for candidates, particles in ((4, 2 * E), (7, 2 * E), (5, 1)):
        actions = torch.rand(2, candidates, 2, 2, generator=torch.Generator().manual_seed(1))
        for env in (eager, aot):
            env.set_seed(3)
        args = (_start(starts, (2,)), actions * 2 - 1, particles)
        want = eager.evaluate_action_sequences(*args, return_success=True)
        got = aot.evaluate_action_sequences(*args, return_success=True)
        torch.testing.assert_close(got[0], want[0], rtol=1e-4, atol=1e-5)
        assert torch.equal(got[1], want[1])
        assert torch.equal(eager.generator.get_state(), aot.generator.get_state())


def test_compiled_scoring_is_called_with_the_garbage_collector_paused(
    ensemble, real_env, starts, monkeypatch, compiled_calls_paused
):
    """A finalizer that changes torch's thread count during a trace fails it: the compiled
    scoring runs with the collector paused (``threads.collection_paused``). ``torch.compile``
    is replaced by a recorder here (the compile itself is tested above)."""
    import gc

    from rcvae_torchrl.rollout import scoring

    monkeypatch.setattr(scoring, "_COMPILED", [])
    kwargs = {"trajectory_sampling": "ts_inf", "seed": 0}
    eager = make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, **kwargs)
    compiled = make_rcvae_env(
        ensemble, real_env, pusher_reward, pusher_success, compile_scoring=True, **kwargs
    )
    actions = torch.rand(2, 4, 2, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    for env in (eager, compiled):
        env.set_seed(3)
    args = (_start(starts, (2,)), actions, 2 * E)
    torch.testing.assert_close(
        compiled.evaluate_action_sequences(*args), eager.evaluate_action_sequences(*args)
    )
    assert compiled_calls_paused == [True] and gc.isenabled()
