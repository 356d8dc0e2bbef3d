"""make_mpc_policy: the compile setting reaches the model env; compiled plans equal eager ones."""

from __future__ import annotations

import pytest
import torch

from rcvae_torchrl.agent import PlannerConfig, make_mpc_policy
from rcvae_torchrl.envs import make_pusher_env, pusher_reward, pusher_success
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

# the model, task and horizon of the other ahead-of-time scoring tests: one build per session
CONFIG = RCVAEConfig(14, 2, hidden_dim=16, latent_dim=4, mlp_dim=16, passthrough_dims=(12, 13))
PLANNER = PlannerConfig(horizon=2, num_candidates=16, top_k=4, iterations=2, particles=6)


@pytest.fixture(scope="module")
def real_env():
    return make_pusher_env(seed=1)


def _policy(real_env, compile):
    torch.manual_seed(0)
    model = RCVAEEnsemble(CONFIG, ensemble_size=3).eval()
    return make_mpc_policy(
        model, real_env, PLANNER, reward_fn=pusher_reward, success_fn=pusher_success,
        compile=compile,
    )  # fmt: skip


@pytest.mark.parametrize("compile", [False, True, "aot"])
def test_compile_reaches_the_model_env(real_env, compile):
    assert _policy(real_env, compile).env.compile_scoring == compile


@pytest.mark.parametrize("compile", ["fast", 1, None])
def test_an_unknown_compile_setting_is_a_named_error(real_env, compile):
    with pytest.raises(ValueError, match=r"compile_scoring: expected False .* or 'aot'"):
        _policy(real_env, compile)


def test_aot_plans_equal_eager_plans(real_env):
    """The same seed, the same noise: the plans of the ahead-of-time compiled scoring agree
    with the eager ones (returns differ by float rounding only, far below elite gaps)."""
    torch.manual_seed(0)
    state = real_env.reset()
    actions = {}
    for compile in (False, "aot"):
        policy = _policy(real_env, compile)
        with torch.no_grad():
            actions[compile] = torch.stack([policy(state.clone())["action"] for _ in range(3)])
    torch.testing.assert_close(actions["aot"], actions[False], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"momentum": "0.1"}, "momentum: expected a number, got '0.1'"),
        ({"prior_std": True}, "prior_std: expected a number, got True"),
        ({"prior_std": float("inf")}, "prior_std: expected a positive finite number, got inf"),
    ],
)
def test_planner_settings_of_another_type_or_unbounded_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PlannerConfig(**kwargs)


def test_collect_episodes_takes_the_planner_which_needs_only_the_real_env_s_observation():
    # its in_keys name the model env's own state, which the real env does not write; the
    # model env makes that state from the observation
    from rcvae_torchrl.data import collect_episodes

    policy = _policy(make_pusher_env(time_limit=1.0), False)
    assert ("rcvae", "hidden") in policy.in_keys
    data = collect_episodes(
        lambda: make_pusher_env(time_limit=1.0), policy, num_episodes=2, seed=0, progress=False
    )
    assert data.shape == (40,) and bool((data["action"].abs() <= 1).all())
