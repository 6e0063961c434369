import pytest

from dapm_lightning.data.samplers import EpochShuffleSampler


def keys(sampler):
    return list(sampler)


def test_order_is_a_function_of_seed_and_epoch_and_carries_the_epoch():
    a, b = EpochShuffleSampler(10, seed=3), EpochShuffleSampler(10, seed=3)
    a.set_epoch(1), b.set_epoch(1)
    assert keys(a) == keys(b) and {epoch for epoch, _ in keys(a)} == {1}
    assert sorted(i for _, i in keys(a)) == list(range(10))
    b.set_epoch(2)
    assert [i for _, i in keys(a)] != [i for _, i in keys(b)]


@pytest.mark.parametrize("length", [10, 11])
def test_processes_partition_the_one_global_order(length):
    single = EpochShuffleSampler(length, seed=1)
    ranks = [EpochShuffleSampler(length, seed=1, num_replicas=2, rank=r) for r in (0, 1)]
    for sampler in (single, *ranks):
        sampler.set_epoch(4)
    usable = [i for _, i in keys(single)][: length - length % 2]
    assert [i for _, i in keys(ranks[0])] == usable[0::2] and [i for _, i in keys(ranks[1])] == usable[1::2]
    assert all(len(r) == len(keys(r)) == length // 2 for r in ranks)


def test_resume_skips_the_global_position_on_every_rank():
    full = [EpochShuffleSampler(16, seed=2, num_replicas=2, rank=r) for r in (0, 1)]
    resumed = [EpochShuffleSampler(16, seed=2, num_replicas=2, rank=r) for r in (0, 1)]
    for sampler in (*full, *resumed):
        sampler.set_epoch(1)
    for sampler in resumed:
        sampler.resume(epoch=1, samples_seen=6)  # 3 batches of 2 per... 6 samples of both ranks together
    for f, r in zip(full, resumed):
        assert keys(r) == keys(f)[3:] and len(r) == 8  # __len__ stays the whole epoch's
    for sampler in resumed:
        sampler.set_epoch(2)  # the next epoch is whole again
        assert len(keys(sampler)) == 8


def test_evaluation_order_keeps_every_sample_once():
    ranks = [EpochShuffleSampler(7, num_replicas=2, rank=r, shuffle=False, drop_last=False) for r in (0, 1)]
    assert sorted(i for r in ranks for _, i in keys(r)) == list(range(7))
    assert [len(r) for r in ranks] == [4, 3]


def test_an_evaluation_process_without_a_sample_counts_one_and_yields_none():
    """So that Lightning runs its evaluation loop (and collectives) there too: it skips a process with no batch."""
    ranks = [EpochShuffleSampler(1, num_replicas=2, rank=r, shuffle=False, drop_last=False) for r in (0, 1)]
    assert [keys(r) for r in ranks] == [[(0, 0)], []] and [len(r) for r in ranks] == [1, 1]
    assert len(EpochShuffleSampler(0, num_replicas=2, rank=1, shuffle=False, drop_last=False)) == 0  # none anywhere
    assert len(EpochShuffleSampler(1, num_replicas=2, rank=1)) == 0  # training: the tail is dropped


def test_resume_sets_the_epoch_before_lightning_does():
    """Loader workers prefetch as soon as the resumed loader's iterator exists, before Lightning's set_epoch."""
    sampler = EpochShuffleSampler(8, seed=2)
    sampler.resume(epoch=3, samples_seen=2)
    assert {epoch for epoch, _ in keys(sampler)} == {3} and len(keys(sampler)) == 6


def test_no_two_seeds_share_an_order_in_any_epoch():
    """The order of (seed, epoch) is not that of another seed in another epoch (seed 1 epoch 0 vs seed 0 epoch 1)."""
    orders = set()
    for seed in range(4):
        for epoch in range(4):
            sampler = EpochShuffleSampler(12, seed=seed)
            sampler.set_epoch(epoch)
            orders.add(tuple(i for _, i in keys(sampler)))
    assert len(orders) == 16


def test_a_position_between_ranks_resumes_each_rank_on_its_own_share():
    """Resumed at a position that is not a multiple of the processes: rounded down, no rank takes another's keys."""
    full = [EpochShuffleSampler(16, seed=2, num_replicas=2, rank=r) for r in (0, 1)]
    resumed = [EpochShuffleSampler(16, seed=2, num_replicas=2, rank=r) for r in (0, 1)]
    for sampler in full:
        sampler.set_epoch(1)
    for sampler in resumed:
        sampler.resume(epoch=1, samples_seen=7)
    for f, r in zip(full, resumed):
        assert keys(r) == keys(f)[3:]
