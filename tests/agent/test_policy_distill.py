"""The amortised policy and behaviour cloning."""

import pytest
import torch

from rcvae_torchrl.agent import DistillConfig, MLPPolicy, distill_policy, make_policy_module


def test_policy_shapes_bounds_and_normaliser():
    policy = MLPPolicy(5, 2, hidden=16)
    obs = torch.randn(7, 3, 5) * 10 + 4
    policy.fit_normalizer(obs)
    torch.testing.assert_close(policy.obs_mean, obs.reshape(-1, 5).mean(0))
    action = policy(obs)
    assert action.shape == (7, 3, 2) and (action.abs() <= 1).all()
    module = make_policy_module(policy)
    assert module.out_keys == ["action"]
    with pytest.raises(ValueError, match=r"observation: expected shape \[\.\.\., 5\]"):
        policy(torch.zeros(3, 4))


def test_distillation_recovers_a_smooth_teacher():
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(3000, 4, generator=g)
    teacher = torch.stack([torch.tanh(obs[:, 0] - obs[:, 1]), 0.5 * torch.sin(obs[:, 2])], -1)
    config = DistillConfig(epochs=60, batch_size=128, lr=3e-3, patience=10)
    policy, stats = distill_policy(obs, teacher, config, progress=False)
    baseline = teacher.var(0).sum().item() / 2  # MSE of predicting the mean action
    assert stats["val_mse"] < 0.05 * baseline, stats
    # Determinism under the seed.
    again, _ = distill_policy(obs, teacher, config, progress=False)
    assert torch.equal(policy(obs[:10]), again(obs[:10]))


def test_bad_pairs():
    with pytest.raises(ValueError, match="same N"):
        distill_policy(torch.zeros(20, 3), torch.zeros(19, 2))
    with pytest.raises(ValueError, match="at least 10 pairs"):
        distill_policy(torch.zeros(5, 3), torch.zeros(5, 2))
    bad = torch.zeros(20, 3)
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        distill_policy(bad, torch.zeros(20, 2))


