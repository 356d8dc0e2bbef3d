"""Clear errors for bad arguments and bad inputs."""

from __future__ import annotations

import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Transform

from rcvae_torchrl.envs import make_pusher_env, pusher_reward, pusher_success
from rcvae_torchrl.model_env import RCVAEEnsembleEnv


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"trajectory_sampling": "ts2"}, ValueError, "trajectory_sampling"),
        ({"member_assignment": "first"}, ValueError, "member_assignment"),
        ({"seed": 0, "generator": torch.Generator()}, ValueError, "seed"),
        ({"start_states": torch.zeros(5, 13)}, ValueError, "start_states"),
        ({"start_states": torch.zeros(2, 3, 14)}, ValueError, "start_states"),
        ({"start_states": torch.zeros(0, 14)}, ValueError, "start_states"),
        ({"start_states": torch.full((2, 14), float("nan"))}, ValueError, "start_states"),
        ({"start_states": torch.zeros(2, 14, dtype=torch.float64)}, TypeError, "start_states"),
        ({"compile_scoring": "fast"}, ValueError, "compile_scoring: expected False .* 'aot'"),
        ({"compile_scoring": 1}, ValueError, "compile_scoring: expected False .* 'aot'"),
        ({"validate": "no"}, TypeError, "validate: expected True or False, got 'no'"),
        ({"terminate_on_success": 1}, TypeError, "terminate_on_success: expected True or False"),
        ({"requires_grad": "yes"}, TypeError, "requires_grad: expected True or False"),
    ],
)
def test_constructor_arguments(ensemble, kwargs, error, match):
    with pytest.raises(error, match=match):
        RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, **kwargs)


def test_constructor_types(ensemble):
    with pytest.raises(TypeError, match="ensemble"):
        RCVAEEnsembleEnv(torch.nn.Linear(2, 2), pusher_reward, pusher_success)
    with pytest.raises(TypeError, match="reward_fn"):
        RCVAEEnsembleEnv(ensemble, None, pusher_success)
    with pytest.raises(TypeError, match="success_fn"):
        RCVAEEnsembleEnv(ensemble, pusher_reward, 0.5)


def _state(env, starts, n=4):
    td = env.reset(TensorDict({"observation": starts[:n]}, batch_size=[n]))
    td["action"] = torch.zeros(n, 2)
    return td


@pytest.mark.parametrize("mode", ["ts_inf", "ts1", "mean"])
def test_step_inputs(make_env, starts, mode):
    env = make_env(trajectory_sampling=mode)
    td = _state(env, starts)
    td["action"] = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="action: expected shape"):
        env.step(td)
    td["action"] = torch.full((4, 2), float("nan"))
    with pytest.raises(ValueError, match="action: expected finite"):
        env.step(td)
    for dtype in (torch.int64, torch.bool):  # refused before the clamp turns them into floats
        td = _state(env, starts)
        td["action"] = torch.ones(4, 2, dtype=dtype)
        with pytest.raises(
            TypeError,
            match=rf"action: expected dtype torch.float32 .*, got {dtype}; integer or bool "
            r"actions are discrete ones .* relax them to a continuous action",
        ):
            env.step(td)
    td = _state(env, starts)
    td["observation"][1, 2] = float("nan")
    with pytest.raises(ValueError, match="observation: expected finite"):
        env.step(td)
    td = _state(env, starts).exclude("rcvae", "member")
    td["observation"][1, 2] = float("nan")
    with pytest.raises(ValueError, match="observation: expected finite"):
        env.step(td)  # no model state: started from the observation, which is checked too
    with pytest.raises(KeyError, match="observation"):
        env.step(TensorDict({"action": torch.zeros(4, 2)}, batch_size=[4]))


def test_step_without_model_state_starts_it(make_env, starts):
    env = make_env()
    td = TensorDict({"observation": starts[:5], "action": torch.zeros(5, 2)}, batch_size=[5])
    out = env.step(td)
    assert out["next", "member"].tolist() == [0, 1, 2, 0, 1]
    assert out["next", "rcvae", "hidden"].shape == (5, 16)


