"""A run under torch.distributed takes another run's finished stage (``reuse_from``)."""

import torch
import workers
from _ranks import run_ranks


def test_ranks_take_the_stage_rank_0_reused(tmp_path):
    first, second = tmp_path / "first", tmp_path / "second"
    run_ranks(workers.staged, str(first), None, str(tmp_path / "first{rank}.pt"))
    run_ranks(workers.staged, str(second), str(first), str(tmp_path / "second{rank}.pt"))
    done = [torch.load(tmp_path / f"second{rank}.pt") for rank in (0, 1)]
    # make's file came from the first run on rank 0; use ran on both ranks (its setting differs)
    assert [d["called"] for d in done] == [["use"], ["use"]]
    assert all(d["summaries"]["make"]["n"] == 4 for d in done)
    assert all(d["summaries"]["use"]["total"] == 6.0 for d in done)
    assert (second / "a.pt").stat().st_ino == (first / "a.pt").stat().st_ino
    assert [torch.load(tmp_path / f"first{rank}.pt")["called"] for rank in (0, 1)] == [
        ["make", "use"],
        ["use"],
    ]
