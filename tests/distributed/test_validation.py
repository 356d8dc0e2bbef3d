"""Real episodes shared out over 2 gloo ranks give the serial run's outcomes."""

import torch
import workers
from _ranks import run_ranks


def test_parallel_real_outcomes_equal_serial(tmp_path):
    serial = workers.outcomes()
    assert serial.success.shape == (3, 3) and serial.trace.shape == (3, 3, 25)
    assert not torch.equal(serial.trace[:, 0], serial.trace[:, 1])  # runs have their own noise
    run_ranks(workers.outcomes, str(tmp_path / "out{rank}.pt"))
    for rank in (0, 1):  # 9 episodes: rank 0 runs 5, rank 1 runs 4; both hold all 9
        gathered = torch.load(tmp_path / f"out{rank}.pt")
        assert gathered.keys() == serial.as_dict().keys()
        for name, value in serial.as_dict().items():
            torch.testing.assert_close(gathered[name], value, rtol=0, atol=0, equal_nan=True)