def test_reset_inputs(make_env, starts):
    env = make_env()
    bad = starts[:2].clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="finite"):
        env.reset(TensorDict({"observation": bad}, batch_size=[2]))
    with pytest.raises(ValueError, match="expected shape"):
        env.reset(TensorDict({"observation": torch.zeros(2, 9)}, batch_size=[2]))
    with pytest.raises(TypeError, match="dtype"):
        env.reset(TensorDict({"observation": starts[:2].double()}, batch_size=[2]))
    with pytest.raises(ValueError, match="member"):
        env.reset(
            TensorDict({"observation": starts[:2], "member": torch.tensor([0, 7])}, batch_size=[2])
        )
    with pytest.raises(
        ValueError,
        match=r"tensordict\['observation'\]: expected shape \[\*B, S=14\] with \[\*B\] the "
        r"tensordict's batch_size \[\], got \(3, 14\); build it with TensorDict\(\{\.\.\.\}, "
        r"batch_size=\[3\]\)",
    ):
        env.reset(TensorDict({"observation": starts[:3]}))  # no batch_size: tensordict's []


def test_task_functions_with_wrong_outputs(ensemble, starts):
    """Refused when the env is made (they are called once on a batch of two states), and at a
    step where they only go wrong on real states."""
    with pytest.raises(ValueError, match="reward_fn: expected a reward of shape"):
        RCVAEEnsembleEnv(ensemble, lambda observation, action: observation, pusher_success)
    with pytest.raises(ValueError, match="success_fn: expected a flag"):
        RCVAEEnsembleEnv(ensemble, pusher_reward, lambda observation: observation[..., :2] > 0)
    with pytest.raises(TypeError, match="reward_fn: expected a tensor"):
        RCVAEEnsembleEnv(ensemble, lambda observation, action: 0.0, pusher_success)

    def later(observation, action):  # wrong only away from the zero states
        return observation if bool((observation != 0).any()) else observation[..., :1]

    td = TensorDict({"observation": starts[:3], "action": torch.zeros(3, 2)}, batch_size=[3])
    env = RCVAEEnsembleEnv(ensemble, later, pusher_success)
    with pytest.raises(ValueError, match="reward_fn: expected a reward of shape"):
        env.step(td)


def test_real_env_must_be_an_env(ensemble):
    with pytest.raises(TypeError, match="real_env: expected a TorchRL EnvBase or None, got str"):
        RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, real_env="pusher")


@pytest.mark.parametrize("mode", ["ts_inf", "ts1", "mean"])
def test_step_refuses_infinite_actions_nan_hidden_states_and_nan_rewards(make_env, starts, mode):
    env = make_env(trajectory_sampling=mode)
    td = _state(env, starts)
    td["action"][2, 1] = float("inf")  # the clamp to the bounds would make it finite
    with pytest.raises(ValueError, match=r"action: expected finite values, got 0 NaN and 1 inf"):
        env.step(td)
    td = _state(env, starts)
    td["rcvae", "hidden"][0, ..., 3] = float("nan")
    with pytest.raises(ValueError, match=r"hidden.*: expected finite values, got \d+ NaN"):
        env.step(td)
    td = _state(env, starts)
    env.step(td)  # the same inputs, finite, step
    nan_reward = make_env(trajectory_sampling=mode)
    nan_reward.task = type(nan_reward.task)(
        lambda observation, action: torch.full((*observation.shape[:-1], 1), float("nan")),
        pusher_success,
        True,
    )
    with pytest.raises(ValueError, match=r"^reward_fn's reward: expected finite values, got 4 NaN"):
        nan_reward.step(_state(nan_reward, starts))
    unchecked = make_env(trajectory_sampling=mode, validate=False)  # the documented opt-out
    td = _state(unchecked, starts)
    td["action"][2, 1] = float("inf")
    assert torch.isfinite(unchecked.step(td)["next", "observation"]).all()


