"""imagine(): layout [E, N, *B, T], determinism, closed loop, input errors."""

from __future__ import annotations

import copy

import pytest
import torch

from rcvae_torchrl.rollout import chunk_size_for, imagine


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_shapes_and_keys(ensemble, batch):
    obs, actions = torch.randn(*batch, 5), torch.rand(*batch, 7, 2)
    td = imagine(ensemble, obs, actions, samples_per_member=6)
    assert td.batch_size == (4, 6, *batch, 7)
    assert td["observation"].shape == (4, 6, *batch, 7, 5)
    assert td["rcvae", "loc"].shape == td["rcvae", "scale"].shape == (4, 6, *batch, 7, 5)
    assert td["rcvae", "latent"].shape == (4, 6, *batch, 7, 3)
    assert torch.equal(td["action"][0, 0], actions)
    assert not td["observation"].requires_grad


def test_passthrough_dims_constant_and_zero_scale(ensemble):
    obs = torch.randn(3, 5)
    td = imagine(ensemble, obs, torch.rand(3, 9, 2), samples_per_member=4)
    assert torch.equal(td["observation"][..., 3:], obs[:, None, 3:].expand(4, 4, 3, 9, 2))
    assert (td["rcvae", "scale"][..., 3:] == 0).all()
    assert (td["rcvae", "scale"][..., :3] > 0).all()


def test_start_states_and_samples_are_laid_out_in_order(ensemble):
    """Sample n of start state b of member m must start from observation[b]."""
    obs = torch.tensor([[0.0] * 5, [100.0] * 5])
    td = imagine(ensemble, obs, torch.zeros(2, 1, 2), samples_per_member=3)
    assert (td["observation"][:, :, 0, 0, 3:] == 0).all()
    assert (td["observation"][:, :, 1, 0, 3:] == 100).all()


@pytest.mark.parametrize("chunk_size", [None, 1, 5, 1024])
def test_chunks_keep_the_layout(ensemble, chunk_size):
    """Trajectory n of start b lands at [:, n, b] whatever the chunking; the passthrough dims
    carry the start's index."""
    obs = torch.zeros(2, 2, 5)
    obs[..., 3] = torch.arange(4.0).reshape(2, 2)
    actions = torch.rand(2, 2, 3, 2)
    td = imagine(ensemble, obs, actions, samples_per_member=3, chunk_size=chunk_size)
    assert td.batch_size == (4, 3, 2, 2, 3)
    index = torch.arange(4.0).reshape(1, 1, 2, 2, 1)
    assert (td["observation"][..., 3] == index).all()
    assert torch.equal(td["action"], actions.expand(4, 3, 2, 2, 3, 2))


def test_determinism_under_generator(ensemble):
    obs, actions = torch.randn(2, 5), torch.rand(2, 6, 2)

    def run(seed):
        g = torch.Generator().manual_seed(seed)
        return imagine(ensemble, obs, actions, samples_per_member=5, generator=g)["observation"]

    assert torch.equal(run(0), run(0))
    assert not torch.equal(run(0), run(1))


def test_closed_loop_with_constant_policy_equals_open_loop(ensemble):
    obs = torch.randn(2, 5)
    action = torch.tensor([0.3, -0.7])
    open_loop = imagine(
        ensemble,
        obs,
        action.expand(2, 4, 2),
        samples_per_member=3,
        generator=torch.Generator().manual_seed(0),
    )
    calls = []

    def policy(state):
        calls.append(state.shape)
        return action.expand(*state.shape[:-1], 2)

    closed = imagine(
        ensemble,
        obs,
        policy=policy,
        horizon=4,
        samples_per_member=3,
        generator=torch.Generator().manual_seed(0),
    )
    assert calls == [(4, 6, 5)] * 4  # [E, trajectories per member, S]
    assert torch.equal(open_loop["observation"], closed["observation"])


def test_closed_loop_policy_sees_current_state(ensemble):
    seen = []

    def policy(state):
        seen.append(state.clone())
        return torch.zeros(*state.shape[:-1], 2)

    td = imagine(ensemble, torch.zeros(5), policy=policy, horizon=3, samples_per_member=2)
    torch.testing.assert_close(seen[1], td["observation"][..., 0, :])
    torch.testing.assert_close(seen[2], td["observation"][..., 1, :])


def test_requires_grad_keeps_graph(ensemble):
    td = imagine(ensemble, torch.zeros(5), torch.zeros(3, 2), requires_grad=True)
    td["observation"].sum().backward()
    assert ensemble.decoder[0].weight.grad is not None


def _nan(shape, where=0):
    x = torch.zeros(shape)
    x.view(-1)[where] = float("nan")
    return x


