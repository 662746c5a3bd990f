"""Data parallelism for `art-guidance train` under `torchrun` (torch.distributed).

Every process builds the same global batch (the batch draw is seeded by the step), keeps its
contiguous share of the rows, and divides its sums of squared errors by the counts of the
*global* batch; summing the gradients over processes (all-reduce) then gives exactly the
single-process gradient, up to floating-point reduction order. Dropout masks are drawn per
process (seeded by seed, step and rank), so with dropout > 0 a data-parallel run is the same
training in distribution but not in its random draws. NCCL on GPUs, gloo on CPU.
Without torchrun (no WORLD_SIZE in the environment) everything runs in one process.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

import numpy as np
import torch
import torch.distributed as dist


@dataclass(frozen=True)
class DistContext:
    """This process's place in the job.

    Attributes:
        rank, world_size, local_rank: as set by torchrun (0, 1, 0 without it).
        device: cuda:<local_rank> when CUDA is available, else cpu.
    """

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        """Rank 0 writes checkpoints and shows the progress bar."""
        return self.rank == 0

    def share(self, rows: np.ndarray) -> np.ndarray:
        """This process's contiguous share of a global batch's rows."""
        return np.array_split(rows, self.world_size)[self.rank]

    def sum(self, values: list[float]) -> list[float]:
        """Element-wise sum of `values` over all processes (float64)."""
        if self.world_size == 1:
            return list(values)
        t = torch.tensor(values, dtype=torch.float64, device=self._comm_device)
        dist.all_reduce(t)
        return t.tolist()

    def sum_gradients(self, params: list[torch.nn.Parameter]) -> None:
        """Replace every gradient by its sum over all processes (one flat all-reduce)."""
        if self.world_size == 1:
            return
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        offset = 0
        for p in params:
            n = p.numel()
            p.grad = flat[offset:offset + n].view_as(p).clone()
            offset += n

    def barrier(self) -> None:
        """Wait for every process (no-op alone)."""
        if self.world_size > 1:
            dist.barrier()

    @property
    def _comm_device(self) -> torch.device:
        return self.device if dist.get_backend() == "nccl" else torch.device("cpu")


def init_distributed(device: str | None = None) -> DistContext:
    """Join the torchrun job if there is one (NCCL with CUDA, gloo otherwise).

    Args:
        device: force "cpu" or "cuda" (default: CUDA when available).
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = torch.cuda.is_available() if device is None else device.startswith("cuda")
    dev = torch.device(f"cuda:{local}" if use_cuda else "cpu")
    if use_cuda:
        torch.cuda.set_device(dev)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo", rank=rank, world_size=world,
                                timeout=timedelta(minutes=30))
    return DistContext(rank, world, local, dev)


def shutdown_distributed() -> None:
    """Leave the process group (no-op alone)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
