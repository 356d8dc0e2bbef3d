"""Bad input to the rollout functions gives errors that name the argument, what was expected
and what was given, before any step runs."""

from __future__ import annotations

import math

import pytest
import torch

from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.rollout import (
    ActionBounds,
    Task,
    alive_mask,
    evaluate_action_sequences,
    imagine,
    make_transition_module,
    particle_groups,
    propagate,
)


@pytest.fixture(scope="module")
def model():
    return RCVAEEnsemble(RCVAEConfig(4, 2, hidden_dim=16, mlp_dim=16), ensemble_size=3)


TASK = Task(
    lambda observation, action: -observation[..., :1], lambda observation: observation[..., 0] > 1
)


def test_an_unknown_trajectory_sampling_is_refused(model):
    """ "TS_INF" ran the deterministic "mean" mode with one particle, without a word."""
    with pytest.raises(ValueError, match=r"trajectory_sampling: expected one of .*'TS_INF'"):
        evaluate_action_sequences(
            model,
            torch.zeros(5, 4),
            torch.zeros(5, 6, 2),
            4,
            task=TASK,
            trajectory_sampling="TS_INF",
        )
    with pytest.raises(ValueError, match=r"trajectory_sampling: expected one of .*'bogus'"):
        particle_groups("bogus", 4, 3)
    with pytest.raises(ValueError, match=r"mode: expected one of .*'bogus'"):
        propagate(model, "bogus", torch.zeros(3, 1, 16), torch.zeros(1, 4), torch.zeros(1, 2))


@pytest.mark.parametrize(
    ("start", "actions", "particles", "match"),
    [
        ((4, 4), (5, 6, 2), 4, r"actions: expected \[R=4, H, A=2\] with H >= 1"),
        ((5, 4), (5, 0, 2), 4, r"actions: expected \[R=5, H, A=2\] with H >= 1"),
        ((5, 4), (5, 6), 4, r"actions: expected \[R=5, H, A=2\]"),
        ((5, 3), (5, 6, 2), 4, r"start: expected \[R, S=4\] with R >= 1, got \(5, 3\)"),
        ((0, 4), (0, 6, 2), 4, r"start: expected \[R, S=4\] with R >= 1"),
        ((5, 4), (5, 6, 2), 0, "particles: expected a positive integer, got 0"),
        ((5, 4), (5, 6, 2), 2.5, "particles: expected a positive integer, got 2.5"),
        ((5, 4), (5, 6, 2), True, "particles: expected a positive integer, got True"),
    ],
)
def test_scoring_names_shapes_and_counts(model, start, actions, particles, match):
    with pytest.raises(ValueError, match=match):
        evaluate_action_sequences(
            model, torch.zeros(start), torch.zeros(actions), particles, task=TASK
        )


def test_scoring_names_a_missing_task_or_model(model):
    with pytest.raises(TypeError, match=r"task: expected a rollout\.Task, got NoneType"):
        evaluate_action_sequences(model, torch.zeros(5, 4), torch.zeros(5, 6, 2), 2, task=None)
    with pytest.raises(TypeError, match="ensemble: expected an RCVAEEnsemble, got NoneType"):
        evaluate_action_sequences(None, torch.zeros(5, 4), torch.zeros(5, 6, 2), 2, task=TASK)


def test_crossed_nan_or_plain_bounds_are_refused(model):
    """Crossed bounds put every action at one of them; NaN ones were blamed on the model."""
    start, plan = torch.zeros(4), torch.full((5, 2), 0.5)
    for low, high in ((torch.ones(2), -torch.ones(2)), (torch.full((2,), math.nan), torch.ones(2))):
        with pytest.raises(ValueError, match=r"bounds: expected low <= high \(and no NaN\)"):
            imagine(model, start, plan, bounds=ActionBounds(low, high))
        with pytest.raises(ValueError, match=r"bounds: expected low <= high \(and no NaN\)"):
            evaluate_action_sequences(
                model,
                torch.zeros(5, 4),
                torch.zeros(5, 6, 2),
                2,
                task=TASK,
                bounds=ActionBounds(low, high),
            )
    with pytest.raises(TypeError, match=r"bounds: expected ActionBounds\(low, high\) of tensors"):
        imagine(model, start, plan, bounds=(-1.0, 1.0))
    with pytest.raises(ValueError, match=r"bounds.low: expected a tensor of shape \[A=2\]"):
        imagine(model, start, plan, bounds=ActionBounds(-torch.ones(3), torch.ones(3)))
    clipped = imagine(model, start, plan, bounds=ActionBounds(-torch.ones(2), 0.25 * torch.ones(2)))
    assert torch.equal(clipped["action"], torch.full_like(clipped["action"], 0.25))


def test_flags_and_prefixes_of_the_wrong_kind_are_refused(model):
    with pytest.raises(TypeError, match="requires_grad: expected True or False, got 'yes'"):
        imagine(model, torch.zeros(4), torch.zeros(5, 2), requires_grad="yes")
    with pytest.raises(TypeError, match=r"out_prefix: expected a tuple of key names"):
        make_transition_module(model, out_prefix="next")
    with pytest.raises(TypeError, match=r"done: expected bool flags, got dtype torch\.float32"):
        alive_mask(torch.tensor([0.0, 0.5, 0.0, 1.0]))
    with pytest.raises(ValueError, match=r"reward, success: expected \[H, n\] rewards and bool"):
        TASK.returns(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match=r"reward, success: expected \[H, n\] rewards and bool"):
        TASK.returns(torch.zeros(4), torch.zeros(4, dtype=torch.bool))


def test_member_layouts_and_devices_are_named():
    from rcvae_torchrl.rollout import MemberLayout, chunk_size_for, init_model_state

    for member in (torch.tensor([0, 3]), torch.tensor([0, -1])):
        with pytest.raises(ValueError, match=r"member: expected values in \[0, 3\), got range"):
            MemberLayout(member, 3)
    with pytest.raises(TypeError, match=r"member: expected an int64 tensor \[B\], got torch"):
        MemberLayout(torch.tensor([0.0, 1.0]), 3)
    with pytest.raises(ValueError, match="ensemble_size: expected a positive integer, got 0"):
        MemberLayout(torch.tensor([0, 1]), 0)
    with pytest.raises(ValueError, match="device: expected a torch device, got 'nodevice'"):
        chunk_size_for("auto", "nodevice")
    model = RCVAEEnsemble(RCVAEConfig(4, 2, hidden_dim=16, mlp_dim=16), ensemble_size=3)
    with pytest.raises(TypeError, match="observation"):
        init_model_state(model, torch.zeros(2, 4, dtype=torch.int64))
    with pytest.raises(TypeError, match="observation"):
        init_model_state(model, torch.zeros(2, 4, dtype=torch.float64))