@pytest.mark.parametrize(
    ("obs", "actions", "kwargs", "error", "match"),
    [
        (_nan((2, 5)), torch.zeros(2, 3, 2), {}, ValueError, "observation: expected finite"),
        (torch.zeros(2, 5), _nan((2, 3, 2), 4), {}, ValueError, "actions: expected finite"),
        (
            torch.zeros(2, 5),
            torch.full((2, 3, 2), float("inf")),
            {},
            ValueError,
            "actions: expected finite",
        ),
        (torch.zeros(2, 4), torch.zeros(2, 3, 2), {}, ValueError, r"observation: expected shape"),
        (torch.zeros(2, 5), torch.zeros(2, 3, 3), {}, ValueError, r"actions: expected shape"),
        (torch.zeros(2, 5), torch.zeros(3, 3, 2), {}, ValueError, r"actions: expected batch shape"),
        (torch.zeros(2, 5), torch.zeros(2, 0, 2), {}, ValueError, r"T >= 1"),
        (torch.zeros(2, 5), torch.zeros(2, 3, 2), {"samples_per_member": 0}, ValueError, "samples"),
        (torch.zeros(5), None, {}, ValueError, "actions, policy: expected exactly one"),
        (torch.zeros(5), None, {"policy": torch.tanh}, ValueError, "horizon"),
        (torch.zeros(5).long(), torch.zeros(3, 2), {}, TypeError, "floating-point"),
        (torch.zeros(5), torch.zeros(3, 2), {"chunk_size": 0}, ValueError, "chunk_size"),
        (torch.zeros(5).double(), torch.zeros(3, 2), {}, TypeError, "observation: expected dtype"),
        (torch.zeros(5), torch.zeros(3, 2).double(), {}, TypeError, "actions: expected dtype"),
        (torch.zeros(5), torch.zeros(3, 2), {"horizon": 7}, ValueError, "horizon: open loop"),
    ],
)
def test_input_errors(ensemble, obs, actions, kwargs, error, match):
    with pytest.raises(error, match=match):
        imagine(ensemble, obs, actions, **kwargs)


def test_policy_with_wrong_output_is_rejected(ensemble):
    said = (
        rf"^policy: expected actions of shape \([\d, ]+\) \(one action of A = "
        rf"{ensemble.config.action_dim} entries for each of the \[[\d, ]+\] imagined states it "
        r"was given\), got \([\d, ]+\) at step 0$"
    )
    with pytest.raises(ValueError, match=said):
        imagine(ensemble, torch.zeros(5), policy=lambda s: s, horizon=2)
    with pytest.raises(ValueError, match="policy output at step 0: expected finite"):
        imagine(
            ensemble,
            torch.zeros(5),
            policy=lambda s: torch.full((*s.shape[:-1], 2), torch.nan),
            horizon=2,
        )


def test_a_later_non_finite_policy_action_is_named_by_its_step(ensemble):
    calls = []

    def policy(s):
        calls.append(None)
        value = torch.inf if len(calls) == 3 else 0.0
        return torch.full((*s.shape[:-1], 2), value)

    with pytest.raises(
        ValueError,
        match=r"policy output at step 2: expected finite values, got 0 NaN and 8 inf entries in "
        r"a tensor of shape \(4, 1, 2\)",
    ):
        imagine(ensemble, torch.zeros(1, 5), policy=policy, horizon=5, samples_per_member=1)


def test_a_non_finite_action_is_named_before_the_policy_fails_on_its_outcome(ensemble):
    """A planner that makes a NaN action and then raises on the NaN state it led to (its model
    env refuses it): the error names the step of the NaN action, not the later failure."""

    def policy(s):
        if not bool(torch.isfinite(s).all()):
            raise ValueError("observation: expected finite values")
        value = torch.nan if s.abs().sum() > 0 else 0.0  # step 0 (zeros) fine, step 1 NaN
        return torch.full((*s.shape[:-1], 2), value)

    with pytest.raises(ValueError, match=r"policy output at step 1: expected finite") as caught:
        imagine(ensemble, torch.zeros(1, 5), policy=policy, horizon=5, samples_per_member=1)
    assert "observation: expected finite" in str(caught.value.__context__)


def test_states_the_model_made_non_finite_are_blamed_on_the_model(ensemble):
    """Damaged weights make NaN states from finite ones; the policy's NaN actions from them
    are named as the model's doing."""
    damaged = copy.deepcopy(ensemble)
    with torch.no_grad():
        for param in damaged.parameters():
            param.fill_(torch.nan)
    with pytest.raises(
        ValueError,
        match=r"the imagined states at step 1: expected finite values, got \d+ NaN .*: the world "
        r"model made them \(the policy's actions were finite until then\)",
    ):
        imagine(
            damaged,
            torch.zeros(1, 5),
            policy=lambda s: s[..., :2].tanh(),
            horizon=3,
            samples_per_member=1,
        )


