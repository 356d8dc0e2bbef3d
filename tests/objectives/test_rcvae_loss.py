"""RCVAELoss: LossModule contract, layouts, masks, open-loop steps, errors."""

from __future__ import annotations

import math

import pytest
import torch

from rcvae_torchrl.objectives import RCVAELoss

SCALARS = ("loss_reconstruction", "loss_kl", "kl_raw", "nll", "mse", "pred_std_mean")
PER_MEMBER = ("loss_per_member", "nll_per_member", "kl_per_member")


def _seeded(ensemble, seed=0, **kwargs):
    return RCVAELoss(ensemble, generator=torch.Generator().manual_seed(seed), **kwargs)


@pytest.mark.parametrize("batch", [(5, 8), (3, 5, 8)])
def test_output_keys_shapes_and_backward(ensemble, windows_of, batch):
    out = RCVAELoss(ensemble)(windows_of(batch))
    assert set(out.keys()) == set(SCALARS + PER_MEMBER)
    for key in SCALARS:
        assert out[key].shape == ()
    for key in PER_MEMBER:
        assert out[key].shape == (3,)
    torch.testing.assert_close(out["loss_reconstruction"], out["nll_per_member"].sum())
    (out["loss_reconstruction"] + out["loss_kl"]).backward()
    for name, param in ensemble.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
    assert not out["kl_raw"].requires_grad and not out["loss_per_member"].requires_grad


def test_broadcast_windows_equal_member_major_copies(ensemble, windows):
    """[W, L] windows are the same as [E, W, L] with each member given the same windows."""
    shared = _seeded(ensemble)(windows)
    stacked = _seeded(ensemble)(windows.expand(3, *windows.batch_size).clone())
    for key in SCALARS:
        torch.testing.assert_close(shared[key], stacked[key])


def test_set_keys(ensemble, windows):
    loss = _seeded(ensemble)
    loss.set_keys(observation="obs", action=("agent", "act"), mask="valid")
    assert loss.in_keys == ["obs", ("agent", "act"), ("next", "observation"), "valid"]
    renamed = windows.clone()
    renamed.rename_key_("observation", "obs")
    renamed.rename_key_("action", ("agent", "act"))
    torch.testing.assert_close(
        loss(renamed)["loss_reconstruction"], _seeded(ensemble)(windows)["loss_reconstruction"]
    )
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(reward="r")


def test_next_observations_add_the_last_transition(ensemble, windows):
    """With ("next", "observation"), a window of L steps has L transitions; the targets come
    from the next observations, so they may differ from the following step's observation
    (e.g. at an episode's end)."""
    with_next = windows.clone()
    following = torch.randn(5, 1, 4)
    with_next["next", "observation"] = torch.cat([windows["observation"][:, 1:], following], 1)
    seq = ensemble(
        with_next["observation"].expand(3, 5, 8, 4),
        with_next["action"].expand(3, 5, 8, 2),
        next_observations=with_next["next", "observation"].expand(3, 5, 8, 4),
    )
    short = ensemble(
        windows["observation"].expand(3, 5, 8, 4), windows["action"].expand(3, 5, 8, 2)
    )
    assert seq.target.shape[-2] == 8 and short.target.shape[-2] == 7
    torch.testing.assert_close(seq.target[..., :7, :], short.target)
    torch.testing.assert_close(seq.prior_mean[..., :7, :], short.prior_mean)
    out = RCVAELoss(ensemble)(with_next)
    assert torch.isfinite(out["loss_reconstruction"])
    single = with_next[:, :1]  # one step with its next observation: one transition
    assert torch.isfinite(RCVAELoss(ensemble)(single)["nll"])


def test_mask_with_next_observations_counts_each_valid_step(ensemble, windows):
    windows["next", "observation"] = torch.randn(5, 8, 4)
    mask = torch.ones(5, 8, dtype=torch.bool)
    mask[:, 7] = False
    windows["collector", "mask"] = mask
    padded = windows.clone()
    padded["next", "observation"][:, 7] = 1e3
    a, b = _seeded(ensemble)(windows), _seeded(ensemble)(padded)
    torch.testing.assert_close(a["nll"], b["nll"])


