"""FixedRowsPolicy: each row's action does not depend on the batch it comes in."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.agent import FixedRowsPolicy, MLPPolicy, make_policy_module, real_outcomes
from rcvae_torchrl.envs import (
    ball_to_target,
    make_batched_pusher_env,
    make_pusher_env,
    reset_to_state,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from tests.pusher_fixtures import pusher_starts


def _mlp_policy(seed: int = 0):
    torch.manual_seed(seed)
    mlp = MLPPolicy(14, 2, hidden=256)
    mlp.obs_std.fill_(0.3)
    return make_policy_module(mlp.eval())


def _actions(policy, observations: torch.Tensor) -> torch.Tensor:
    td = TensorDict(observation=observations, batch_size=observations.shape[:-1])
    with torch.no_grad():
        return policy(td)["action"]


@pytest.mark.parametrize("name", ["mlp", "scripted"])
def test_each_rows_action_is_the_same_in_any_batch(name):
    # the scripted pusher is elementwise, but a vectorised kernel (atan2 above all) can round an
    # element otherwise than the scalar loop that takes a short tensor: called bare, some of
    # these states get another action alone than in the batch of all of them
    base = _mlp_policy() if name == "mlp" else make_scripted_policy()
    policy = FixedRowsPolicy(base, rows=16 if name == "mlp" else 64)
    count, scale = (90, 1.0) if name == "mlp" else (400, 0.3)
    states = scale * torch.randn(count, 14, generator=torch.Generator().manual_seed(1))
    reference = _actions(policy, states)
    for size in (1, 2, 7, 15, 16, 17, 40, 63):
        for offset in (0, 3, 27):
            got = _actions(policy, states[offset : offset + size])
            assert torch.equal(got, reference[offset : offset + size]), (size, offset)
    for i in range(count):  # an env with batch_size []: a single state
        alone = _actions(policy, states[i])
        assert alone.shape == (2,) and torch.equal(alone, reference[i]), i
    nested = _actions(policy, states[:60].reshape(3, 20, 14))  # workers x envs
    assert torch.equal(nested, reference[:60].reshape(3, 20, 2))


def test_the_wrapped_policy_writes_into_the_given_tensordict():
    td = TensorDict(observation=torch.zeros(3, 14), batch_size=[3])
    out = FixedRowsPolicy(_mlp_policy(), rows=2)(td)
    assert out is td and td["action"].shape == (3, 2) and td["observation"].shape == (3, 14)


def test_reset_is_passed_on_and_bad_arguments_are_named():
    class Counting:
        resets = 0

        def __call__(self, td):
            return td.set("action", td["observation"][..., :2])

        def reset(self):
            self.resets += 1

    inner = Counting()
    FixedRowsPolicy(inner).reset()
    FixedRowsPolicy(_mlp_policy()).reset()  # a policy without reset: nothing to do
    assert inner.resets == 1
    with pytest.raises(ValueError, match="rows"):
        FixedRowsPolicy(inner, rows=0)
    with pytest.raises(TypeError, match="policy: expected a TensorDict policy, got int"):
        FixedRowsPolicy(3)


def test_real_outcomes_do_not_depend_on_the_batched_envs_size():
    """A learned policy alone, in batches of 3 and of 5: the same episodes, bit for bit."""
    starts, kwargs = pusher_starts(4), dict(time_limit=2.0, terminate_on_success=False)
    args = dict(
        runs_per_start=2,
        reset_to_state=reset_to_state,
        max_steps=40,
        trace=ball_to_target,
        seed=3,
        policy_rows=8,
        progress=False,
    )
    policy = _mlp_policy(1)
    runs = [real_outcomes(make_pusher_env("stochastic", **kwargs), policy, starts, **args)]
    for n in (3, 5):
        env = make_batched_pusher_env(n, "stochastic", **kwargs)
        runs.append(real_outcomes(env, policy, starts, **args))
    for run in runs[1:]:
        for name in ("success", "first_step", "steps", "trace"):
            assert torch.equal(getattr(run, name).nan_to_num(), getattr(runs[0], name).nan_to_num())


def test_a_planner_is_refused_blocks_of_rows():
    """A planner's warm start would carry over from one block of rows to the next."""
    from rcvae_torchrl.envs import pusher_reward, pusher_success
    from rcvae_torchrl.model_env import RCVAEEnsembleEnv
    from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
    from rcvae_torchrl.planners import CEMPlanner

    ensemble = RCVAEEnsemble(RCVAEConfig(14, 2, hidden_dim=8, latent_dim=2, mlp_dim=8), 2)
    model_env = RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, seed=0)
    planner = CEMPlanner(model_env, horizon=2, num_candidates=4, top_k=2)
    with pytest.raises(ValueError, match=r"policy_rows: expected None for a planner .* got 8"):
        real_outcomes(
            make_pusher_env(),
            planner,
            pusher_starts(1),
            runs_per_start=1,
            reset_to_state=reset_to_state,
            max_steps=2,
            policy_rows=8,
        )