def test_action_specs_with_crossed_bounds_are_refused(ensemble, starts):
    from torchrl.data import Bounded

    from rcvae_torchrl.planners import CEMPlanner

    crossed = Bounded(low=torch.tensor([-1.0, 1.0]), high=torch.tensor([1.0, -1.0]), shape=(2,))
    planner_env = RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, start_states=starts)
    planner_env.action_spec = crossed
    with pytest.raises(
        ValueError,
        match=r"^action_spec \(its low and high\): expected low <= high \(and no NaN\), got "
        r"\[-1\.0, 1\.0\] and \[1\.0, -1\.0\]",
    ):
        CEMPlanner(planner_env, 2, num_candidates=4, top_k=2, iterations=1)
    real = make_pusher_env(seed=0)
    real.action_spec = crossed
    with pytest.raises(
        ValueError, match=r"^action_spec \(its low and high\): expected low <= high"
    ):
        RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, real_env=real)


def test_a_transform_that_writes_the_observation_is_refused(ensemble, real_env, starts):
    """The model env reads its next state from "observation": an ObservationNorm on it fed
    the normalised state back into the model (x read 0.999, 9.99, 99.8 ... for 0.0999,
    0.0998, 0.0997 ... untransformed)."""
    from torchrl.envs import CatFrames, ObservationNorm, StepCounter

    from rcvae_torchrl.envs import pusher_reward, pusher_success
    from rcvae_torchrl.model_env import make_rcvae_env

    args = (ensemble, real_env, pusher_reward, pusher_success)
    for transform in (
        ObservationNorm(loc=0.0, scale=10.0, in_keys=["observation"]),
        [StepCounter(5), CatFrames(2, dim=-1, in_keys=["observation"])],
    ):
        with pytest.raises(
            ValueError,
            match=r"^transforms: (ObservationNorm|CatFrames) writes 'observation', the model's "
            r"state: .* write to another key \(out_keys=\[\.\.\.\]\)",
        ):
            make_rcvae_env(*args, start_states=starts, transforms=transform)
    # written to another key, the model's state is left as it is
    norm = ObservationNorm(
        loc=0.0, scale=10.0, in_keys=["observation"], out_keys=["observation_norm"]
    )
    env = make_rcvae_env(*args, start_states=starts, seed=0, transforms=norm)
    td = env.reset(TensorDict({"observation": starts[:2]}, batch_size=[2]))
    assert torch.equal(td["observation"], starts[:2])
    assert torch.allclose(td["observation_norm"], starts[:2] * 10)
    # a transform that knows its keys only from its parent env (an acrobot trial's
    # InitTracker, which a planner's warm start reads): built there, then checked
    from torchrl.envs import InitTracker

    tracked = make_rcvae_env(*args, start_states=starts, seed=0, transforms=[InitTracker()])
    assert bool(tracked.reset()["is_init"].all())


class SignAction(Transform):
    """Rounds the action to ±1 on its way to the env (a cart-pole's two pushes)."""

    def __init__(self):
        super().__init__(in_keys_inv=["action"], out_keys_inv=["action"])

    def _inv_apply_transform(self, action):
        return torch.where(action > 0, 1.0, -1.0).to(action.dtype)


def test_a_frame_skip_on_the_model_env_is_refused(ensemble, real_env, starts):
    """A cheetah trial: a FrameSkipTransform(4) on the model env stepped the stateless model
    four times from the same input, the state one step on and the reward four draws summed
    (0.450 against the state's own 0.086)."""
    from torchrl.envs import FrameSkipTransform

    from rcvae_torchrl.model_env import make_rcvae_env

    with pytest.raises(
        ValueError,
        match=r"^transforms: FrameSkipTransform\(4\) on the model env .* in the real env",
    ):
        make_rcvae_env(
            ensemble, real_env, pusher_reward, pusher_success, transforms=FrameSkipTransform(4)
        )