def test_beta_and_free_nats(ensemble, windows):
    base = _seeded(ensemble)(windows)
    half = _seeded(ensemble, beta=0.5)(windows)
    torch.testing.assert_close(half["loss_kl"], 0.5 * base["loss_kl"])
    free = _seeded(ensemble, free_nats=50.0)(windows)
    torch.testing.assert_close(free["loss_kl"], torch.tensor(3 * 50.0))  # sum over 3 members
    torch.testing.assert_close(free["kl_raw"], base["kl_raw"])


def test_beta_nll_reweights_only_the_training_reconstruction(ensemble, windows):
    base = _seeded(ensemble)(windows)
    weighted = _seeded(ensemble, nll_beta=0.5)(windows)
    torch.testing.assert_close(weighted["nll"], base["nll"])  # diagnostics stay the plain NLL
    torch.testing.assert_close(weighted["loss_per_member"], base["loss_per_member"])
    assert not torch.allclose(weighted["loss_reconstruction"], base["loss_reconstruction"])


def test_beta_nll_of_one_gives_the_mean_a_squared_error_gradient():
    from rcvae_torchrl.objectives.functional import gaussian_nll

    target, mean = torch.tensor([1.0, 1.0]), torch.zeros(2, requires_grad=True)
    std = torch.tensor([0.1, 10.0])
    (gaussian_nll(target, mean, std) * std.pow(2.0)).sum().backward()
    torch.testing.assert_close(mean.grad, torch.tensor([-1.0, -1.0]))  # same for both stds


def test_mask_excludes_padded_steps(ensemble, windows):
    mask = torch.ones(5, 8, dtype=torch.bool)
    mask[:, 6:] = False  # right padding
    windows["collector", "mask"] = mask
    padded = windows.clone()
    padded["observation"][:, 6:] = 1e3  # garbage where the mask is off
    a, b = _seeded(ensemble)(windows), _seeded(ensemble)(padded)
    for key in SCALARS:
        torch.testing.assert_close(a[key], b[key])
    cut = _seeded(ensemble)(windows[:, :6].exclude(("collector", "mask")))
    assert cut["nll"] != a["nll"]  # different noise layout; but both finite
    assert torch.isfinite(cut["nll"]) and torch.isfinite(a["nll"])


def test_left_padding_resets_the_hidden_state(ensemble, windows):
    """With the first 3 steps masked, the model state is that of the window starting at 3."""
    seq_full = ensemble(
        windows["observation"].expand(3, 5, 8, 4),
        windows["action"].expand(3, 5, 8, 2),
        mask=torch.arange(8).ge(3).expand(1, 5, 8),
    )
    seq_cut = ensemble(
        windows["observation"][:, 3:].expand(3, 5, 5, 4),
        windows["action"][:, 3:].expand(3, 5, 5, 2),
    )
    torch.testing.assert_close(seq_full.prior_mean[..., 3:, :], seq_cut.prior_mean)
    torch.testing.assert_close(seq_full.posterior_std[..., 3:, :], seq_cut.posterior_std)


def test_open_loop_steps(ensemble, windows):
    teacher = _seeded(ensemble)(windows)
    opened = _seeded(ensemble, open_loop_steps=3)(windows)
    assert opened["nll"] != teacher["nll"]
    capped = _seeded(ensemble, open_loop_steps=100)(windows)  # capped at L - 2
    assert torch.isfinite(capped["loss_reconstruction"])
    loss = _seeded(ensemble, open_loop_steps=0)
    loss.open_loop_steps = 3  # curriculum: change between steps
    torch.testing.assert_close(loss(windows)["nll"], opened["nll"])


def test_open_loop_gradients_flow_through_fed_back_samples(ensemble, windows):
    """The reconstruction term reaches the prior network only through the fed-back prior
    samples of the open-loop steps, so detaching them cuts that gradient."""

    def prior_grad(open_loop_steps, detach):
        ensemble.zero_grad()
        loss = _seeded(ensemble, open_loop_steps=open_loop_steps, detach_open_loop=detach)
        loss(windows)["loss_reconstruction"].backward()
        return ensemble.prior_net[0].weight.grad

    assert prior_grad(0, False) is None
    assert prior_grad(6, False).abs().max() > 0
    assert prior_grad(6, True) is None


