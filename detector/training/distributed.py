"""Data-parallel training under ``torchrun``: process-group set-up and the few collectives training needs.

``torchrun --nproc_per_node N $(which detector) train ...`` starts N processes with ``RANK``,
``WORLD_SIZE``, ``LOCAL_RANK`` and ``MASTER_ADDR``/``MASTER_PORT`` set; :func:`setup` reads them and joins
the process group (``gloo`` on CPU, ``nccl`` on CUDA, one GPU per process: ``cuda:LOCAL_RANK``). Without
those variables (a plain ``detector train``) everything here is a no-op for a world of one.

How a distributed run matches a single-process one (see :mod:`detector.stage1.train`): ``batch_size`` stays the
*global* batch, each process takes its share of every batch (:func:`detector.data.batches.rank_share`), the
object-keypoint count that normalises the offset and confidence terms is summed over the processes, and
DDP averages the gradients, so one step of N processes computes the gradient of the same loss over the
same frames as one process (up to floating-point summation order). Only rank 0 writes files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from detector.errors import DetectorError


@dataclass
class DistContext:
    """Where this process stands: ``rank`` of ``world_size``, its device, and whether :func:`setup` created
    the process group (and so :func:`teardown` destroys it)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    owns_group: bool = False

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        """Wait for all processes (no-op for a world of one)."""
        if self.enabled:
            dist.barrier()

    def sum_(self, t: torch.Tensor) -> torch.Tensor:
        """In-place sum of ``t`` over the processes; returns ``t``."""
        if self.enabled:
            dist.all_reduce(t, op=dist.ReduceOp.SUM)
        return t

    def mean_of(self, values: dict[str, float]) -> dict[str, float]:
        """The mean over the processes of each float of ``values`` (same keys on every process)."""
        if not self.enabled:
            return values
        keys = sorted(values)
        t = torch.tensor([values[k] for k in keys], dtype=torch.float64)
        if dist.get_backend() == "nccl":
            t = t.cuda()
        self.sum_(t)
        return {k: float(v) / self.world_size for k, v in zip(keys, t.tolist())}


def env_world() -> tuple[int, int, int]:
    """(rank, world_size, local_rank) from torchrun's environment; (0, 1, 0) without it."""
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local = int(os.environ.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise DetectorError("WORLD_SIZE, RANK and LOCAL_RANK must be integers (set by torchrun)") from None
    if world < 1 or not 0 <= rank < world:
        raise DetectorError(f"RANK {rank} is not in a world of WORLD_SIZE {world}")
    return rank, world, local


def setup(device: str = "auto") -> DistContext:
    """Join the process group that torchrun's environment describes (idempotent); a world of one otherwise.

    device: the run's ``auto | cpu | cuda``; CUDA (when chosen or available under ``auto``) uses ``nccl``
    and pins this process to ``cuda:LOCAL_RANK``, CPU uses ``gloo``.
    """
    rank, world, local = env_world()
    if world == 1:
        return DistContext()
    if dist.is_initialized():
        return DistContext(dist.get_rank(), dist.get_world_size(), local, owns_group=False)
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if use_cuda:
        if local >= torch.cuda.device_count():
            raise DetectorError(f"LOCAL_RANK {local} has no GPU ({torch.cuda.device_count()} visible); "
                                f"start at most one process per GPU")
        torch.cuda.set_device(local)
    dist.init_process_group(backend="nccl" if use_cuda else "gloo")
    return DistContext(rank, world, local, owns_group=True)


def teardown(ctx: DistContext) -> None:
    """Leave the process group if :func:`setup` created it."""
    if ctx.owns_group and dist.is_initialized():
        dist.destroy_process_group()
