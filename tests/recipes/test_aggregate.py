"""The multi-seed aggregate: mean ± sd per column and check, and seeds counted per check."""

from __future__ import annotations

import json
import math

import pytest
import torch

from rcvae_torchrl.io import write_json
from recipes.pusher_competency.aggregate import aggregate, main, markdown


def _summary(gap: float, met: bool) -> dict:
    row = {"aleatoric_bits": 1.0, "epistemic_bits": 2.0}
    scores = {"forecast": 0.5 + gap, "real": 0.5, "gap": gap, "spearman": 0.7}
    return {
        "rows": {"stochastic": row},
        "validation": {"stochastic": scores, "overall": dict(scores)},
        "checks": {"a check": {"value": gap, "met": met}},
    }


def test_mean_sd_and_counts():
    result = aggregate({"seed0": _summary(0.02, True), "seed1": _summary(0.06, False)})
    gap = result["table"]["stochastic"]["gap"]
    assert gap["mean"] == pytest.approx(0.04) and gap["sd"] == pytest.approx(0.02 * 2**0.5)
    assert result["checks"]["a check"]["met"] == 1 and result["checks"]["a check"]["seeds"] == 2
    mean_gap = result["checks"]["mean |forecast - real| over seeds <= 0.05 (stochastic)"]
    assert mean_gap["mean"] == pytest.approx(0.04) and mean_gap["met"] == 1


def test_the_command_writes_both_files(tmp_path):
    for i, gap in enumerate((0.01, 0.2)):
        (tmp_path / f"seed{i}").mkdir()
        (tmp_path / f"seed{i}" / "summary.json").write_text(json.dumps(_summary(gap, gap < 0.1)))
    main([str(tmp_path)])
    text = (tmp_path / "aggregate.md").read_text()
    assert "over 2 seeds" in text and "| a check | 0.105 ± 0.134 | 1/2 |" in text
    assert json.loads((tmp_path / "aggregate.json").read_text())["seeds"] == ["seed0", "seed1"]
    with pytest.raises(SystemExit, match="directory: expected seed"):
        main([str(tmp_path / "seed0")])


def test_a_check_counts_only_the_seeds_it_applied_to():
    # seed0 made no "own rate" check (every real episode agreed); seed1 made one and met it.
    first, second = _summary(0.02, True), _summary(0.06, True)
    second["checks"]["own rate"] = {"value": 0.3, "met": True}
    result = aggregate({"seed0": first, "seed1": second})
    own = result["checks"]["own rate"]
    assert (own["met"], own["seeds"], own["mean"]) == (1, 1, pytest.approx(0.3))
    assert list(result["checks"])[:2] == ["a check", "own rate"]


def test_nested_scores_are_aggregated():
    first, second = _summary(0.02, True), _summary(0.06, True)
    for s, gap in ((first, 0.01), (second, 0.03)):
        s["validation"]["stochastic"]["recalibrated"] = {"gap": gap}
        mapped = {"gap": 2 * gap, "forecast": 0.5 - 2 * gap}  # too pessimistic after the map
        s["validation"]["stochastic"]["recalibrated_held_out"] = mapped
    result = aggregate({"seed0": first, "seed1": second})
    assert result["table"]["stochastic"]["recalibrated.gap"]["mean"] == pytest.approx(0.02)
    held_out = result["table"]["stochastic"]["recalibrated_held_out.gap"]
    assert held_out["mean"] == pytest.approx(0.04)
    # the mean gap over seeds through each seed's held-out map, beside the forecast's own
    name = "mean |forecast - real| over seeds <= 0.05 through the held-out map (stochastic)"
    through = result["checks"][name]
    assert through["mean"] == pytest.approx(0.04) and through["met"] == 1
    assert through["signed_mean"] == pytest.approx(-0.04)
    assert result["checks"]["mean |forecast - real| over seeds <= 0.05 (stochastic)"]["met"] == 1
    second["validation"]["stochastic"].pop("recalibrated_held_out")  # one seed without a map
    assert name not in aggregate({"seed0": first, "seed1": second})["checks"]
    assert "recalibrated.gap" not in result["table"]["overall"]
    assert "recalibrated_held_out.gap" not in result["table"]["overall"]


