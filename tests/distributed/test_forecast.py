"""The forecast sharded over 2 gloo ranks equals the single-process report under the seed."""

import pytest
import torch
import workers
from _ranks import run_ranks


@pytest.fixture(scope="module")
def single_process():
    assessor = workers.make_assessor()
    return assessor.assess(workers.forecast_starts(), policy=workers.policy, seed=5).data


def _assert_equal(a, b):
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), key


def test_sharded_forecast_equals_single_process(tmp_path, single_process):
    run_ranks(workers.forecast, str(tmp_path / "report{rank}.pt"), 5)
    for rank in (0, 1):
        saved = torch.load(tmp_path / f"report{rank}.pt", weights_only=False)
        _assert_equal(saved["data"], single_process)
        assert saved["error"].startswith("seed: an assessment sharded over torch.distributed")
    # one start (one chunk) for two ranks: rank 0 says that rank 1 gets no work
    idle = torch.load(tmp_path / "report0.pt", weights_only=False)["idle"]
    assert idle == [
        "start_chunk: 1 start states in chunks of 2 make 1 for 2 ranks, which share out "
        "chunks: 1 of them get no work; give start_chunk=1 or less (the forecasts then draw "
        "other noise: a chunk's seed is its own)"
    ]
    assert torch.load(tmp_path / "report1.pt", weights_only=False)["idle"] == []
    assert single_process.batch_size == (7,)  # 4 chunks of 2: ranks take chunks 0-1 and 2-3
    p = single_process["competency", "p_success"]
    assert ((p > 0) & (p < 1)).any() and (p == 0).any()  # outcomes that differ by start


def test_the_seed_decides_the_noise(single_process):
    other = workers.make_assessor().assess(workers.forecast_starts(), policy=workers.policy, seed=6)
    p, q = single_process["competency", "p_success"], other.data["competency", "p_success"]
    assert not torch.equal(single_process["per_sample", "x"], other.data["per_sample", "x"])
    assert p.shape == q.shape == (7,)


def test_seed_and_generator_exclude_each_other():
    with pytest.raises(ValueError, match="seed, generator: expected at most one"):
        workers.make_assessor().assess(
            workers.forecast_starts(),
            policy=workers.policy,
            seed=1,
            generator=torch.Generator().manual_seed(1),
        )
