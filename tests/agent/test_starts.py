"""Start states for any env, the real agent from them, and the forecast scored against it."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import DMControlEnv

from rcvae_torchrl.agent import (
    MODEL_FIELDS,
    draw_starts,
    observe_starts,
    physics_of,
    real_outcomes,
    reset_by_seed,
    reset_to_physics,
    run_episodes,
    score_forecast,
)
from rcvae_torchrl.data import ActionNoise, prepare_env


@pytest.fixture(scope="module")
def reacher():
    return prepare_env(DMControlEnv("reacher", "easy"))[0]


def test_seeded_and_physics_resets_give_the_drawn_start(reacher):
    starts = draw_starts(reacher, [5, 6, 7], physics=True)
    assert starts.batch_size == (3,) and starts["seed"].tolist() == [5, 6, 7]
    reacher.reset()  # somewhere else
    for i in range(3):
        assert torch.equal(
            reset_by_seed(reacher, starts[i])["observation"], starts["observation"][i]
        )
        td = reset_to_physics(reacher, starts[i])  # the target too: a model field
        assert torch.equal(td["observation"], starts["observation"][i])


def test_a_seed_past_numpy_s_range_resets_as_it_was_drawn(reacher):
    """draw_starts seeds the env with the seed mod 2**32 (numpy's range); the seeded reset
    replays that, whatever the seed (a study seed times 10,000, say)."""
    big = 10_000 * 1_000_000 + 5
    starts = draw_starts(reacher, [big])
    assert starts["seed"].tolist() == [big]
    assert torch.equal(draw_starts(reacher, [big % 2**32])["observation"], starts["observation"])
    reacher.reset()
    assert torch.equal(reset_by_seed(reacher, starts[0])["observation"], starts["observation"][0])


def test_a_start_s_model_holds_for_its_episode_only():
    env = prepare_env(DMControlEnv("reacher", "easy"))[0]  # its own: the model is changed
    physics = physics_of(env)
    own = physics.model.body_mass.copy()
    seeded = draw_starts(env, [3])
    heavy = draw_starts(env, [1], physics=True)[0].clone()
    heavy["physics", "model", "body_mass"] = heavy["physics", "model", "body_mass"] * 3
    for _ in range(2):  # twice in a row too: the env's own model is still the one put back
        reset_to_physics(env, heavy)
        assert (physics.model.body_mass == own * 3).all()
    env.reset()  # anyone's next reset: the env's own masses again
    assert (physics.model.body_mass == own).all()
    again = draw_starts(env, [3])
    assert torch.equal(again["observation"], seeded["observation"])


def test_physics_a_task_draws_per_episode_can_be_left_to_its_draw_and_its_patch_kept():
    """A domain-randomisation trial drew a cart-pole's pole mass in a patch of the task's
    ``initialize_episode``: the start's restored ``body_mass`` replaced every run's draw (each
    start kept its one mass), and the patch itself was deleted after the first reset."""
    env = prepare_env(DMControlEnv("cartpole", "balance"), ["position", "velocity"])[0]
    physics = physics_of(env)
    task = env.base_env._env.task
    pole = physics.model.name2id("pole_1", "body")
    drawn = []
    class_initialize = type(task).initialize_episode

    def randomised(physics_):  # the user's patch: a mass drawn per episode
        class_initialize(task, physics_)
        physics_.model.body_mass[pole] = float(task.random.uniform(0.5, 2.0))
        drawn.append(float(physics_.model.body_mass[pole]))

    task.initialize_episode = randomised
    start = draw_starts(env, [1], physics=True)[0]
    at_start = float(start["physics", "model", "body_mass"][pole])
    masses = []
    for _ in range(3):  # by default the start's mass, in every run
        reset_to_physics(env, start)
        masses.append(float(physics.model.body_mass[pole]))
    assert masses == [at_start] * 3
    kept = [f for f in MODEL_FIELDS if f != "body_mass"]
    fresh = []
    for _ in range(3):  # the task's own draw, without the mass among the fields restored
        td = reset_to_physics(env, start, model_fields=kept)
        fresh.append(float(physics.model.body_mass[pole]))
        assert torch.equal(td["observation"], start["observation"])  # the same state
    assert fresh == drawn[-3:] and len(set(fresh)) == 3
    before = len(drawn)
    env.reset()  # the patch is the user's: it is still there, and draws
    assert task.__dict__["initialize_episode"] is randomised and len(drawn) == before + 1
    with pytest.raises(ValueError, match=r"^model_fields: expected names among MODEL_FIELDS"):
        reset_to_physics(env, start, model_fields=("mass",))
    # runs that repeat one episode say why, where the mass was restored
    from rcvae_torchrl.competency import SuccessBoundary

    class Still(torch.nn.Module):
        def forward(self, observation):
            return torch.zeros(*observation.shape[:-1], 1)

    from tensordict.nn import TensorDictModule

    lasting = SuccessBoundary.survival(lambda o: o[..., 0].abs() > 10.0, time_limit=5)
    with pytest.warns(UserWarning, match=r"copies of one outcome.*leave those fields out"):
        real_outcomes(
            env,
            TensorDictModule(Still(), in_keys=["observation"], out_keys=["action"]),
            start[None],
            runs_per_start=2,
            reset_to_state=reset_to_physics,
            max_steps=5,
            success=lasting.success_over_time,
            progress=False,
        )


def test_physics_resets_reach_states_no_reset_draws(reacher):
    start = draw_starts(reacher, [1], physics=True)[0].clone()
    start["physics", "qvel"] = torch.tensor([3.0, -2.0], dtype=torch.float64)
    td = reset_to_physics(reacher, start)
    torch.testing.assert_close(td["observation"][4:], torch.tensor([3.0, -2.0]))


def test_starts_edited_by_hand_get_their_observation(reacher):
    """A state no reset draws needs the observation that goes with it: with the drawn one,
    the real episodes' reset is refused; observed, the episodes run from it."""
    starts = draw_starts(reacher, [1, 2], physics=True)
    starts["physics", "qvel"] = torch.tensor([[3.0, -2.0], [0.5, 4.0]], dtype=torch.float64)
    policy = _still_policy()
    args = dict(
        runs_per_start=1,
        reset_to_state=reset_to_physics,
        max_steps=3,
        success=lambda observation: observation[..., 0] > 100.0,
        progress=False,
    )
    with pytest.raises(ValueError, match=r"start's .*agent.observe_starts gives it"):
        real_outcomes(reacher, policy, starts, **args)
    observed = observe_starts(reacher, starts)
    torch.testing.assert_close(observed["observation"][:, 4:], starts["physics", "qvel"].float())
    assert torch.equal(observed["observation"][:, :4], starts["observation"][:, :4])
    assert torch.equal(observed["physics", "qvel"], starts["physics", "qvel"])
    assert real_outcomes(reacher, policy, observed, **args).steps.tolist() == [[3], [3]]
    with pytest.raises(TypeError, match=r"starts: expected a TensorDict \[B\] of start states"):
        observe_starts(reacher, starts[0])

    def by_observation(env, start):  # a reset of one's own, from the start's observation
        return env.reset().set("observation", start["observation"])

    with pytest.raises(
        KeyError, match=r"reset_to_state: it reads the start's 'observation', which observe_st"
    ):
        observe_starts(reacher, starts, reset_to_state=by_observation)


def _still_policy():
    """A reacher agent that does not move."""
    from tensordict.nn import TensorDictModule

    return TensorDictModule(
        lambda obs: torch.zeros((*obs.shape[:-1], 2)), ["observation"], ["action"]
    )


def test_a_reset_that_is_not_a_function_of_the_seed_is_detected(reacher):
    start = draw_starts(reacher, [1])[0].clone()
    start["observation"] = start["observation"] + 1.0
    with pytest.raises(ValueError, match="not a function of its seed"):
        reset_by_seed(reacher, start)
    short = draw_starts(reacher, [1])[0].clone()
    short["observation"] = short["observation"][:4]  # another env's starts, say
    size = reacher.observation_spec["observation"].shape[-1]
    with pytest.raises(
        ValueError, match=rf"expected the env's observation shape \[{size}\], got \[4\]"
    ):
        reset_by_seed(reacher, short)
    with pytest.raises(TypeError, match="expected a TorchRL env over a dm_control environment"):
        reset_to_physics(object(), start)
    from torchrl.envs import PendulumEnv, StepCounter, TransformedEnv

    with pytest.raises(TypeError, match=r"got a TransformedEnv over a PendulumEnv; for another"):
        reset_to_physics(TransformedEnv(PendulumEnv(), StepCounter(5)), start)


def test_real_outcomes_repeat_runs_with_their_own_noise():
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    env.append_transform(ActionNoise(1.0))
    starts = draw_starts(env, [0, 1])

    def push(td):
        return td.set("action", -5 * td["observation"][..., :2].clamp(-0.2, 0.2))

    def near(observation):
        return observation[..., :2].norm(dim=-1) < 0.2

    out = real_outcomes(
        env,
        push,
        starts,
        runs_per_start=3,
        reset_to_state=reset_by_seed,
        max_steps=20,
        success=near,
        trace=lambda o: o[..., :2].norm(dim=-1),
        seed=1,
        progress=False,
    )
    assert out.success.shape == out.first_step.shape == (2, 3)
    assert out.trace.shape == (2, 3, 20) and not out.trace.isnan().any()
    hit = out.trace < 0.2
    first = torch.where(hit.any(-1), hit.float().argmax(-1), torch.tensor(20))
    assert torch.equal(out.first_step, first) and torch.equal(out.success, hit.any(-1))
    assert not torch.equal(out.trace[:, 0], out.trace[:, 1])  # runs differ in their noise
    again = real_outcomes(
        env,
        push,
        starts,
        runs_per_start=3,
        reset_to_state=reset_by_seed,
        max_steps=20,
        success=near,
        trace=lambda o: o[..., :2].norm(dim=-1),
        seed=1,
        progress=False,
    )
    assert torch.equal(again.trace, out.trace)  # the same seeds, the same episodes
    scores = score_forecast(torch.tensor([0.5, 0.5]), out)
    assert scores["episodes"] == 6 and 0 <= scores["brier"] <= 1
    with pytest.raises(ValueError, match="runs_per_start: expected a positive integer"):
        real_outcomes(
            env, push, starts, runs_per_start=0, reset_to_state=reset_by_seed, max_steps=5
        )


def test_run_episodes_needs_a_reset_for_given_starts():
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    with pytest.raises(ValueError, match="reset_to_state: expected a function"):
        run_episodes(env, lambda td: td, seeds=[0], starts=torch.zeros(1, 4), max_steps=2)
    with pytest.raises(ValueError, match="starts: expected one start state per seed"):
        run_episodes(
            env,
            lambda td: td,
            seeds=[0, 1],
            starts=TensorDict({}, [1]),
            reset_to_state=reset_by_seed,
            max_steps=2,
        )


def test_bad_starts_seeds_and_success_flags_are_named(reacher):
    start = draw_starts(reacher, [1], physics=True)[0].clone()
    start["physics", "qpos"][0] = float("nan")
    with pytest.raises(ValueError, match=r"start\['physics', 'qpos'\]: expected 2 finite values"):
        reset_to_physics(reacher, start)
    with pytest.raises(ValueError, match=r"start: expected one start of draw_starts\(env, seeds"):
        reset_to_physics(reacher, draw_starts(reacher, [1])[0])
    with pytest.raises(
        ValueError,
        match=r"got a tensordict of batch \(2,\) .*; this reset serves one env \(batch_size "
        r"\[\]\): for a batched env, pass a reset_to_state of your own",
    ):
        reset_by_seed(reacher, draw_starts(reacher, [1, 2]))  # all starts, not one
    with pytest.raises(ValueError, match="with a 'seed' entry"):
        reset_by_seed(reacher, TensorDict({"observation": torch.zeros(6)}, []))
    with pytest.raises(ValueError, match=r"seeds: expected integer seeds, got 1\.7"):
        draw_starts(reacher, [1.7])
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    starts = draw_starts(env, [0])
    args = {"reset_to_state": reset_by_seed, "max_steps": 3, "runs_per_start": 1}
    with pytest.raises(ValueError, match=r"seed: expected an integer >= 0, got 0\.5"):
        real_outcomes(env, lambda td: td.set("action", torch.zeros(2)), starts, seed=0.5, **args)
    with pytest.raises(ValueError, match="starts: expected at least one start state, got none"):
        real_outcomes(env, lambda td: td.set("action", torch.zeros(2)), starts[:0], **args)
    with pytest.raises(ValueError, match="seeds: expected at least one seed"):
        run_episodes(env, lambda td: td, seeds=[], max_steps=3)
    with pytest.raises(
        KeyError, match=r"success: the env writes no 'success' flag .*a function of"
    ):
        real_outcomes(env, lambda td: td.set("action", torch.zeros(2)), starts, **args)
    with pytest.raises(ValueError, match="max_steps: expected a positive integer, got 0"):
        real_outcomes(env, lambda td: td, starts, **{**args, "max_steps": 0})
    act = lambda td: td.set("action", torch.zeros(2))  # noqa: E731
    for success, error, match in (
        (lambda obs: obs[..., :2] > 0, ValueError, r"success: expected one flag per step of the"),
        (lambda obs: obs[..., 0].float(), TypeError, "success: expected a bool tensor"),
    ):
        with pytest.raises(error, match=match):
            run_episodes(env, act, seeds=[0], max_steps=3, success=success)


def test_run_episodes_refuses_actions_the_env_would_not_apply_as_recorded():
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    never = lambda obs: obs[..., 0] > 100  # noqa: E731  (point_mass has no success flag)
    args = {"seeds": [0], "max_steps": 3, "success": never}
    run_episodes(env, lambda td: td.set("action", torch.ones(2)), **args)  # on the bound: fine
    with pytest.raises(
        ValueError,
        match=r"^policy: expected actions inside the env's action_spec: 3 of 3 actions fall "
        r"outside \[\[-1\.0, -1\.0\], \[1\.0, 1\.0\]\], by up to 0\.5; clip them",
    ):
        run_episodes(env, lambda td: td.set("action", torch.tensor([0.0, 1.5])), **args)
    from rcvae_torchrl.data import check_actions

    nan = TensorDict(action=torch.tensor([[0.0, float("nan")], [0.0, 0.0]]), batch_size=[2])
    with pytest.raises(
        ValueError,
        match=r"policy: expected actions inside the env.s action_spec: 1 of 2 actions are NaN",
    ):
        check_actions(env, nan)  # (the env itself refuses to step with a NaN action)
    with pytest.raises(
        TypeError, match=r"^policy: expected actions of the env's action_spec dtype torch.float32"
    ):
        run_episodes(env, lambda td: td.set("action", torch.zeros(2, dtype=torch.float64)), **args)