def test_every_seed_has_its_value_and_verdict(tmp_path):
    # seed1 misses "a check"; "own rate" applied to seed1 only
    first, second = _summary(0.02, True), _summary(0.2, False)
    second["checks"]["own rate"] = {"value": 0.3, "met": True}
    for name, summary in (("seed0", first), ("seed1", second)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps(summary))
    result = main([str(tmp_path)])
    assert result["checks"]["own rate"]["by_seed"] == [None, {"value": 0.3, "met": True}]
    text = (tmp_path / "aggregate.md").read_text()
    every = text[text.index("## Every seed") :]
    assert "| check | seed0 | seed1 |" in every
    assert "| a check | 0.020 | 0.200 ✗ |" in every
    assert "| own rate | – | 0.300 |" in every
    assert "over seeds" not in every  # the checks over all seeds have no per-seed value
    assert r"| mean \|forecast - real\| over seeds <= 0.05 (stochastic) | 0.110 | 0/1 |" in text


def _seeds(root, count, settings=lambda i: {"train": {"max_steps": 10}, "seed": i}):
    for i in range(count):
        (root / f"seed{i}").mkdir(parents=True)
        (root / f"seed{i}" / "summary.json").write_text(json.dumps(_summary(0.05, True)))
        (root / f"seed{i}" / "study_config.json").write_text(json.dumps(settings(i)))


def test_unfinished_foreign_and_damaged_seeds_are_refused_by_name(tmp_path):
    _seeds(tmp_path, 2)
    main([str(tmp_path)])  # the same settings but the seed: aggregated
    (tmp_path / "seed2").mkdir()  # a run that crashed before its summary
    with pytest.raises(SystemExit, match=r"\['seed2'\] under .* hold no summary.json"):
        main([str(tmp_path)])
    assert not (tmp_path / "aggregate.md").exists()  # the old table does not look current
    (tmp_path / "seed2").rmdir()
    (tmp_path / "seed1" / "study_config.json").write_text(json.dumps({"train": {}, "seed": 1}))
    with pytest.raises(SystemExit, match=r"seed1: made with other settings than seed0 .*'train'"):
        main([str(tmp_path)])
    (tmp_path / "seed1" / "study_config.json").write_text(json.dumps({"train": {"max_steps": 10}}))
    (tmp_path / "seed1" / "summary.json").write_text("[]")
    with pytest.raises(SystemExit, match=r"seed1/summary.json: expected a study summary"):
        main([str(tmp_path)])
    # a run writes its summary checksummed: read as it is, refused by name once edited
    write_json(tmp_path / "seed1" / "summary.json", _summary(0.05, False), checksum=True)
    assert main([str(tmp_path)])["checks"]["a check"]["met"] == 1
    edited = json.loads((tmp_path / "seed1" / "summary.json").read_text())
    edited["checks"]["a check"]["met"] = True
    (tmp_path / "seed1" / "summary.json").write_text(json.dumps(edited))
    with pytest.raises(SystemExit, match=r"seed1/summary.json'?: its content changed since"):
        main([str(tmp_path)])


def test_the_held_out_forecast_checks_are_counted_over_the_seeds_that_made_them(tmp_path):
    def held_out(gap: float, passed: bool) -> dict:
        return {"stochastic": {"gap": gap, "passed": passed}}

    first, second, third = _summary(0.02, True), _summary(0.04, True), _summary(0.03, True)
    first["forecast_checks"] = held_out(-0.12, False)
    second["forecast_checks"] = held_out(-0.02, True)  # the third run made none
    result = aggregate({"seed0": first, "seed1": second, "seed2": third})
    found = result["forecast_checks"]["stochastic"]
    assert found["biased"] == 1 and found["seeds"] == 2
    assert found["mean"] == pytest.approx(-0.07)
    assert found["by_seed"] == [
        {"gap": -0.12, "passed": False, "verdict": "too pessimistic"},
        {"gap": -0.02, "passed": True, "verdict": "passed"},
        None,
    ]
    text = markdown(result)
    assert "## The forecasts from start states they are not scored on" in text
    assert found["shared"] is None  # two seeds: too few to test what they share
    row = "| stochastic | -0.070 ± 0.071 | – (fewer than 3 seeds) | 1/2 | 1/2 | -0.120 ✗ | -0.020 |"
    assert row in text
    assert aggregate({"seed0": third})["forecast_checks"] == {}


