"""Independent jobs side by side over parts of the ranks (3 gloo ranks: parts of 2 and 1)."""

import numpy as np
import pytest
import torch
import workers
from _ranks import run_ranks

from rcvae_torchrl import distributed
from rcvae_torchrl.training import train_ensemble

pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")


def test_each_part_trains_its_ensemble_as_a_single_process_would(tmp_path):
    out = str(tmp_path / "out")
    run_ranks(workers.train_in_parts, out, world=3)
    seen = [torch.load(f"{out}.rank{r}") for r in range(3)]
    # ranks 0 and 1 form part 0, rank 2 part 1; the helpers act within the part
    assert [s["part"] for s in seen] == [(0, 2), (0, 2), (1, 2)]
    # every rank enters its part once all have made the groups (rank 0 came 0.5 s late): a rank
    # that left a group while a peer still connected to it broke the peer's connect
    assert min(s["entered"] for s in seen) >= seen[0]["arrived"]
    assert [(s["rank"], s["world"]) for s in seen] == [(0, 2), (1, 2), (0, 1)]
    assert [s["gathered"] for s in seen] == [[0, 1], [0, 1], [2]]
    assert [s["broadcast"] for s in seen] == [1, 1, 2]  # the part's last rank's
    assert "within parts" in seen[0]["replicas"] and seen[2]["replicas"] is None
    assert [s["after"] for s in seen] == [(0, 3), (1, 3), (2, 3)]  # all the ranks again
    assert [s["alone"] for s in seen] == [(0, 1, False, [r], r, (0, 1)) for r in range(3)]
    for s in seen:
        assert s["errors"] == [
            "n: expected at most the number of ranks, 3, got 4",
            "parts: already within parts of the ranks (parts do not nest)",
        ]
    train, val = workers.linear_data()
    for part in (0, 1):
        alone = train_ensemble(
            workers.small_ensemble(seed=part), train, val, workers.CONFIG, progress=False,
            checks=False,
        )  # fmt: skip
        weights = torch.load(f"{out}.part{part}")
        for name, value in alone.ensemble.state_dict().items():
            assert torch.equal(weights[name], value), (part, name)


def test_without_a_group_the_one_process_is_the_only_part():
    with distributed.parts(3) as part:
        assert part == distributed.Part(0, 1)
        assert (distributed.rank(), distributed.world_size()) == (0, 1)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="n: expected a positive int"):
            with distributed.parts(bad):
                pass


def test_parts_do_not_nest_in_a_single_process_either():
    """A nested ``parts`` passed on one process and failed under torchrun (its docstring says
    it raises): the one process refuses it too, and the block leaves nothing behind."""
    with distributed.parts(2):
        with pytest.raises(ValueError, match=r"^parts: already within parts of the ranks"):
            with distributed.parts(1):
                pass
        with distributed.alone(), pytest.raises(ValueError, match=r"parts do not nest"):
            with distributed.parts(1):
                pass
    with distributed.parts(np.int64(2)) as part:  # and again after the block
        assert part == distributed.Part(0, 1)
    with pytest.raises(KeyError), distributed.parts(1):
        raise KeyError("inside")
    with distributed.parts(1):  # an error inside left nothing behind
        pass


def test_a_resumed_job_runs_on_the_part_it_ran_on(tmp_path):
    """Job ``b`` of ``[a, b]`` runs on part 1 (rank 1 alone) also when ``a`` is done: resumed
    after a kill, its checkpoint is one rank's, as before (with 2 jobs missing or 1)."""
    (tmp_path / "stage").mkdir()
    (tmp_path / "stage" / "a.pt").write_bytes(b"done")
    out = str(tmp_path / "out")
    run_ranks(workers.jobs_over_ranks, str(tmp_path), out)
    seen = [torch.load(f"{out}.rank{r}") for r in range(2)]
    assert [s["ran"] for s in seen] == [[], ["b"]]
    for s in seen:
        assert s["results"] == {"b": "b on 0 of 1"} and s["elsewhere"] == ["b"]