@pytest.mark.parametrize(
    ("mutate", "error", "match"),
    [
        (lambda td: td[:, 0], ValueError, r"batch \[W, L\] or \[E=3, W, L\]"),
        (lambda td: td.expand(2, 5, 8).clone(), ValueError, r"\[E=3, W, L\]"),
        (lambda td: td[:, :1], ValueError, "at least one transition, got L=1 without next"),
        (
            lambda td: td.set(
                "observation", td["observation"].index_fill(1, torch.tensor(2), torch.nan)
            ),
            ValueError,
            "observation: expected finite values, got 20 NaN",
        ),
        (
            lambda td: td.set("action", td["action"].index_fill(0, torch.tensor(0), torch.inf)),
            ValueError,
            "action: expected finite",
        ),
        (
            lambda td: td.exclude("observation").set("observation", torch.zeros(5, 8, 3)),
            ValueError,
            r"observation: expected shape \[..., L, S=4\], got \(5, 8, 3\)",
        ),
        (
            lambda td: td.exclude("action").set("action", torch.zeros(5, 8, 1)),
            ValueError,
            r"action: expected shape \[..., L, A=2\]",
        ),
        (
            lambda td: td.set("observation", td["observation"].double()),
            TypeError,
            "observation: expected dtype torch.float32",
        ),
        (
            lambda td: td.set(("collector", "mask"), torch.ones(5, 8)),
            ValueError,
            "expected a bool mask",
        ),
    ],
)
def test_input_errors(ensemble, windows, mutate, error, match):
    with pytest.raises(error, match=match):
        RCVAELoss(ensemble)(mutate(windows))


def test_constructor_errors(ensemble):
    with pytest.raises(ValueError, match=r"nll_beta: expected a float in \[0, 1\], got 2"):
        RCVAELoss(ensemble, nll_beta=2.0)
    with pytest.raises(ValueError, match="beta: expected a finite number >= 0, got -1"):
        RCVAELoss(ensemble, beta=-1.0)
    for name, bad in (("beta", math.nan), ("beta", math.inf), ("free_nats", math.nan)):
        with pytest.raises(ValueError, match=f"{name}: expected a finite number >= 0"):
            RCVAELoss(ensemble, **{name: bad})
    for bad in (2.7, "2", True, -1):
        with pytest.raises(ValueError, match="open_loop_steps: expected an integer >= 0"):
            RCVAELoss(ensemble, open_loop_steps=bad)
    with pytest.raises(TypeError, match="detach_open_loop: expected True or False, got 'no'"):
        RCVAELoss(ensemble, detach_open_loop="no")
    with pytest.raises(TypeError, match="validate: expected True or False, got 1"):
        RCVAELoss(ensemble, validate=1)


def test_validate_false_skips_only_the_finite_check(ensemble, windows):
    """Off, a NaN window reaches the loss (the caller has checked its data); shapes and
    dtypes are still refused, and on finite windows the loss is the same."""
    nan = windows["observation"].index_fill(1, torch.tensor(2), torch.nan)
    bad = windows.clone().set("observation", nan)
    loss = RCVAELoss(ensemble, validate=False)
    assert torch.isnan(loss(bad)["loss_per_member"]).all()
    with pytest.raises(TypeError, match=r"observation: expected dtype torch\.float32"):
        loss(windows.clone().set("observation", windows["observation"].double()))
    torch.manual_seed(0)
    checked = RCVAELoss(ensemble)(windows)["loss_per_member"]
    torch.manual_seed(0)
    assert torch.equal(loss(windows)["loss_per_member"], checked)


def test_the_checked_loss_reads_nothing_back_under_compile(ensemble, windows):
    """With validate=False the loss is one graph for torch.compile: no value read back to the
    host (which on a GPU waits for the queued kernels at every training step)."""
    explained = torch._dynamo.explain(RCVAELoss(ensemble, validate=False))(windows)
    assert explained.graph_break_count == 0, explained.break_reasons
    torch._dynamo.reset()


def test_windows_that_would_teach_nothing_are_refused(ensemble, windows, windows_of):
    """A missing entry failed as an AttributeError; no windows gave a NaN loss and an
    all-False mask a loss of 0."""
    loss = RCVAELoss(ensemble)
    with pytest.raises(KeyError, match="RCVAELoss: expected an entry 'observation'"):
        loss(windows.exclude("observation"))
    with pytest.raises(ValueError, match="RCVAELoss: expected at least one window"):
        loss(windows_of((0, 8)))
    masked = windows.clone()
    masked["collector", "mask"] = torch.zeros(5, 8, dtype=torch.bool)
    with pytest.raises(ValueError, match="expected some valid steps, got a mask that is all"):
        loss(masked)
