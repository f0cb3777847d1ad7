"""The threads that run a frame's independent geometry side by side: ICP's starts
(:func:`detector.geometry.icp.refine_poses`) and stage 2's poses from its crops
(:class:`detector.stage2.poser.CropPoser`). Their heavy parts (open3d's ICP, scipy's tree queries, numpy's matrix
products and SVDs) release the GIL, so two cores finish them sooner than one. Each piece's result is the same as
run alone: nothing random is drawn inside a thread, and open3d runs one thread inside each ICP."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

#: Most threads in the pool.
MAX_THREADS = 4

_POOL: list[ThreadPoolExecutor] = []


def worker_pool() -> ThreadPoolExecutor:
    """The process's pool of threads for geometry: as many as the CPU has cores, at most ``MAX_THREADS``."""
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(max(1, min(MAX_THREADS, os.cpu_count() or 1)), thread_name_prefix="geometry"))
    return _POOL[0]


def map_threads(fn, items) -> list:
    """``[fn(x) for x in items]`` (a callable, an iterable), in their order, run on :func:`worker_pool`'s threads
    when there are two or more."""
    items = list(items)
    return list(worker_pool().map(fn, items)) if len(items) > 1 else [fn(x) for x in items]
