"""Any TorchRL env as the library expects it: dict float64 observations, noise, seeds."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, NonTensor, Unbounded
from torchrl.envs import DMControlEnv, EnvBase, PendulumEnv
from torchrl.envs.utils import check_env_specs

from rcvae_torchrl.data import ActionNoise, ObservationLayout, prepare_env, seed_env
from rcvae_torchrl.model_env import make_rcvae_env
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble


def _reward(observation, action):
    return -observation[..., :1]


def _success(observation):
    return observation[..., 0] > 1.0


@pytest.fixture(scope="module")
def reacher():
    return DMControlEnv("reacher", "easy")


def test_dict_float64_observations_become_one_named_float32_vector(reacher):
    env, layout = prepare_env(reacher)
    assert layout == ObservationLayout(("position", "to_target", "velocity"), (2, 2, 2))
    assert layout.names[2:4] == ("to_target[0]", "to_target[1]")
    assert layout.indices("velocity") == [4, 5]
    td = env.reset()
    assert td["observation"].dtype == torch.float32 and td["observation"].shape == (6,)
    torch.testing.assert_close(td["observation"][2:4], td["to_target"])
    assert env.action_spec.dtype == torch.float32
    check_env_specs(env)


def test_keys_are_concatenated_in_the_order_given(reacher):
    env, layout = prepare_env(reacher, ["velocity", "position"], keep_keys=False)
    assert layout.keys == ("velocity", "position")
    td = env.reset()
    assert "velocity" not in td.keys() and td["observation"].shape == (4,)


class _ScalarEnv(EnvBase):
    """A stateful env with a scalar and a vector observation."""

    def __init__(self):
        super().__init__()
        self.observation_spec = Composite(x=Unbounded(()), v=Unbounded((2,)))
        self.action_spec = Bounded(-1.0, 1.0, (1,))
        self.reward_spec = Unbounded((1,))
        self._x = torch.zeros(())

    def _reset(self, tensordict):
        self._x = torch.zeros(())
        return TensorDict({"x": self._x.clone(), "v": torch.zeros(2)})

    def _step(self, tensordict):
        self._x = self._x + tensordict["action"][0]
        return TensorDict(
            {
                "x": self._x.clone(),
                "v": torch.stack([self._x, -self._x]),
                "reward": -self._x.abs().reshape(1),
                "done": torch.zeros(1, dtype=torch.bool),
                "terminated": torch.zeros(1, dtype=torch.bool),
            }
        )

    def _set_seed(self, seed):
        pass


def test_scalar_entries_count_as_one_dimension_and_stay_scalars():
    # TorchRL's pendulum reads its state back from the tensordict: the sources must stay
    env, layout = prepare_env(PendulumEnv(), ["th", "thdot"])
    assert layout == ObservationLayout(("th", "thdot"), (1, 1))
    check_env_specs(env)
    td = env.rollout(3)
    assert td["th"].shape == (3,) and td["next", "observation"].shape == (3, 2)
    expected = torch.stack([td["next", "th"], td["next", "thdot"]], -1)
    torch.testing.assert_close(td["next", "observation"], expected)
    assert not any("unsqueezed" in str(k) for k in td.keys(True, True))


def test_scalar_entries_without_keeping_the_sources():
    env, layout = prepare_env(_ScalarEnv(), ["x", "v"], keep_keys=False)
    assert layout.names == ("x", "v[0]", "v[1]")
    check_env_specs(env)
    td = env.rollout(2, lambda td: td.set("action", torch.full((1,), 0.5)))
    assert set(td["next"].keys()) == {"observation", "reward", "done", "terminated"}
    torch.testing.assert_close(td["next", "observation"][-1], torch.tensor([1.0, 1.0, -1.0]))


def test_bad_keys_are_clear_errors(reacher):
    with pytest.raises(KeyError, match=r"observation_keys: DMControlEnv has no observation 'pos'"):
        prepare_env(reacher, ["pos"])
    with pytest.raises(KeyError, match="key: expected one of"):
        ObservationLayout(("a",), (2,)).indices("b")
    with pytest.raises(TypeError, match=r"observation_keys: expected a list of keys, e.g. \['x'\]"):
        prepare_env(_ScalarEnv(), "x")  # not the keys 'x' character by character
    with pytest.raises(
        ValueError, match=r"observation_keys: expected each key once, got \['x', 'x'\]"
    ):
        prepare_env(_ScalarEnv(), ["x", "x"])
    with pytest.raises(TypeError, match="keep_keys: expected True or False, got 'no'"):
        prepare_env(_ScalarEnv(), ["x"], keep_keys="no")
    for env, given in ((None, "NoneType"), (_ScalarEnv, "the class _ScalarEnv")):
        with pytest.raises(TypeError, match=f"env: expected a TorchRL env .*, got {given}"):
            prepare_env(env)


def test_entries_that_are_not_tensors_are_left_out_or_named():
    env = _ScalarEnv()
    env.observation_spec = Composite(x=Unbounded(()), v=Unbounded((2,)), note=NonTensor(shape=()))
    assert prepare_env(env)[1].keys == ("x", "v")  # by default: only floating tensors
    with pytest.raises(
        ValueError, match=r"'note' must be a floating .* got dtype None \(NonTensor"
    ):
        prepare_env(env, ["x", "note"])


def test_the_model_env_names_the_fix_for_a_raw_dm_control_env(reacher):
    model = RCVAEEnsemble(RCVAEConfig(6, 2, hidden_dim=8, mlp_dim=8), 2)
    with pytest.raises(KeyError, match=r"has no 'observation'.*prepare_env"):
        make_rcvae_env(model, reacher, _reward, _success)
    from torchrl.envs import CatTensors, TransformedEnv

    raw = TransformedEnv(reacher, CatTensors(["position", "to_target", "velocity"], "observation"))
    with pytest.raises(TypeError, match=r"dtype torch.float64.*DoubleToFloat"):
        make_rcvae_env(model, raw, _reward, _success)
    prepared, _ = prepare_env(reacher)
    check_env_specs(make_rcvae_env(model, prepared, _reward, _success, seed=0))


def test_action_noise_is_seeded_and_records_the_commanded_action():
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    env.append_transform(ActionNoise(0.5))

    def zero(td):
        return td.set("action", torch.zeros(2))

    runs = []
    for seed in (3, 3, 4):
        seed_env(env, seed)
        runs.append(env.rollout(5, zero))
    assert (runs[0]["action"] == 0).all()
    assert runs[0]["next", "velocity"].abs().sum() > 0  # the noise moved the mass
    assert torch.equal(runs[0]["next", "observation"], runs[1]["next", "observation"])
    assert not torch.equal(runs[0]["next", "observation"], runs[2]["next", "observation"])
    with pytest.raises(ValueError, match="std: expected a finite standard deviation >= 0"):
        ActionNoise(-1.0)


def test_action_noise_is_clipped_to_the_spec():
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    noise = ActionNoise(100.0)
    env.append_transform(noise)
    td = TensorDict({"action": torch.zeros(2)}, [])
    applied = noise.inv(td)["action"]
    assert (applied.abs() <= 1).all() and (applied.abs() == 1).any()


def test_seed_env_restarts_noise_in_every_layer_of_transforms():
    """ActionNoise wrapped around the raw env before prepare_env sits in an inner layer of
    transforms: seeding the prepared env restarts it too, so seeded episodes repeat."""
    from torchrl.envs import StepCounter, TransformedEnv

    raw = TransformedEnv(DMControlEnv("point_mass", "easy"), ActionNoise(1.0))
    env, _ = prepare_env(raw)
    env.append_transform(StepCounter(10))
    runs = []
    for _ in range(2):
        seed_env(env, 3)
        runs.append(env.rollout(5, lambda td: td.set("action", torch.zeros(2)))["observation"])
    assert torch.equal(*runs) and runs[0].std(0).max() > 0


def test_action_noise_of_another_size_than_the_actions_is_named():
    env, _ = prepare_env(PendulumEnv(), ["th", "thdot"])  # one action dimension
    env.append_transform(ActionNoise(torch.tensor([0.5, 0.5])))
    with pytest.raises(
        ValueError,
        match=r"^std: expected a scalar or one standard deviation per action dimension, "
        r"\[A = 1\] for this env's actions, got shape \(2,\)",
    ):
        env.rand_step()


def test_an_angle_is_modelled_as_its_cosine_and_sine():
    from torchrl.envs import TransformedEnv

    from rcvae_torchrl.data import AngleAsCosSin

    angles = TransformedEnv(PendulumEnv(), AngleAsCosSin(["th"]))
    env, layout = prepare_env(angles, ["th_cos", "th_sin", "thdot"])
    assert layout.names == ("th_cos", "th_sin", "thdot")
    check_env_specs(env)
    rollout = env.rollout(4)
    for td in (rollout, rollout["next"]):
        torch.testing.assert_close(td["observation"][..., 0], td["th"].cos())
        torch.testing.assert_close(td["observation"][..., 1], td["th"].sin())
    assert env.observation_spec["th_cos"].space.low == -1
    with pytest.raises(KeyError, match=r"^\"in_keys: the env has no observation 'angle'"):
        _ = TransformedEnv(PendulumEnv(), AngleAsCosSin(["angle"])).observation_spec
    with pytest.raises(TypeError, match=r"^in_keys: expected a non-empty list of angle keys"):
        AngleAsCosSin("th")


def test_control_step_reads_the_simulator_s_step_times_every_frame_skip():
    from torchrl.envs import FrameSkipTransform

    from rcvae_torchrl.data import control_step

    env, _ = prepare_env(DMControlEnv("reacher", "easy"))  # dm_control's reacher: 0.02 s
    assert control_step(env) == (0.02, "DMControlEnv's control timestep 0.02 s")
    env.append_transform(FrameSkipTransform(5))
    assert control_step(env) == (
        0.1,
        "DMControlEnv's control timestep 0.02 s x FrameSkipTransform(5)",
    )
    # TorchRL's own frame skip, done by the wrapper, then a transform's on top
    native = DMControlEnv("reacher", "easy", frame_skip=3).append_transform(FrameSkipTransform(2))
    assert control_step(native) == (
        0.12,
        "DMControlEnv's control timestep 0.02 s x frame_skip=3 x FrameSkipTransform(2)",
    )
    # TorchRL's PendulumEnv declares its parameters (gen_params()), its dt among them
    assert control_step(PendulumEnv()) == (0.05, "PendulumEnv's default params' dt 0.05 s")

    class OtherParams(PendulumEnv):  # a gen_params of another kind: no step to read
        @staticmethod
        def gen_params(scale, batch_size=None, device=None):
            raise AssertionError("not called without its arguments")

    assert control_step(OtherParams(td_params=PendulumEnv.gen_params())) is None

    class OwnEnv(EnvBase):  # an env of one's own: its dt attribute, not gen_params' default
        def __init__(self, dt=None):
            super().__init__()
            if dt is not None:
                self.dt = dt
            self.observation_spec = Composite(observation=Unbounded((1,)))
            self.action_spec = Unbounded((1,))
            self.reward_spec = Unbounded((1,))

        @staticmethod
        def gen_params(dt=0.05):
            return TensorDict({"params": {"dt": torch.tensor(dt)}})

        def _reset(self, tensordict):
            return TensorDict({"observation": torch.zeros(1)})

        def _step(self, tensordict):
            raise AssertionError("not stepped")

        def _set_seed(self, seed):
            pass

    assert control_step(OwnEnv(dt=0.1)) == (0.1, "OwnEnv's dt 0.1 s")
    assert control_step(OwnEnv()) is None  # gen_params' default need not be the env's
    # a gym or gymnasium env (TorchRL's GymEnv keeps it as _env): its unwrapped env's dt
    from types import SimpleNamespace

    gym_like = PendulumEnv()
    gym_like._env = SimpleNamespace(unwrapped=SimpleNamespace(dt=0.05))
    assert control_step(gym_like.append_transform(FrameSkipTransform(2))) == (
        0.1,
        "PendulumEnv's dt 0.05 s x FrameSkipTransform(2)",
    )
    # a batched env: its sub-envs are not reached, nor are its workers started to ask them
    from torchrl.envs import ParallelEnv

    batched = ParallelEnv(2, lambda: DMControlEnv("reacher", "easy"))
    assert control_step(batched) is None and batched.is_closed


def test_observation_layout_reads_a_prepared_env_s_concatenation(reacher):
    from torchrl.envs import FrameSkipTransform

    from rcvae_torchrl.data import observation_layout

    env, layout = prepare_env(reacher)
    assert observation_layout(env) == layout
    # named entries in another order, a scalar among them, the sources dropped, and a
    # transform appended after: still the layout prepare_env returned
    finger = DMControlEnv("finger", "turn_easy")
    keys = ["velocity", "dist_to_target", "position"]
    env, layout = prepare_env(finger, keys, keep_keys=False)
    env.append_transform(FrameSkipTransform(2))
    assert observation_layout(env) == layout == ObservationLayout(tuple(keys), (3, 1, 4))
    # an env that gives "observation" itself: nothing to read
    assert observation_layout(finger) is None
    assert observation_layout(prepare_env(PendulumEnv(), ["th", "thdot"])[0]).names == (
        "th",
        "thdot",
    )


def test_a_model_env_refuses_a_real_env_whose_dimensions_are_in_another_order():
    finger = DMControlEnv("finger", "turn_easy")
    trained, layout = prepare_env(finger)  # position, velocity, touch, target, distance
    config = RCVAEConfig(layout.dim, 2, hidden_dim=8, mlp_dim=8, observation_names=layout.names)
    model = RCVAEEnsemble(config, 2)
    make_rcvae_env(model, trained, _reward, _success)  # the layout it was trained on
    order = ["velocity", "position", "touch", "dist_to_target", "target_position"]
    moved, _ = prepare_env(finger, order)  # the same 12 dimensions, elsewhere
    with pytest.raises(
        ValueError,
        match=r"^real_env: its 'observation' has 'velocity\[0\]' as dimension 0, where the "
        r"ensemble was trained on 'position\[0\]' \(10 of 12 dimensions differ\): .*"
        r"prepare_env\(env, observation_keys=\['position', 'velocity', 'touch', "
        r"'target_position', 'dist_to_target'\]\)",
    ):
        make_rcvae_env(model, moved, _reward, _success)
    # names of the user's own (none of the env's entries') are not compared
    renamed = RCVAEConfig(
        layout.dim, 2, hidden_dim=8, mlp_dim=8, observation_names=[f"d{i}" for i in range(12)]
    )
    make_rcvae_env(RCVAEEnsemble(renamed, 2), moved, _reward, _success)


def test_a_boundary_dt_that_is_not_the_real_env_s_step_is_named():
    from torchrl.envs import FrameSkipTransform, StepCounter

    from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary

    env, layout = prepare_env(DMControlEnv("reacher", "easy"))
    env.append_transform(FrameSkipTransform(5))  # 0.1 s per step
    model = RCVAEEnsemble(RCVAEConfig(layout.dim, 2, hidden_dim=8, mlp_dim=8), 2)

    def assess(model_env, boundary):
        return CompetencyAssessor(model_env, boundary, bin_width=0.1)

    for model_env in (
        make_rcvae_env(model, env, _reward, _success, seed=0),
        make_rcvae_env(model, env, _reward, _success, seed=0, transforms=StepCounter(10)),
    ):
        assert model_env.real_control_step[0] == 0.1
        with pytest.raises(
            ValueError,
            match=r"^dt: expected the seconds one step of the model env stands for, 0.1 s "
            r"\(DMControlEnv's control "
            r"timestep 0.02 s x FrameSkipTransform\(5\)\), got 0.02 s: .* off by 5x; give "
            r"SuccessBoundary\(\.\.\., dt=0.1\)",
        ):
            assess(model_env, SuccessBoundary(_success, time_limit_s=1.0, dt=0.02))
        right = assess(model_env, SuccessBoundary(_success, time_limit_s=1.0, dt=0.1))
        assert right.boundary.time_limit == 10
        # times in steps (no dt) are not checked: nothing in them is in seconds
        assess(model_env, SuccessBoundary(_success, time_limit=10))
    # a model env without a real env has no step to check against
    assert make_rcvae_env(model, None, _reward, _success).real_control_step is None


def test_a_model_that_records_its_training_step_refuses_an_env_of_another_step(tmp_path):
    from torchrl.envs import FrameSkipTransform

    from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary
    from rcvae_torchrl.data import control_step
    from rcvae_torchrl.training import load_ensemble, save_ensemble

    skipped, layout = prepare_env(DMControlEnv("reacher", "easy"))
    skipped.append_transform(FrameSkipTransform(5))  # 0.1 s per step, as trained
    config = RCVAEConfig(
        layout.dim, 2, hidden_dim=8, mlp_dim=8, control_step=control_step(skipped)[0]
    )
    save_ensemble(RCVAEEnsemble(config, 2), tmp_path / "model.pt")
    model = load_ensemble(tmp_path / "model.pt")  # the step is kept with the model
    assert model.config.control_step == 0.1
    assert make_rcvae_env(model, skipped, _reward, _success).real_control_step[0] == 0.1
    plain, _ = prepare_env(DMControlEnv("reacher", "easy"))  # the frame skip forgotten
    with pytest.raises(
        ValueError,
        match=r"^real_env: one of its steps takes 0.02 s \(DMControlEnv's control timestep "
        r"0.02 s\), where the ensemble was trained on steps of 0.1 s \(its config's "
        r"control_step\): each imagined step would stand for a real step 5x its length; .*"
        r"FrameSkipTransform",
    ):
        make_rcvae_env(model, plain, _reward, _success)
    # without a real env, a boundary's dt is checked against the training step
    alone = make_rcvae_env(model, None, _reward, _success)
    assert alone.real_control_step == (
        0.1,
        "the ensemble's control_step, the step of its training episodes",
    )
    with pytest.raises(
        ValueError, match=r"^dt: .* 0.1 s \(the ensemble's control_step, .*off by 5x"
    ):
        CompetencyAssessor(
            alone, SuccessBoundary(_success, time_limit_s=1.0, dt=0.02), bin_width=0.1
        )
    CompetencyAssessor(alone, SuccessBoundary(_success, time_limit_s=1.0, dt=0.1), bin_width=0.1)
    # a step of no length, or not a number, is refused where the config is made
    for bad, error in ((0.0, ValueError), (float("nan"), ValueError), ("0.1", TypeError)):
        with pytest.raises(error, match=r"^RCVAEConfig.control_step must be"):
            RCVAEConfig(layout.dim, 2, control_step=bad)