def test_a_bias_every_seed_shares_is_found_though_each_check_passed():
    """Five seeds whose own checks all passed, each 0.06-0.10 too optimistic: the t-test of
    their gaps names the shared bias (closed form); gaps that scatter about 0 share none."""
    from scipy.stats import t as student

    gaps = [0.06, 0.07, 0.08, 0.09, 0.10]
    runs = {f"seed{i}": _summary(0.02, True) for i in range(5)}
    for name, gap in zip(runs, gaps, strict=True):
        runs[name]["forecast_checks"] = {"ood": {"gap": gap, "passed": True, "alpha": 0.01}}
    shared = aggregate(runs)["forecast_checks"]["ood"]["shared"]
    # mean 0.08, sd 0.0158 over 5 seeds: t = 0.08 / (0.0158 / sqrt 5) = 11.31, 4 dof
    expected = 2 * student.sf(0.08 / (0.025**0.5 / 10 / 5**0.5), 4)
    assert shared["p_value"] == pytest.approx(expected, rel=1e-6) and expected < 0.001
    assert shared["verdict"] == "too optimistic" and shared["seeds"] == 5
    assert "| ood | 0.080 ± 0.016 | too optimistic (p = 0.00035) ✗ | 0/5 | 0/5 |" in markdown(
        aggregate(runs)
    )
    for name, gap in zip(runs, [-0.05, 0.03, 0.0, 0.04, -0.02], strict=True):
        runs[name]["forecast_checks"]["ood"]["gap"] = gap
    assert aggregate(runs)["forecast_checks"]["ood"]["shared"]["verdict"] == "none found"


def test_a_forecast_check_that_measured_nothing_is_not_counted_biased():
    """A trial's 2-seed quick study: seed 0's out-of-distribution check was 'not measured'
    (94 of 100 starts settled, its gap left blank in its report), and the aggregate showed
    its gap with a ✗ and counted it biased."""
    from rcvae_torchrl.training import OutcomeCheck

    settled = torch.ones(20, 1, dtype=torch.bool)
    unmeasured = OutcomeCheck.from_outcomes(torch.full((20,), 0.9995), settled).as_dict()
    g = torch.Generator().manual_seed(0)
    real = torch.rand(30, 5, generator=g) < 0.3
    biased = OutcomeCheck.from_outcomes(torch.full((30,), 0.8), real).as_dict()
    runs = {f"seed{i}": _summary(0.02, True) for i in range(2)}
    runs["seed0"]["forecast_checks"] = {"out-of-distribution": unmeasured}
    runs["seed1"]["forecast_checks"] = {"out-of-distribution": biased}
    found = aggregate(runs)["forecast_checks"]["out-of-distribution"]
    assert [x["verdict"] for x in found["by_seed"]] == ["not measured", "too optimistic"]
    assert found["biased"] == 1 and found["not_passed"] == 2 and found["seeds"] == 2
    assert found["mean"] == pytest.approx(biased["gap"])  # the unmeasured gap left out
    text = markdown(aggregate(runs))
    assert f"| 1/2 | 2/2 | not measured ? | {biased['gap']:+.3f} ✗ |" in text


def test_the_pattern_per_live_step_over_the_seeds_that_kept_it():
    def pattern(ale_sto: float, epi_ood: float, ale_ood: float) -> dict:
        return {
            "1s": {},
            "per live step": {
                "aleatoric_stochastic_over_deterministic": ale_sto,
                "epistemic_ood_over_deterministic": epi_ood,
                "aleatoric_ood_over_deterministic": ale_ood,
            },
        }

    first, second, third = _summary(0.02, True), _summary(0.04, True), _summary(0.03, True)
    first["pattern_by_window"] = pattern(1.0, 0.9, 1.1)
    second["pattern_by_window"] = pattern(1.2, 1.1, 1.0)  # the third kept none
    result = aggregate({"seed0": first, "seed1": second, "seed2": third})
    live = result["pattern_per_live_step"]
    assert live["aleatoric_stochastic_over_deterministic"]["mean"] == pytest.approx(1.1)
    assert live["epistemic_ood_over_deterministic"]["by_seed"] == [0.9, 1.1, None]
    text = markdown(result)
    assert "## The pattern per live step" in text
    assert (
        "| aleatoric out-of-distribution / deterministic | 1.050 ± 0.071 | 1.10 | 1.00 | – |"
        in text
    )
    assert aggregate({"seed0": third})["pattern_per_live_step"] == {}
    assert "per live step" not in markdown(aggregate({"seed0": third}))