def test_closed_loop_reads_nothing_back_per_step(ensemble, monkeypatch):
    """The policy's actions are checked once per rollout, not once per step: the number of
    values read back to the host does not grow with the horizon (on an accelerator each read
    makes it wait for the host)."""
    reads = []
    for name in ("__bool__", "item", "__int__", "__float__", "tolist"):
        original = getattr(torch.Tensor, name)

        def counted(self, *args, _original=original, **kwargs):
            reads.append(None)
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(torch.Tensor, name, counted)

    def count(horizon: int) -> int:
        reads.clear()
        imagine(ensemble, torch.zeros(2, 5), policy=lambda s: s[..., :2].tanh(), horizon=horizon)
        return len(reads)

    assert count(3) == count(12)


def test_non_finite_model_output_is_an_error(ensemble):
    with torch.no_grad():
        ensemble.decoder[-1].bias.fill_(float("inf"))
    with pytest.raises(ValueError, match="non-finite states from step 1"):
        imagine(ensemble, torch.zeros(5), torch.zeros(3, 2))


def test_auto_chunk_size_by_device():
    """``"auto"`` keeps the CPU's cache-sized chunks and widens them on an accelerator."""
    assert chunk_size_for("auto", "cpu") == 1024
    assert chunk_size_for("auto", torch.device("cuda", 0)) == 65536
    assert chunk_size_for(None, "cpu") is None and chunk_size_for(7, "cuda") == 7
    with pytest.raises(ValueError, match="chunk_size"):
        chunk_size_for(0, "cpu")


def test_the_default_chunks_are_the_cpus_1024(ensemble):
    """On a CPU the default draws the same samples as ``chunk_size=1024`` (and not as one
    chunk, once there is more than one chunk)."""
    obs, actions = torch.randn(3, 5), torch.rand(3, 4, 2)

    def draw(chunk_size):
        gen = torch.Generator().manual_seed(0)
        kwargs = {} if chunk_size == "default" else {"chunk_size": chunk_size}
        return imagine(ensemble, obs, actions, samples_per_member=400, generator=gen, **kwargs)

    default = draw("default")["observation"]
    assert torch.equal(default, draw(1024)["observation"])
    assert not torch.equal(default, draw(None)["observation"])


class _Counting:
    """A policy with memory (the steps it has acted in its batch of episodes) and a reset."""

    def __init__(self) -> None:
        self.steps, self.resets, self.first_steps = 0, 0, []

    def reset(self) -> None:
        self.steps, self.resets = 0, self.resets + 1

    def __call__(self, s: torch.Tensor) -> torch.Tensor:
        if self.steps == 0:
            self.first_steps.append(s.shape[1])
        self.steps += 1
        return torch.full((*s.shape[:-1], 2), 0.1 * min(self.steps, 5))


def test_a_stateful_policy_is_reset_before_every_batch_of_imagined_episodes(ensemble):
    """An LSTM trial: imagine's chunks of 1,024 episodes per member began with the last
    chunk's memory (h = 0.9999 in place of 0), and a planner's warm start leaked the same way.
    Each chunk after the first now starts with the policy's reset; the caller resets before
    the first."""
    policy = _Counting()
    out = imagine(
        ensemble, torch.zeros(5, 5), policy=policy, horizon=3, samples_per_member=4, chunk_size=8
    )
    assert policy.resets == 2 and policy.first_steps == [8, 8, 4]  # 20 rows, chunks of 8
    # every episode acts as at its start: the same actions in every chunk
    assert torch.equal(out["action"], out["action"][:1, :1, :1].expand_as(out["action"]))


def test_a_recurrent_tensordict_policy_is_refused_before_it_runs(ensemble):
    """A trial's LSTM policy (TorchRL's LSTMModule, with InitTracker's is_init written from
    the observation) ran with its memory reset at every step, silently: it reads entries
    imagination does not carry, which the module filled with zeros."""
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.modules import LSTMModule

    lstm = LSTMModule(input_size=5, hidden_size=4, in_keys=["observation", "rh", "rc"],
                      out_keys=["features", ("next", "rh"), ("next", "rc")])  # fmt: skip
    init = TensorDictModule(
        lambda o: torch.ones(*o.shape[:-1], 1, dtype=torch.bool),
        in_keys=["observation"],
        out_keys=["is_init"],
    )
    head = TensorDictModule(torch.nn.Linear(4, 2), in_keys=["features"], out_keys=["action"])
    policy = TensorDictSequential(init, lstm, head)
    with pytest.raises(
        KeyError,
        match=r"policy: holds a recurrent LSTMModule, whose memory lives in entries beside the "
        r"state .* as if every step were its first\. Keep the memory inside a policy of your "
        r"own: .* reset\(\) before each batch",
    ):
        imagine(ensemble, torch.zeros(2, 5), policy=policy, horizon=3, samples_per_member=2)
