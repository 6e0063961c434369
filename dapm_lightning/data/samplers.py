"""The training order: a permutation of (seed, epoch), split across processes, that can resume mid-epoch.

Lightning's own mid-epoch resume needs ``torchdata``'s ``StatefulDataLoader`` (another dependency, whose
worker-state snapshots cost a round trip per batch); this sampler needs only the global position, which
the data module saves in every checkpoint.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import DistributedSampler

from dapm_lightning.data.sample import SampleKey


class EpochShuffleSampler(DistributedSampler[SampleKey]):
    """Yields ``(epoch, index)`` keys: the order is a function of (seed, epoch), the epoch seeds each augmentation.

    The epoch travels with every index, so loader workers (persistent ones included) augment each
    epoch differently without being told the epoch. Under DDP every process takes every
    ``num_replicas``-th key of the one global permutation, so a subclass of ``DistributedSampler`` is
    used as is by Lightning (it wraps other samplers). :meth:`resume` skips the first samples of the
    global order, so a run restarted mid-epoch sees what the uninterrupted one would.

    Args:
        length: size of the data set.
        seed: order seed.
        num_replicas, rank: processes and this one's rank (1 and 0 outside DDP).
        shuffle: ``False`` keeps the data set order (evaluation).
        drop_last: drop the tail that does not divide among processes (training); ``False`` gives the
            first ranks one sample more instead (evaluation: every sample exactly once, none repeated; a
            process without a sample still counts one, see :meth:`__len__`).
    """

    def __init__(self, length: int, seed: int = 0, *, num_replicas: int = 1, rank: int = 0, shuffle: bool = True,
                 drop_last: bool = True) -> None:
        if not 0 <= rank < num_replicas:
            raise ValueError(f"rank {rank} is not in [0, {num_replicas})")
        super().__init__(range(length), num_replicas=num_replicas, rank=rank, shuffle=shuffle, seed=seed,
                         drop_last=drop_last)
        self.length = length
        self.skip_epoch, self.skip_samples = -1, 0

    def resume(self, epoch: int, samples_seen: int) -> None:
        """Skip the first ``samples_seen`` samples of the global order of ``epoch`` (all processes together).

        Also sets the epoch: loader workers prefetch from the sampler as soon as Lightning builds the
        resumed loader's iterator, which can come before its ``set_epoch`` call.
        """
        self.skip_epoch, self.skip_samples = epoch, samples_seen
        self.set_epoch(epoch)

    def _global_order(self) -> list[int]:
        if self.shuffle:
            generator = torch.Generator().manual_seed(self.seed * 100003 + self.epoch)
            order = torch.randperm(self.length, generator=generator).tolist()
        else:
            order = list(range(self.length))
        if self.drop_last:
            order = order[:self.length - self.length % self.num_replicas]
        return order

    def __iter__(self) -> Iterator[SampleKey]:
        order = self._global_order()
        if self.epoch == self.skip_epoch:  # the data module resumes at whole global batches: multiples already
            order = order[self.skip_samples - self.skip_samples % self.num_replicas:]
        return iter([(self.epoch, index) for index in order[self.rank::self.num_replicas]])

    def __len__(self) -> int:
        """Keys per process in a whole epoch (a resumed epoch yields fewer; Lightning counts on from where it was).

        Without ``drop_last``, 1 for a process left without a sample (fewer samples than processes), which yields
        none: Lightning skips the evaluation loop of a process with no batch, and the others would wait for its
        share of the collectives (metrics, logs, callbacks); counted as one, its loop runs and ends at once.
        """
        if self.drop_last:
            return self.length // self.num_replicas
        return max(len(range(self.rank, self.length, self.num_replicas)), min(self.length, 1))
