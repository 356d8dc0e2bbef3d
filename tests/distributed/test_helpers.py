"""rcvae_torchrl.distributed without a process group, and its pure helpers."""

import numpy as np
import pytest
import torch

from rcvae_torchrl import distributed


@pytest.mark.parametrize(("n", "world"), [(4, 2), (7, 3), (2, 5), (0, 2), (9, 1)])
def test_shards_cover_the_range_in_rank_order(n, world):
    blocks = [distributed.shard(n, r, world) for r in range(world)]
    assert [i for b in blocks for i in b] == list(range(n))
    assert max(map(len, blocks)) - min(map(len, blocks)) <= 1


def test_shard_errors():
    with pytest.raises(ValueError, match="n: expected a non-negative int, got -1"):
        distributed.shard(-1, 0, 1)
    with pytest.raises(ValueError, match="expected 0 <= rank < world, got 2, 2"):
        distributed.shard(4, 2, 2)
    for rank, world in ((True, 2), (0.5, 2), (0, 2.0)):
        with pytest.raises(ValueError, match="rank, world: expected ints"):
            distributed.shard(3, rank, world)
    with pytest.raises(ValueError, match="backend: expected 'gloo', 'nccl' or None, got 'mpi'"):
        distributed.init("mpi")


def test_without_a_group_this_is_the_only_rank(monkeypatch):
    monkeypatch.delenv("RANK", raising=False)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert (distributed.rank(), distributed.world_size(), distributed.is_main()) == (0, 1, True)
    assert not distributed.is_active() and not distributed.init()
    assert distributed.all_gather({"a": 1}) == [{"a": 1}] and distributed.broadcast(3) == 3
    assert distributed.shard(5) == range(5)
    distributed.barrier()
    distributed.teardown()
    monkeypatch.setenv("RANK", "3")
    monkeypatch.setenv("WORLD_SIZE", "4")
    assert (distributed.rank(), distributed.world_size(), distributed.is_main()) == (3, 4, False)
    for name, text in (("WORLD_SIZE", "abc"), ("WORLD_SIZE", "0"), ("RANK", "-1")):
        monkeypatch.setenv(name, text)
        with pytest.raises(ValueError, match=rf"^{name}: expected an integer >= \d in the env"):
            distributed.world_size() if name == "WORLD_SIZE" else distributed.rank()
        monkeypatch.setenv(name, "3" if name == "RANK" else "4")


def test_work_generators_depend_on_their_keys_alone():
    draw = lambda *keys: torch.rand(4, generator=distributed.work_generator(*keys))  # noqa: E731
    assert torch.equal(draw(0, 1, 2), draw(0, 1, 2))
    assert not torch.equal(draw(0, 1, 2), draw(0, 2, 1))
    assert not torch.equal(draw(0, 1), draw(1, 0))
    with pytest.raises(ValueError, match="keys: expected one or more non-negative ints"):
        distributed.work_generator(-1)


def test_without_a_group_one_process_is_the_only_replica():
    assert distributed.replicas(1) == distributed.Replicas(0, 1, 0, 1)
    assert distributed.replicas(4) == distributed.Replicas(0, 1, 0, 1)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="size: expected a positive int"):
            distributed.replicas(bad)


def test_a_launcher_s_rank_outside_its_world_is_refused(monkeypatch):
    """``RANK=5 WORLD_SIZE=2`` gave rank 5, and ``RANK=1`` alone a rank 1 of a world of 1 that
    is not main and so never wrote."""
    monkeypatch.setenv("RANK", "5")
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match=r"^RANK, WORLD_SIZE: expected RANK < WORLD_SIZE .*'5'"):
        distributed.rank()
    with pytest.raises(ValueError, match=r"^RANK, WORLD_SIZE: expected RANK < WORLD_SIZE"):
        distributed.is_main()
    monkeypatch.setenv("RANK", "1")
    assert (distributed.rank(), distributed.world_size()) == (1, 2)
    monkeypatch.delenv("WORLD_SIZE")
    with pytest.raises(ValueError, match=r"^RANK, WORLD_SIZE: RANK is '1' .* WORLD_SIZE is not"):
        distributed.rank()
    monkeypatch.delenv("RANK")
    monkeypatch.setenv("WORLD_SIZE", "2")  # RANK unset: rank 0, as before
    assert distributed.rank() == 0


def test_numpy_integers_are_taken_where_ints_are():
    assert distributed.shard(np.int64(5), np.int64(1), np.int32(2)) == range(3, 5)
    draw = lambda *keys: torch.rand(4, generator=distributed.work_generator(*keys))  # noqa: E731
    assert torch.equal(draw(np.int64(3), np.uint8(1)), draw(3, 1))
    assert distributed.replicas(np.int64(2)) == distributed.Replicas(0, 1, 0, 1)
    for bad in (np.float64(1.0), np.bool_(True)):
        with pytest.raises(ValueError, match="keys: expected one or more non-negative ints"):
            distributed.work_generator(bad)


def test_a_work_generator_names_a_bad_device():
    with pytest.raises(ValueError, match=r"^device: expected a torch device .* got 'foo'"):
        distributed.work_generator(1, device="foo")
    assert distributed.work_generator(1, device=torch.device("cpu")).device.type == "cpu"