def test_policy_files_round_trip_and_refuse_bad_files(tmp_path):
    from rcvae_torchrl.agent import ResidualPolicy, load_policy, save_policy
    from rcvae_torchrl.io import StoredFileError

    policy = MLPPolicy(5, 2, hidden=16)
    policy.fit_normalizer(torch.randn(40, 5) * 3 + 1)
    obs = torch.randn(6, 5)
    save_policy(policy, tmp_path / "mlp.pt")
    torch.testing.assert_close(load_policy(tmp_path / "mlp.pt")(obs), policy(obs))

    base = torch.nn.Linear(5, 2)
    save_policy(ResidualPolicy(base, policy), tmp_path / "residual.pt")
    with pytest.raises(ValueError, match=r"base: .*residual policy"):
        load_policy(tmp_path / "residual.pt")
    loaded = load_policy(tmp_path / "residual.pt", base=base)
    assert isinstance(loaded, ResidualPolicy)
    torch.testing.assert_close(loaded(obs), ResidualPolicy(base, policy)(obs))

    data = (tmp_path / "mlp.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(StoredFileError, match=r"policy file .*cut\.pt.* truncated or corrupt"):
        load_policy(tmp_path / "cut.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(StoredFileError, match="expected a policy saved by save_policy"):
        load_policy(tmp_path / "foreign.pt")
    with pytest.raises(StoredFileError, match="the file is missing"):
        load_policy(tmp_path / "none.pt")


def test_labels_a_tanh_policy_cannot_reach_and_mismatched_policies_are_refused():
    obs = torch.randn(40, 3)
    with pytest.raises(ValueError, match=r"actions: expected labels in \[-1, 1\]"):
        distill_policy(obs, torch.full((40, 2), 3.0))
    with pytest.raises(
        ValueError, match=r"policy: expected actions of A=1 .*, got a policy of A=2$"
    ):
        distill_policy(obs, torch.zeros(40, 1), policy=MLPPolicy(3, 2))
    for kwargs in ({"lr": float("inf")}, {"seed": -1}, {"epochs": True}):
        with pytest.raises(ValueError, match=f"{next(iter(kwargs))}: expected"):
            DistillConfig(**kwargs)
    policy = MLPPolicy(3, 2)
    for bad in (torch.zeros(1, 3), torch.zeros(4, 2), torch.full((4, 3), float("nan"))):
        with pytest.raises(ValueError, match="observations: expected"):
            policy.fit_normalizer(bad)


def test_a_perturbed_policy_of_unbounded_noise_or_crossed_bounds_is_refused():
    from rcvae_torchrl.agent.dagger import PerturbedPolicy

    policy = make_policy_module(MLPPolicy(3, 2))
    with pytest.raises(ValueError, match="noise_std: expected a finite number >= 0, got inf"):
        PerturbedPolicy(policy, float("inf"))
    with pytest.raises(
        ValueError, match=r"low, high: expected low <= high \(and no NaN\), got 1\.0 and -1\.0"
    ):
        PerturbedPolicy(policy, 0.1, low=1.0, high=-1.0)


@pytest.mark.parametrize(
    ("args", "name"), [((0, 2), "obs_dim"), ((3, 2, -1), "hidden"), ((2.5, 1), "obs_dim")]
)
def test_policy_sizes_are_positive_ints(args, name):
    with pytest.raises(ValueError, match=f"{name}: expected a positive integer"):
        MLPPolicy(*args)


def test_pairs_of_another_dtype_and_bad_dagger_arguments_are_named():
    from rcvae_torchrl.agent import PerturbedPolicy, dagger, label_states

    obs, act = torch.rand(20, 3), torch.rand(20, 2) * 2 - 1
    with pytest.raises(TypeError, match=r"observations: expected torch\.float32 .* torch\.float64"):
        distill_policy(obs.double(), act, DistillConfig(epochs=1), progress=False)
    with pytest.raises(TypeError, match=r"observations: expected a torch\.Tensor, got ndarray"):
        distill_policy(obs.numpy(), act, DistillConfig(epochs=1), progress=False)
    with pytest.raises(TypeError, match="val_fraction: expected a float in"):
        DistillConfig(val_fraction="0.1")
    with pytest.raises(ValueError, match="seed: expected an integer"):
        PerturbedPolicy(lambda td: td, 0.1, seed=1.5)
    with pytest.raises(ValueError, match="noise_std: expected a finite number >= 0"):
        PerturbedPolicy(lambda td: td, "0.1")
    with pytest.raises(TypeError, match="policy: expected a TorchRL policy"):
        PerturbedPolicy(None, 0.1)
    with pytest.raises(ValueError, match=r"states: expected shape \[M, S\]"):
        label_states(lambda td: td, torch.zeros(4))
    common = {"max_steps": 3, "progress": False}
    with pytest.raises(TypeError, match="episode_seeds: expected a function of the round"):
        dagger(None, None, obs, act, DistillConfig(epochs=1), rounds=1, episode_seeds=[1], **common)
    with pytest.raises(ValueError, match="rounds: expected an integer >= 0, got -1"):
        dagger(
            None, None, obs, act, DistillConfig(epochs=1), rounds=-1, episode_seeds=None, **common
        )


def test_a_residual_on_a_base_of_another_action_size_is_refused():
    from rcvae_torchrl.agent import ResidualPolicy

    mlp = MLPPolicy(4, 2)
    with pytest.raises(ValueError, match=r"base: expected actions \[B, A=2\] .* got \(1, 1\)"):
        ResidualPolicy(torch.nn.Linear(4, 1), mlp)
    with pytest.raises(TypeError, match="residual: expected an MLPPolicy"):
        ResidualPolicy(torch.nn.Linear(4, 2), torch.nn.Linear(4, 2))
    assert ResidualPolicy(torch.nn.Linear(4, 2), mlp)(torch.zeros(3, 4)).shape == (3, 2)


def test_dagger_names_a_planner_of_another_action_size():
    from rcvae_torchrl.agent import dagger
    from tests.agent.worker_envs import terminating_point_mass

    env = terminating_point_mass()
    obs = torch.rand(20, 4, generator=torch.Generator().manual_seed(0))
    labels = torch.zeros(20, 2)

    def planner(td):  # three actions where the labels hold two
        return td.set("action", torch.zeros(*td.batch_size, 3))

    with pytest.raises(ValueError, match=r"planner: expected actions of A=2 .* got A=3"):
        dagger(
            planner,
            env,
            obs,
            labels,
            DistillConfig(epochs=1),
            rounds=1,
            episode_seeds=lambda k: [k],
            max_steps=3,
            progress=False,
        )