def test_the_assessor_refuses_a_transform_that_changes_the_action(ensemble, real_env, starts):
    """A cart-pole trial: a transform rounding the action on the model env was passed over by
    the assessor's imagination (``imagine`` is the base env's), so 0.3 was imagined as 0.3, not
    as the +1 the env acts on. Transforms of other entries stay welcome."""
    from torchrl.envs import InitTracker, RewardSum, StepCounter

    from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary
    from rcvae_torchrl.model_env import make_rcvae_env

    args = (ensemble, real_env, pusher_reward, pusher_success)
    boundary = SuccessBoundary(lambda s: s[..., 0] > 10.0, time_limit=5)
    rounded = make_rcvae_env(*args, start_states=starts, seed=0, transforms=[SignAction()])
    # the env's own step rounds (its transforms apply there), imagine does not
    td = rounded.reset(TensorDict({"observation": starts[:2]}, batch_size=[2]))
    assert rounded.transform.inv(td.set("action", torch.full((2, 2), 0.3)))["action"].eq(1).all()
    with pytest.raises(
        ValueError,
        match=r"^model_env: its transform SignAction changes the action .* past the transforms.*"
        r"TensorDictSequential\(policy, rounding_module\)",
    ):
        CompetencyAssessor(rounded, boundary, bin_width=0.1)
    others = [StepCounter(5), RewardSum(), InitTracker()]
    kept = make_rcvae_env(*args, start_states=starts, seed=0, transforms=others)
    assert CompetencyAssessor(kept, boundary, bin_width=0.1).model_env is kept


def test_training_actions_in_other_units_than_the_env_takes_are_warned_of(pusher_data, real_env):
    """An inventory trial: a model trained on orders of 0 to 50 units, for an env whose action
    spec is [0, 1] (in 50s), was accepted; its forecasts then fed it actions it never saw."""
    from model_env_utils import CONFIG

    from rcvae_torchrl.models import RCVAEEnsemble

    def model(actions: torch.Tensor) -> RCVAEEnsemble:
        ensemble = RCVAEEnsemble(CONFIG, ensemble_size=2)
        ensemble.fit_normalizer(pusher_data["observation"], actions)
        return ensemble

    actions = pusher_data["action"]  # inside the Pusher's [-1, 1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        RCVAEEnsembleEnv(model(actions), pusher_reward, pusher_success, real_env=real_env)
    scaled = model(actions * 25.0 + 25.0)  # the same actions in other units
    with pytest.warns(
        UserWarning,
        match=r"^action_spec: the world model's training actions cannot have lain inside its "
        r"bounds at action dimension\(s\) \[0, 1\]: their mean \[.*\] and spread .* against "
        r"bounds \[-1\.0, -1\.0\] to \[1\.0, 1\.0\]",
    ):
        RCVAEEnsembleEnv(scaled, pusher_reward, pusher_success, real_env=real_env)
    wide = actions.clone()
    wide[..., 1] = wide[..., 1].sign() * 3.0  # a spread no actions inside [-1, 1] can have
    with pytest.warns(UserWarning, match=r"at action dimension\(s\) \[1\]: "):
        RCVAEEnsembleEnv(model(wide), pusher_reward, pusher_success, real_env=real_env)


def test_a_dtype_mismatch_is_told_which_way_to_cast(pusher_data, real_env):
    """A trial's float64 model beside a float32 env (prepare_env's) and float32 data was told
    to "cast with TorchRL's DoubleToFloat transform", the wrong way round."""
    from model_env_utils import CONFIG

    from rcvae_torchrl._checks import check_dtype
    from rcvae_torchrl.models import RCVAEEnsemble

    double = RCVAEEnsemble(CONFIG, ensemble_size=2).double()
    with pytest.raises(
        TypeError,
        match=r"has dtype torch\.float32, the ensemble's is torch\.float64; give the model the "
        r"env's dtype \(ensemble\.to\(torch\.float32\)\), or an env of the model's",
    ):
        RCVAEEnsembleEnv(double, pusher_reward, pusher_success, real_env=real_env)
    with pytest.raises(TypeError, match=r"or the model to theirs \(model\.to\(torch\.float32\)\)$"):
        check_dtype("x", torch.zeros(2), torch.float64)
    with pytest.raises(TypeError, match=r"append a DoubleToFloat transform$"):
        check_dtype("x", torch.zeros(2, dtype=torch.float64), torch.float32)


