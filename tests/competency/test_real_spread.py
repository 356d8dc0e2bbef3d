"""The real episodes' spread, in bits, measured as an assessor measures the imagined ones'.

Closed-form cases: repeated episodes have no spread (0 bits); R runs in R bins of a dimension
have log2 R bits there; an episode that ends shares its bin with the other ended ones, so the
bits of a step are those of the process over states and {ended}.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from rcvae_torchrl.agent import RealOutcomes
from rcvae_torchrl.competency import RealSpread
from rcvae_torchrl.envs import obs_indices, resolution_tensor
from rcvae_torchrl.fingerprint import weights_digest
from tests.competency.test_assessor import T, make_assessor, make_ensemble, make_env

R, S = 4, 14


def _episodes() -> torch.Tensor:
    """``[2, R, T, S]``: start 0 repeats one episode; start 1's runs lie in R bins of
    dimension 0 (bin centres, one bin apart), its other dimensions alike, and its last run
    ends after 3 steps. The ball lies far from the target: no episode succeeds."""
    obs = torch.zeros(2, R, T, S)
    width = resolution_tensor()
    obs[..., obs_indices("ball")] = torch.tensor([0.3, 0.3])
    obs[..., obs_indices("target")] = torch.tensor([-0.3, -0.3])
    obs[..., 0] = 0.5 * width[0]
    obs[1, :, :, 0] += torch.arange(R, dtype=torch.float32)[:, None] * width[0]
    obs[1, -1, 3:] = math.nan  # ended by the env after its third step
    return obs


def _outcomes(obs: torch.Tensor) -> RealOutcomes:
    b, r = obs.shape[:2]
    none = torch.zeros(b, r, dtype=torch.bool)
    steps = (~obs.isnan().any(-1)).sum(-1)
    return RealOutcomes(none, torch.full((b, r), T), steps, observation=obs)


@pytest.mark.parametrize("episode_end", [False, True])
def test_the_real_spread_in_closed_form(episode_end):
    assessor = make_assessor(make_env(make_ensemble()), episode_end=episode_end)
    spread = assessor.real_spread(_outcomes(_episodes())).bits
    assert spread.batch_size == (2,)
    total = spread["total"]  # [2, T, S]
    assert total.shape == (2, T, S)
    assert torch.equal(spread["aleatoric"], total) and not bool(spread["epistemic"].any())
    assert not bool(total[0].any())  # repeated episodes: no spread at all
    ln2 = math.log(2)
    torch.testing.assert_close(total[1, :, 0], torch.full((T,), math.log2(R)))
    if not episode_end:  # the ended run holds its last state: alike in the other dimensions
        assert not bool(total[1, :, 1:].any())
        assert "live" not in spread.keys()
        return
    # from step 3 on, 3 runs alike and one ended: H(3/4, 1/4) in each other dimension
    after = -(0.75 * math.log(0.75) + 0.25 * math.log(0.25)) / ln2
    assert not bool(total[1, :3, 1:].any())
    torch.testing.assert_close(total[1, 3:, 1:], torch.full((T - 3, S - 1), after))
    live = torch.tensor([1.0] * 3 + [0.75] * (T - 3))
    torch.testing.assert_close(spread["live"][1], live)
    per_live = total[1].sum(-1).sum() / live.sum()
    torch.testing.assert_close(spread["per_live_step", "total"][1], per_live)
    assert float(spread["per_live_step", "total"][0]) == 0.0


def test_the_real_spread_needs_kept_observations_of_two_runs_over_the_horizon():
    assessor = make_assessor(make_env(make_ensemble()))
    obs = _episodes()
    with pytest.raises(ValueError, match=r"^outcomes: expected real outcomes with their obs"):
        assessor.real_spread(
            RealOutcomes(torch.zeros(2, R, dtype=torch.bool), torch.zeros(2, R), torch.ones(2, R))
        )
    with pytest.raises(ValueError, match=r"^outcomes: expected at least 2 real episodes per"):
        assessor.real_spread(_outcomes(obs[:, :1]))
    short = rf"^outcomes: expected real episodes of at least the horizon \({T} steps\), got {T - 1}"
    with pytest.raises(ValueError, match=short):
        assessor.real_spread(_outcomes(obs[:, :, : T - 1]))
    histogram_free = make_assessor(make_env(make_ensemble()), estimator="gaussian")
    with pytest.raises(ValueError, match=r"^estimator: the real spread is measured with the hi"):
        histogram_free.real_spread(_outcomes(obs))


def test_a_report_says_where_its_aleatoric_bits_leave_the_real_spread():
    assessor = make_assessor(make_env(make_ensemble()), episode_end=True)
    report = assessor.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    spread = assessor.real_spread(_outcomes(_episodes()))
    assert isinstance(spread, RealSpread) and spread.steps == T
    real = float(spread.bits["per_live_step", "total"].mean())
    assert repr(spread) == (
        f"RealSpread(start_states=2, steps={T}, per_live_step_bits={real:.2f}, agent=None, "
        "acting=None)"
    )
    aleatoric = report.uncertainty["per_live_step", "aleatoric"]
    assert bool((aleatoric > 1.0).all())  # an untrained model: bits of its own error
    attached = report.with_real_spread(spread)
    assert torch.equal(attached.data["real_spread", "total"], spread.bits["total"])
    first = attached.summary(0)
    mean = float(report.uncertainty["summary", "aleatoric"][0])
    assert (
        "The agent's real episodes from this start state spread 0.00 bits per live step (0.00 "
        f"as a time mean), the imagined aleatoric part {float(aleatoric[0]):.2f} ({mean:.2f})."
    ) in first
    assert "Caution: the aleatoric bits overstate the real episodes' spread" in first
    real = float(spread.bits["per_live_step", "total"].mean())
    overall = attached.overall()
    assert f"from these 2 start states spread {real:.2f} bits per live step" in overall
    assert "overstate" in overall
    assert "real episodes from" not in report.overall()  # none attached: nothing said
    # real episodes spread far wider than imagined: the model has not learned the noise
    wide = spread.bits.clone()
    wide["per_live_step", "total"] = aleatoric * 10
    said = report.with_real_spread(replace(spread, bits=wide)).summary(1)
    assert "Caution: the aleatoric bits understate the real episodes' spread" in said
    # within the tolerance: no caution
    near = spread.bits.clone()
    near["per_live_step", "total"] = aleatoric * 1.2
    near = replace(spread, bits=near)
    assert "Caution: the aleatoric bits" not in report.with_real_spread(near).summary(0)
    assert "Caution: the aleatoric bits" in report.with_real_spread(near, factor=1.1).summary(0)
    with pytest.raises(ValueError, match=r"^factor: expected >= 1, got 0.5"):
        report.with_real_spread(spread, factor=0.5)


def test_a_spread_of_other_starts_agent_or_measure_is_refused():
    assessor = make_assessor(make_env(make_ensemble()), episode_end=True)
    starts = _episodes()[:, 0, 0]
    report = assessor.assess(starts, actions=torch.zeros(T, 2), seed=0)
    spread = assessor.real_spread(_outcomes(_episodes()))
    with pytest.raises(TypeError, match=r"^spread: expected the RealSpread of CompetencyAssess"):
        report.with_real_spread(report.uncertainty)  # imagined bits are no real spread
    with pytest.raises(ValueError, match=r"^spread: expected the real episodes of this report's 2"):
        report.with_real_spread(replace(spread, bits=spread.bits[:1]))
    wider = make_assessor(
        make_env(make_ensemble()), episode_end=True, bin_width=resolution_tensor() * 10
    )
    with pytest.raises(ValueError, match=r"^spread: measured otherwise than this report's bits "):
        report.with_real_spread(wider.real_spread(_outcomes(_episodes())))
    no_end = make_assessor(make_env(make_ensemble()))
    with pytest.raises(ValueError, match=r"episode_end: False, this report's True"):
        report.with_real_spread(no_end.real_spread(_outcomes(_episodes())))
    with pytest.raises(ValueError, match=rf"steps: {T + 2}, this report's {T}"):
        report.with_real_spread(replace(spread, steps=T + 2))
    agent, other = (torch.nn.Linear(S, 2) for _ in range(2))
    mine = replace(report, agent=weights_digest(agent))
    with pytest.raises(ValueError, match=r"^spread: the real episodes are of another agent"):
        mine.with_real_spread(replace(spread, agent=weights_digest(other)))
    assert mine.with_real_spread(replace(spread, agent=weights_digest(agent))).data is not None
    moved = starts.clone()
    moved[1, 0] += 1.0
    with pytest.raises(ValueError, match=r"^spread: expected real episodes from the forecast's "):
        report.with_real_spread(replace(spread, starts=moved))
    assert report.with_real_spread(replace(spread, starts=starts)).data is not None
