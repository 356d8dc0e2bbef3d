"""The arithmetic of ``benchmarks/scaling.py``'s training-by-members summary."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from scaling import members_summary


def test_fixed_and_per_member_costs_come_from_a_line_through_the_medians():
    times = {1: [0.75, 0.74, 0.9], 2: [1.0, 1.1, 0.99], 4: [1.5, 1.4, 1.5]}  # 0.5 + 0.25 m
    summary = members_summary(times, t1=1.5, t2=1.1)
    assert summary["fixed_s"] == pytest.approx(0.5)
    assert summary["per_member_s"] == pytest.approx(0.25)
    assert summary["speedup_ceiling_alone"] == pytest.approx(1.5)
    assert summary["side_by_side_over_alone"] == pytest.approx(1.1)
    # (t1 - x) / (t2 - x) = 1.7 at x = (1.7 t2 - t1) / 0.7
    x = summary["fixed_to_remove_for_1.7x_s"]
    assert (1.5 - x) / (1.1 - x) == pytest.approx(1.7)
    assert members_summary(times, t1=2.0, t2=1.0)["fixed_to_remove_for_1.7x_s"] == 0.0


def test_interleaved_rounds_join_in_order():
    from scaling import join_rounds

    rounds = [
        {
            "times": [2.0],
            "cpu_by_rank": [[1.9], [1.8]],
            "gather_bytes": 10,
            "gather_s": 0.5,
            "probe": {"payload_s": 0.2, "latency_s": 0.1},
        },
        {
            "times": [3.0],
            "cpu_by_rank": [[2.9], [2.8]],
            "gather_bytes": 10,
            "gather_s": 0.1,
            "probe": {"payload_s": 0.4, "latency_s": 0.3},
        },
    ]
    joined = join_rounds(rounds)
    assert joined["times"] == [2.0, 3.0]
    assert joined["cpu_by_rank"] == [[1.9, 2.9], [1.8, 2.8]]
    assert joined["gather_bytes"] == 10 and joined["gather_s"] == pytest.approx(0.3)
    assert joined["probe"] == pytest.approx({"payload_s": 0.3, "latency_s": 0.2})
    one_rank = [{**r, "cpu_by_rank": r["cpu_by_rank"][:1], "probe": None} for r in rounds]
    assert join_rounds(one_rank)["probe"] is None


def test_each_round_has_its_own_speedup():
    from scaling import round_speedups

    assert round_speedups([4.0, 3.0], [2.0, 2.5]) == pytest.approx([2.0, 1.2])
    with pytest.raises(ValueError, match="one 2-rank time per round"):
        round_speedups([4.0], [2.0, 2.5])
