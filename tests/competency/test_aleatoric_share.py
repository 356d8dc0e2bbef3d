"""The split of the doubt calibrated against real episodes: ``AleatoricShare``.

Closed-form cases: a dimension whose real episodes repeat keeps none of its aleatoric bits; a
share of 1 changes nothing; the total bits, P(success) and the rest of a report never change,
and at every level (steps, time means, summaries, per live step, by dimension) the epistemic
part is the total less the kept aleatoric part.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import AleatoricShare, UncertaintyMetric, rescale_aleatoric
from rcvae_torchrl.envs import OBSERVATION_NAMES, resolution_tensor
from rcvae_torchrl.io import load_torch, read_json, save_torch, write_json
from tests.competency.test_assessor import T, make_assessor, make_ensemble, make_env
from tests.competency.test_real_spread import R, _episodes, _outcomes


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
    for bad in (torch.tensor([0.5, 1.5]), torch.tensor([math.nan, 0.5])):
        with pytest.raises(ValueError, match=r"^share: expected shares in \[0, 1\]"):
            rescale_aleatoric(bits, bad)


def _assessor(seed: int = 0, **kwargs):
    """An assessor with as many samples per member as the real runs per start (R)."""
    kwargs.setdefault("episode_end", True)
    return make_assessor(make_env(make_ensemble(seed)), samples_per_member=R, **kwargs)


def _fitted(episode_end: bool = True):
    assessor = _assessor(episode_end=episode_end)
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
    # start 1's runs spread over R bins of dimension 0 at every step: log2 R bits there, start
    # 0's repeat (0 bits); without an episode end the other dimensions repeat: none kept
    if not episode_end:
        torch.testing.assert_close(real.sum(0)[0], torch.tensor(math.log2(R)))
        expected_0 = min(1.0, math.log2(R) / float(imagined.sum(0)[0]))
        assert float(share.share[0]) == pytest.approx(expected_0)
    if not episode_end:
        moving = imagined.sum(0)[1:] > 0
        assert not bool(share.share[1:][moving].any())
    assert unit in report.uncertainty.keys()


def test_a_calibrated_report_keeps_its_forecast_and_says_so():
    _, report, spread, share = _fitted()
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
        f"from 2 other start states, where they spread {float(share.real.sum()):.2f} bits per "
        f"live step and the world model imagined {float(share.imagined.sum()):.2f} aleatoric, "
        f"so it keeps {kept / float(share.imagined.sum()):.0%} of its aleatoric bits"
    ) in share.describe()
    spread_said = calibrated.with_real_spread(spread).summary(0)
    assert "the imagined calibrated aleatoric part" in spread_said
    overall = calibrated.overall()  # over all start states too
    assert share.describe() in overall and "Most of the doubt" in overall
    assert "by chance, or by an error they all make" not in overall
    # a deterministic env's repeated episodes: no aleatoric part is left, all is epistemic
    none = replace(share, share=torch.zeros_like(share.share))
    repeated = report.with_aleatoric_share(none)
    assert not bool(repeated.uncertainty["aleatoric"].any())
    torch.testing.assert_close(repeated.uncertainty["epistemic"], report.uncertainty["total"])
    said = repeated.summary(0)
    assert none.describe() in said
    assert none.describe().endswith(
        "aleatoric, so none of its aleatoric bits count as aleatoric: all are the model's own "
        "error (epistemic)."
    )
    assert "Most of the doubt is epistemic" in said
    assert "spread beyond what the agent's real episodes do" in said
    # the same report indexed keeps its share
    assert report.with_aleatoric_share(share)[0].aleatoric_share is share


def test_a_share_of_another_model_measure_or_report_is_refused():
    _, report, spread, share = _fitted()
    with pytest.raises(ValueError, match=r"^share: this report's split is calibrated already"):
        report.with_aleatoric_share(share).with_aleatoric_share(share)
    other = _assessor(seed=1)
    theirs = other.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    with pytest.raises(ValueError, match=r"^share: fitted for another task than this report's"):
        theirs.with_aleatoric_share(share)
    unended = _assessor(episode_end=False)
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
    coarse = _assessor(bin_width=2 * resolution_tensor())
    wider = coarse.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    with pytest.raises(ValueError, match=r"^spread: measured otherwise than this report's"):
        AleatoricShare.fit(wider, spread)
    # fitted on a calibrated report, every share would read 1: refused
    with pytest.raises(ValueError, match=r"^report: its split is calibrated already"):
        AleatoricShare.fit(report.with_aleatoric_share(share), spread)
    # as many real runs per start as imagined samples per member, and applied at that count
    more = make_assessor(make_env(make_ensemble()), episode_end=True, samples_per_member=2 * R)
    twice = more.assess(_episodes()[:, 0, 0], actions=torch.zeros(T, 2), seed=0)
    with pytest.raises(ValueError, match=rf"^spread: expected {2 * R} real episodes per start st"):
        AleatoricShare.fit(twice, spread)
    with pytest.raises(ValueError, match=r"^share: fitted on bits .*samples_per_member: 4, this"):
        twice.with_aleatoric_share(share)
    # another agent, or the same one acting otherwise
    for field, value in (("agent", "f" * 64), ("acting", "random")):
        mine = replace(report, **{field: value})
        theirs_share = replace(share, **{field: "0" * 64 if field == "agent" else "deterministic"})
        with pytest.raises(ValueError, match=r"^share: fitted on the real episodes of another ag"):
            mine.with_aleatoric_share(theirs_share)
    # a calibrated report and a reference of the model's own split: every rise would be the
    # calibration's; both calibrated alike compare, in the calibrated words
    with pytest.raises(ValueError, match=r"^reference: its split is the world model's own, th"):
        report.with_aleatoric_share(share).with_reference(report)
    with pytest.raises(ValueError, match=r"^reference: its split is calibrated against real e"):
        report.with_reference(report.with_aleatoric_share(share))
    with pytest.raises(ValueError, match=r"^share: this report compares its split with a refer"):
        report.with_reference(report).with_aleatoric_share(share)
    calibrated = report.with_aleatoric_share(share)
    compared = calibrated.with_reference(calibrated[:1])
    assert compared.reference.calibrated is True
    assert "has not seen states like this" not in compared.summary(1)


@pytest.mark.parametrize("kind", ["torch", "json"])
def test_a_share_is_saved_and_read_back(tmp_path, kind):
    _, report, _, share = _fitted()
    if kind == "torch":
        path = save_torch(tmp_path / "share.pt", share.as_dict())
        back = AleatoricShare.from_dict(load_torch(path, "aleatoric share"))
    else:
        write_json(tmp_path / "share.json", share.as_dict())
        back = AleatoricShare.from_dict(read_json(tmp_path / "share.json"))
    for name in ("share", "imagined", "real"):
        torch.testing.assert_close(getattr(back, name), getattr(share, name))
    kept = ("task", "steps", "dim_names", "per_live_step", "samples_per_member", "measure")
    assert {k: getattr(back, k) for k in kept} == {k: getattr(share, k) for k in kept}
    assert back.samples_per_member == R
    torch.testing.assert_close(
        report.with_aleatoric_share(back).uncertainty["aleatoric"],
        report.with_aleatoric_share(share).uncertainty["aleatoric"],
    )
    with pytest.raises(ValueError, match=r"^values: expected the entries .* missing \['task'\]"):
        AleatoricShare.from_dict({k: v for k, v in share.as_dict().items() if k != "task"})
    bad = {**share.as_dict(), "share": (share.share + 2).tolist()}
    with pytest.raises(ValueError, match=r"^share: expected shares in \[0, 1\]"):
        AleatoricShare.from_dict(bad)
    with pytest.raises(TypeError, match=r"^values\['imagined'\]: expected a list of numbers"):
        AleatoricShare.from_dict({**share.as_dict(), "imagined": "junk"})
    # the constructor checks what it is given
    with pytest.raises(ValueError, match=r"^share: expected finite values >= 0, got \[nan"):
        replace(share, share=torch.full_like(share.share, math.nan))
    with pytest.raises(ValueError, match=r"^imagined: expected finite values >= 0, got \[inf"):
        replace(share, imagined=torch.full_like(share.imagined, math.inf))
    edits = [
        ({"start_states": -1}, ValueError, "start_states: expected a positive integer"),
        ({"steps": -3}, ValueError, "steps: expected a positive integer"),
        ({"samples_per_member": 0}, ValueError, "samples_per_member: expected a positive"),
        ({"per_live_step": "no"}, TypeError, "per_live_step: expected True or False"),
        ({"dim_names": ("a",) * 14}, ValueError, "dim_names: expected distinct names"),
    ]
    for change, error, said in edits:
        with pytest.raises(error, match=said):
            replace(share, **change)
    record = share.as_dict()
    for change, error, said in [
        ({"per_live_step": "no"}, TypeError, "per_live_step: expected True or False"),
        ({"start_states": 2.9}, ValueError, "start_states: expected a positive integer"),
        ({"measure": 3}, TypeError, r"values\['measure'\]: expected a mapping"),
        ({"dim_names": None}, TypeError, r"values\['dim_names'\]: expected a list of names"),
    ]:
        with pytest.raises(error, match=said):
            AleatoricShare.from_dict({**record, **change})
    with pytest.raises(ValueError, match=r"^real: expected one value per state dimension \(14 "):
        replace(share, real=torch.zeros(3))


def test_a_share_fitted_where_nothing_was_imagined_describes_itself():
    nothing = AleatoricShare(
        share=torch.ones(2),
        imagined=torch.zeros(2),
        real=torch.zeros(2),
        start_states=3,
        per_live_step=True,
        task="",
        measure={},
        steps=5,
        dim_names=("a", "b"),
    )
    assert nothing.describe() == (
        "The split is calibrated against the agent's real episodes from 3 other start states, "
        "where they spread 0.00 bits per live step and the world model imagined 0.00 aleatoric."
    )
