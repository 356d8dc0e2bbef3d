"""The split of the doubt calibrated against real episodes: ``AleatoricShare``.

Closed-form cases: a dimension whose real episodes repeat keeps none of its aleatoric bits; a
share of 1 changes nothing; the total bits, P(success) and the rest of a report never change,
and at every level (steps, time means, summaries, per live step, by dimension) the epistemic
part is the total less the kept aleatoric part.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import AleatoricShare, UncertaintyMetric, rescale_aleatoric
from rcvae_torchrl.envs import OBSERVATION_NAMES, resolution_tensor
from rcvae_torchrl.io import load_torch, save_torch
from tests.competency.test_assessor import T, make_assessor, make_ensemble, make_env
from tests.competency.test_real_spread import _episodes, _outcomes


def _bits(episode_end: bool = True) -> TensorDict:
    gen = torch.Generator().manual_seed(0)
    obs = torch.randn(3, 16, 2, 6, 2, generator=gen)
    data = TensorDict(observation=obs)
    if episode_end:
        data["ended"] = torch.zeros(3, 16, 2, 6, dtype=torch.bool)
        data["ended"][:, :4, :, 3:] = True
    metric = UncertaintyMetric(bin_width=0.5, dim_names=("a", "b"), episode_end=episode_end)
    return metric(data)["uncertainty"]


@pytest.mark.parametrize("episode_end", [False, True])
def test_rescale_keeps_the_total_and_moves_the_rest_to_epistemic_at_every_level(episode_end):
    bits = _bits(episode_end)
    share = torch.tensor([0.25, 1.0])
    out = rescale_aleatoric(bits, share)
    levels = ["", "time_mean", "summary", *(["per_live_step"] if episode_end else [])]
    for level in levels:
        get = (lambda td, k: td[k]) if not level else (lambda td, k, lv=level: td[lv, k])
        torch.testing.assert_close(get(out, "total"), get(bits, "total"))
        torch.testing.assert_close(get(out, "epistemic"), get(out, "total") - get(out, "aleatoric"))
    torch.testing.assert_close(out["aleatoric"], bits["aleatoric"] * share)
    torch.testing.assert_close(
        out["time_mean", "aleatoric"], bits["time_mean", "aleatoric"] * share
    )
    # the summary sums the dimensions' time means: the kept ones
    torch.testing.assert_close(
        out["summary", "aleatoric"], (bits["time_mean", "aleatoric"] * share).sum(-1)
    )
    torch.testing.assert_close(
        out["by_dim", "a", "aleatoric"], bits["by_dim", "a", "aleatoric"] / 4
    )
    torch.testing.assert_close(out["by_dim", "b", "aleatoric"], bits["by_dim", "b", "aleatoric"])
    torch.testing.assert_close(
        out["by_dim", "a", "epistemic"],
        bits["by_dim", "a", "total"] - bits["by_dim", "a", "aleatoric"] / 4,
    )
    assert bool((out["epistemic"] >= bits["epistemic"]).all())
    unchanged = rescale_aleatoric(bits, torch.ones(2))
    for key in unchanged.keys(include_nested=True, leaves_only=True):
        torch.testing.assert_close(unchanged[key], bits[key])
    nothing = rescale_aleatoric(bits, torch.zeros(2))
    assert not bool(nothing["aleatoric"].any()) and not bool(nothing["summary", "aleatoric"].any())
    torch.testing.assert_close(nothing["epistemic"], bits["total"])
    assert bits["aleatoric"].sum() > 0  # the input is left as it was
    # the bare parts alone (a stored forecast) are rescaled too
    bare = rescale_aleatoric(TensorDict({k: bits[k] for k in ("total", "aleatoric")}), share)
    torch.testing.assert_close(bare["aleatoric"], out["aleatoric"])
    with pytest.raises(ValueError, match=r"^share: expected one share per state dimension \[2\]"):
        rescale_aleatoric(bits, torch.ones(3))


def _fitted(episode_end: bool = True):
    assessor = make_assessor(make_env(make_ensemble()), episode_end=episode_end)
    starts = _episodes()[:, 0, 0]
    report = assessor.assess(starts, actions=torch.zeros(T, 2), seed=0)
    spread = assessor.real_spread(_outcomes(_episodes()))
    return assessor, report, spread, AleatoricShare.fit(report, spread)


@pytest.mark.parametrize("episode_end", [False, True])
def test_the_share_is_the_real_spread_over_the_imagined_aleatoric_bits(episode_end):
    _, report, spread, share = _fitted(episode_end)
    assert share.start_states == 2 and share.per_live_step is episode_end
    assert share.dim_names == tuple(OBSERVATION_NAMES) and share.task == report.task
    unit = "per_live_step" if episode_end else "time_mean"
    if episode_end:  # the imagined and real episodes' own lives
        imagined = report.uncertainty["time_mean", "aleatoric"] * (
            report.uncertainty["live"].shape[-1] / report.uncertainty["live"].sum(-1, keepdim=True)
        )
        real = spread.bits["time_mean", "total"] * (
            spread.bits["live"].shape[-1] / spread.bits["live"].sum(-1, keepdim=True)
        )
    else:
        imagined = report.uncertainty["time_mean", "aleatoric"]
        real = spread.bits["time_mean", "total"]
    torch.testing.assert_close(share.imagined, imagined.mean(0))
    torch.testing.assert_close(share.real, real.mean(0))
    expected = torch.where(
        imagined.sum(0) > 0, (real.sum(0) / imagined.sum(0)).clamp(max=1.0), torch.ones(())
    )
    torch.testing.assert_close(share.share, expected)
    # dimension 0's runs spread over 4 bins at every step, 2 bits of the 4 starts' sum; the
    # untrained model's spread is wider: it keeps part; without an episode end the others repeat
    assert 0 < float(share.share[0]) < 1
    if not episode_end:
        moving = imagined.sum(0)[1:] > 0
        assert not bool(share.share[1:][moving].any())
    assert unit in report.uncertainty.keys()


def test_a_calibrated_report_keeps_its_forecast_and_says_so():
    _, report, _, share = _fitted()
    calibrated = report.with_aleatoric_share(share)
    assert calibrated.aleatoric_share is share
    torch.testing.assert_close(calibrated.uncertainty["total"], report.uncertainty["total"])
    torch.testing.assert_close(
        calibrated.uncertainty["aleatoric"], report.uncertainty["aleatoric"] * share.share
    )
    assert torch.equal(
        calibrated.competency["p_success"], report.competency["p_success"]
    )  # the forecast is the same
    said = calibrated.summary(0)
    assert share.describe() in said
    assert said.startswith(report.summary(0).split(" Most of the doubt")[0])
    a, e = calibrated.mean_bits()
    assert e > report.mean_bits()[1] and a < report.mean_bits()[0]
    kept = float((share.imagined * share.share).sum())
    assert (
        f"spread {float(share.real.sum()):.2f} bits per live step where the world model imagined "
        f"{float(share.imagined.sum()):.2f} aleatoric, so {kept:.2f} of them count as aleatoric"
    ) in share.describe()
    # a deterministic env's repeated episodes: no aleatoric part is left, all is epistemic
    none = replace(share, share=torch.zeros_like(share.share))
    repeated = report.with_aleatoric_share(none)
    assert not bool(repeated.uncertainty["aleatoric"].any())
    torch.testing.assert_close(repeated.uncertainty["epistemic"], report.uncertainty["total"])
    said = repeated.summary(0)
    assert none.describe() in said
    assert none.describe().endswith(
        "aleatoric, so none of them count as aleatoric: all are the model's own error (epistemic)."
    )
    assert "Most of the doubt is epistemic" in said
    assert "spread beyond what the agent's real episodes do" in said
    # the same report indexed keeps its share
    assert report.with_aleatoric_share(share)[0].aleatoric_share is share


def test_a_share_of_another_model_measure_or_report_is_refused():
    _, report, spread, share = _fitted()
    with pytest.raises(ValueError, match=r"^share: this report's split is calibrated already"):
        report.with_aleatoric_share(share).with_aleatoric_share(share)
    other = make_assessor(make_env(make_ensemble(seed=1)), episode_end=True)
    theirs = other.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    with pytest.raises(ValueError, match=r"^share: fitted for another task than this report's"):
        theirs.with_aleatoric_share(share)
    unended = make_assessor(make_env(make_ensemble()), episode_end=False)
    plain = unended.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    with pytest.raises(ValueError, match=r"^share: fitted on bits measured otherwise .*episode_e"):
        plain.with_aleatoric_share(replace(share, task=plain.task))
    with pytest.raises(TypeError, match=r"^share: expected the AleatoricShare of Aleatoric"):
        report.with_aleatoric_share(share.share)
    # fitted only on the real episodes of the report's own start states
    with pytest.raises(ValueError, match=r"^spread: expected the real episodes of this report's"):
        AleatoricShare.fit(report[:1], spread)
    with pytest.raises(TypeError, match=r"^report: expected a CompetencyReport"):
        AleatoricShare.fit(report.data, spread)
    coarse = make_assessor(
        make_env(make_ensemble()), episode_end=True, bin_width=2 * resolution_tensor()
    )
    wider = coarse.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    with pytest.raises(ValueError, match=r"^spread: measured otherwise than this report's"):
        AleatoricShare.fit(wider, spread)


def test_a_share_is_saved_and_read_back(tmp_path):
    _, report, _, share = _fitted()
    path = save_torch(tmp_path / "share.pt", share.as_dict())
    back = AleatoricShare.from_dict(load_torch(path, "aleatoric share"))
    for name in ("share", "imagined", "real"):
        torch.testing.assert_close(getattr(back, name), getattr(share, name))
    assert (back.task, back.steps, back.dim_names, back.per_live_step) == (
        share.task,
        share.steps,
        share.dim_names,
        share.per_live_step,
    )
    torch.testing.assert_close(
        report.with_aleatoric_share(back).uncertainty["aleatoric"],
        report.with_aleatoric_share(share).uncertainty["aleatoric"],
    )
    with pytest.raises(ValueError, match=r"^values: expected the entries .* missing \['task'\]"):
        AleatoricShare.from_dict({k: v for k, v in share.as_dict().items() if k != "task"})
    bad = {**share.as_dict(), "share": share.share + 2}
    with pytest.raises(ValueError, match=r"^values\['share'\]: expected shares in \[0, 1\]"):
        AleatoricShare.from_dict(bad)
