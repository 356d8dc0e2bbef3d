"""Real episodes shared out over 2 gloo ranks give the serial run's outcomes, one env at a time
and in a batched env."""

import torch
import workers
from _ranks import run_ranks


def test_parallel_real_outcomes_equal_serial(tmp_path):
    serial = workers.outcomes()
    one_env, batched = serial["one_env"], serial["batched"]
    assert one_env.success.shape == (3, 3) and one_env.trace.shape == (3, 3, 25)
    assert batched.success.shape == (2, 3) and batched.trace.shape == (2, 3, 40)
    for runs in (one_env, batched):  # the runs of a start have their own noise
        assert not torch.equal(runs.trace[:, 0], runs.trace[:, 1])
    run_ranks(workers.outcomes, str(tmp_path / "out{rank}.pt"))
    for rank in (0, 1):  # rank 0 runs the first block of episodes, rank 1 the rest
        gathered = torch.load(tmp_path / f"out{rank}.pt")
        for kind, outcomes in serial.items():
            assert gathered[kind].keys() == outcomes.as_dict().keys()
            for name, value in outcomes.as_dict().items():
                if isinstance(value, str):  # what is known of the agent and the predicates
                    assert gathered[kind][name] == value, name
                    continue
                torch.testing.assert_close(
                    gathered[kind][name], value, rtol=0, atol=0, equal_nan=True, msg=name
                )