def test_the_novelty_cautions_are_summed_over_the_seeds_that_made_the_check():
    def rows(cautioned: int) -> dict:
        return {
            "out-of-distribution": {
                "starts": 100,
                "start_unlike": cautioned,
                "cautioned": cautioned,
            }
        }

    first, second, third = _summary(0.02, True), _summary(0.04, True), _summary(0.03, True)
    first["novelty"], third["novelty"] = rows(5), rows(21)  # the second run's models had none
    result = aggregate({"seed0": first, "seed1": second, "seed2": third})
    found = result["novelty"]["out-of-distribution"]
    assert (found["cautioned"], found["starts"], found["seeds"]) == (26, 200, 2)
    assert found["by_seed"] == [5, None, 21]
    text = markdown(result)
    assert "## Start states unlike the training states" in text
    assert "| out-of-distribution | 26 of 200 | 5 | – | 21 |" in text
    assert aggregate({"seed0": second})["novelty"] == {}


def test_a_mean_over_fewer_seeds_than_the_study_says_over_how_many():
    from recipes._aggregate import cell as _cell
    from recipes._aggregate import stats as _stats

    assert _cell(_stats([float("nan"), -1.263])) == "-1.263 (of 1 seed)"
    assert _cell(_stats([0.1, 0.3, None])) == "0.200 ± 0.141 (of 2 seeds)"
    assert _cell(_stats([0.1, 0.3])) == "0.200 ± 0.141"
    assert _cell(_stats([float("nan")])) == "n/a"
    assert _cell(_stats([math.inf, math.inf])) == "inf"  # a rise from 0 bits in every seed
    assert _cell(_stats([math.inf, float("nan")])) == "n/a"


def test_the_point_mass_study_over_seeds_with_its_word_checks_and_outcome_checks(tmp_path):
    """The template's aggregate: its rows' columns, checks whose value is a word (a cause, a
    verdict) counted by seeds met with no mean, and the outcome checks by their verdicts."""
    from recipes.point_mass_competency.aggregate import main as point_mass

    for i, (gap, verdict) in enumerate(((0.02, "passed"), (0.12, "not measured"))):
        run = tmp_path / f"seed{i}"
        run.mkdir()
        summary = {
            "rows": {"stochastic": {"gap": gap, "auroc": 0.8, "aleatoric_bits": 3.0}},
            "checks": {
                "|forecast - real| <= 0.10 (stochastic)": {"value": gap, "met": gap <= 0.1},
                "outcome check passed (stochastic)": {"value": verdict, "met": i == 0},
            },
            "forecast_checks": {"stochastic": {"gap": -gap, "passed": i == 0, "verdict": verdict}},
        }
        (run / "summary.json").write_text(json.dumps(summary))
        (run / "study_config.json").write_text(json.dumps({"seed": i, "task": {"kp": 20}}))
    result = point_mass([str(tmp_path)])
    assert result["table"]["stochastic"]["gap"]["mean"] == pytest.approx(0.07)
    text = (tmp_path / "aggregate.md").read_text()
    assert "# Point-mass competency study over 2 seeds (seed0, seed1)" in text
    assert "| \\|forecast - real\\| <= 0.10 (stochastic) | 0.070 ± 0.071 | 1/2 |" in text
    assert "| outcome check passed (stochastic) |  | 1/2 |" in text  # a word: no mean
    assert "| outcome check passed (stochastic) | passed | not measured ✗ |" in text
    row = "| stochastic | -0.020 | – (fewer than 3 seeds) | 0/2 | 1/2 | -0.020 | not measured ? |"
    assert row in text
    with pytest.raises(SystemExit, match=r"expected a study summary \(a mapping with 'checks' and"):
        (tmp_path / "seed1" / "summary.json").write_text(json.dumps({"rows": {}}))
        point_mass([str(tmp_path)])


def test_seeds_are_in_the_order_of_their_numbers(tmp_path):
    for seed in (10, 2, 1, 0):
        (tmp_path / f"seed{seed}").mkdir()
        summary = json.dumps(_summary(0.01 * seed, True))
        (tmp_path / f"seed{seed}" / "summary.json").write_text(summary)
    main([str(tmp_path)])
    seeds = json.loads((tmp_path / "aggregate.json").read_text())["seeds"]
    assert seeds == ["seed0", "seed1", "seed2", "seed10"]  # not seed10 before seed2
    assert "| check | seed0 | seed1 | seed2 | seed10 |" in (tmp_path / "aggregate.md").read_text()
