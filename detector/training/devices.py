"""Devices and data-loader plumbing shared by the trainers: the torch device of a run, the loader workers'
thread count, and the loaders' own generators."""

from __future__ import annotations

import torch

from detector.errors import DetectorError


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda when available else cpu; asking for cuda without one is a DetectorError."""
    if name == "cuda" and not torch.cuda.is_available():
        raise DetectorError("--device cuda: no CUDA device is available")
    return torch.device("cuda" if name == "cuda" or (name == "auto" and torch.cuda.is_available()) else "cpu")


def worker_init(_: int) -> None:
    torch.set_num_threads(1)


def loader_generator(seed: int) -> torch.Generator:
    """A DataLoader's own generator: creating an iterator would otherwise draw from torch's global generator
    and shift the dropout stream of a resumed run (the items are keyed by (seed, epoch, frame), not seeded by it)."""
    return torch.Generator().manual_seed(seed)