@pytest.mark.parametrize(
    ("reward_fn", "success_fn", "words"),
    [
        (
            pusher_reward,
            lambda observation: (observation[..., 0] > 9).any(),
            "success_fn: expected a flag of shape [*B] = (2,) or [*B, 1] = (2, 1)",
        ),
        (
            lambda observation, action: observation.sum(),
            pusher_success,
            "reward_fn: expected a reward of shape [*B, 1] = (2, 1)",
        ),
    ],
)
def test_task_functions_that_reduce_over_the_batch_are_refused_when_the_env_is_made(
    ensemble, reward_fn, success_fn, words
):
    """Unbatched, one value has the right shape; on a batch of two it shows."""
    with pytest.raises(ValueError) as info:
        RCVAEEnsembleEnv(ensemble, reward_fn, success_fn)
    assert words in str(info.value)


def test_task_functions_that_raise_on_zero_states_are_judged_at_their_first_step(ensemble):
    def picky(observation):
        if not bool((observation != 0).any()):
            raise RuntimeError("not a state of mine")
        return observation[..., 0] > 9

    RCVAEEnsembleEnv(ensemble, pusher_reward, picky)  # made; judged on real states later


@pytest.mark.parametrize(
    ("call", "error", "words"),
    [
        (lambda env: env.set_seed("a"), ValueError, "seed: expected an integer in [0, 2**63)"),
        (
            lambda env: env.set_start_states([[0.0] * 14]),
            TypeError,
            "start_states: expected a torch.Tensor, got list",
        ),
    ],
)
def test_model_env_methods_refuse_other_types_by_name(ensemble, call, error, words):
    env = RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success)
    with pytest.raises(error) as info:
        call(env)
    assert words in str(info.value)


def test_a_generator_of_another_type_is_refused_when_the_env_is_made(ensemble):
    with pytest.raises(TypeError, match=r"generator: expected a torch\.Generator or None, got int"):
        RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, generator=3)


def test_a_plan_from_a_tensordict_without_its_batch_size_says_so(ensemble, starts):
    from rcvae_torchrl.planners import CEMPlanner

    env = RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, seed=0)
    planner = CEMPlanner(env, horizon=3, num_candidates=8, top_k=2)
    with pytest.raises(ValueError, match=r"batch_size \[\]") as info:
        planner(TensorDict({"observation": starts[:2]}, []))
    assert "build it with TensorDict({...}, batch_size=[2])" in str(info.value)
    assert planner(TensorDict({"observation": starts[:2]}, [2]))["action"].shape == (2, 2)


def test_model_env_specs_name_a_bad_ensemble_sampling_or_env(ensemble, make_env):
    """An unknown trajectory sampling got the specs of "ts1"; a string or a tensor for the
    ensemble or the env gave an AttributeError."""
    from rcvae_torchrl.model_env import model_env_specs

    cpu = torch.device("cpu")
    with pytest.raises(
        ValueError, match=r"trajectory_sampling: expected one of \['mean', 'ts1', 'ts_inf'\]"
    ):
        model_env_specs(ensemble, "foo", cpu)
    for bad in ("x", torch.zeros(3)):
        with pytest.raises(TypeError, match="ensemble: expected an RCVAEEnsemble, got"):
            model_env_specs(bad, "ts1", cpu)
    with pytest.raises(TypeError, match="real_env: expected a TorchRL EnvBase or None, got str"):
        model_env_specs(ensemble, "ts1", cpu, real_env="pusher")
    env = make_env()
    for bad, kind in (("x", "str"), (torch.zeros(3), "Tensor")):
        with pytest.raises(TypeError, match=f"env: expected a TorchRL EnvBase, got {kind}"):
            env.set_specs_from_env(bad)
    for bad, kind in (("nodevice", ValueError), (5.5, TypeError)):
        with pytest.raises(kind, match=r"device: expected a torch device \(e\.g\. 'cpu'"):
            model_env_specs(ensemble, "ts1", bad)
    assert "member" not in model_env_specs(ensemble, "mean", cpu).state.keys()  # as before
    assert "member" in model_env_specs(ensemble, "ts1", cpu).state.keys()
