"""Batching shared by the trainers: stacking items, the endless stream of (epoch, frame) batches that a resumed run
continues exactly, and each DDP process's share of a global batch."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch

from detector.errors import DetectorError


def collate(items: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack a list of items into a batch: every key gains a leading batch dimension."""
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def rank_share(batch_size: int, rank: int, world_size: int) -> slice:
    """The part of a global batch of ``batch_size`` keys that process ``rank`` of ``world_size`` takes.

    Returns a slice of ``batch_size // world_size`` consecutive positions; a batch size that the world
    size does not divide is a :class:`DetectorError`.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} is not in a world of {world_size}")
    if batch_size % world_size:
        raise DetectorError(f"batch_size {batch_size} is not divisible by the {world_size} distributed processes; "
                            f"choose a multiple of {world_size}")
    per = batch_size // world_size
    return slice(rank * per, (rank + 1) * per)


class StreamBatchSampler(torch.utils.data.Sampler):
    """An endless stream of batches of ``(epoch, frame)`` keys, starting at batch ``start``.

    Epoch ``e`` visits the frames in the order ``default_rng([seed, e]).permutation(num_frames)``; batches
    are consecutive runs of ``batch_size`` keys of this stream (they may span an epoch boundary), so batch
    ``b`` is the same whether the run started at 0 or was resumed at ``b``. With ``world_size`` > 1 (DDP)
    process ``rank`` yields its :func:`rank_share` of each global batch: together the processes see the
    keys one process would.
    """

    def __init__(self, num_frames: int, batch_size: int, seed: int, start: int = 0, rank: int = 0,
                 world_size: int = 1):
        self.num_frames, self.batch_size, self.seed, self.start = num_frames, batch_size, seed, start
        self.share = rank_share(batch_size, rank, world_size)

    def keys(self, first: int, count: int) -> list[tuple[int, int]]:
        """Keys at stream positions ``first .. first + count - 1``."""
        out, pos = [], first
        while len(out) < count:
            epoch, j = divmod(pos, self.num_frames)
            perm = np.random.default_rng([self.seed, epoch]).permutation(self.num_frames)
            take = min(count - len(out), self.num_frames - j)
            out += [(epoch, int(i)) for i in perm[j:j + take]]
            pos += take
        return out

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        b = self.start
        while True:
            yield self.keys(b * self.batch_size + self.share.start, self.share.stop - self.share.start)
            b += 1

    def __len__(self) -> int:  # endless; a large number keeps DataLoader happy
        return 2**62
