"""Data-parallel fitting with torch.distributed (docs/design.md *Scale-out*).

Under ``torchrun`` every process draws the same global ray batch from the same seeded generator, renders a
disjoint contiguous share of it, and the gradients are summed over processes with ``all_reduce``. The loss terms
are normalised by global counts, so the summed gradient is the gradient of the single-process loss on the global
batch: a fit on N processes follows the single-process fit step for step, up to summation order. Gloo on CPU,
NCCL on CUDA; rank 0 alone writes the checkpoint, logs and validation images.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class Processes:
    """This process's place in a run: rank in ``0..world_size-1`` and the local rank on its machine."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    def share(self, n: int) -> slice:
        """This rank's contiguous share of ``n`` items (shares differ by at most one item)."""
        return slice(self.rank * n // self.world_size, (self.rank + 1) * n // self.world_size)


SINGLE = Processes()


def from_environment(device: torch.device) -> Processes:
    """The process group that ``torchrun`` describes in the environment (``WORLD_SIZE``, ``RANK``,
    ``LOCAL_RANK``, rendezvous variables), initialised once; a single process without it."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return SINGLE
    processes = Processes(int(os.environ["RANK"]), world_size, int(os.environ.get("LOCAL_RANK", "0")))
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            torch.cuda.set_device(processes.local_rank)
        dist.init_process_group(backend)
    if device.type == "cpu":  # the machine's cores are shared by the processes on it
        local = int(os.environ.get("LOCAL_WORLD_SIZE", str(world_size)))
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // local))
    return processes


def sum_gradients(parameters, processes: Processes) -> None:
    """Sum the gradients of ``parameters`` over all processes (one flat all_reduce). A parameter that no process
    used keeps ``grad = None`` (the optimiser skips it, as a single process would); one used anywhere gets the sum,
    zeros standing in for the processes that did not use it."""
    if not processes.distributed:
        return
    params = list(parameters)
    used = torch.tensor([p.grad is not None for p in params], dtype=params[0].dtype, device=params[0].device)
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params] + [used])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    offset = 0
    for p, anywhere in zip(params, flat[-len(params) :].tolist()):
        p.grad = flat[offset : offset + p.numel()].view_as(p).clone() if anywhere > 0 else None
        offset += p.numel()


def agreed_max(value: float, processes: Processes, device: torch.device) -> float:
    """The largest of every process's ``value``, on every process (time budgets are agreed, never diverge)."""
    if not processes.distributed:
        return value
    shared = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(shared, op=dist.ReduceOp.MAX)
    return float(shared.item())


def any_process(flag: bool, processes: Processes, device: torch.device) -> bool:
    """True on every process if ``flag`` is true on any (stops are agreed, never diverge)."""
    return agreed_max(1.0 if flag else 0.0, processes, device) > 0


def barrier(processes: Processes) -> None:
    if processes.distributed:
        dist.barrier()


def shutdown(processes: Processes, timeout_s: float = 60.0) -> None:
    """Leave the process group together: each process waits until every other has finished (rank 0 may still be
    writing the last checkpoint and the curve) before the group is destroyed, and exits only once every process has
    destroyed its own. Without the second wait, a process that finishes first closes its gloo connections while a
    peer is still tearing down the same group, whose worker threads can then abort it at exit ("terminate called
    without an active exception"). The rendezvous store, which outlives the group, counts the processes out (for at
    most ``timeout_s``). A process that fails instead never reaches this point, and torchrun stops the others."""
    if not (processes.distributed and dist.is_initialized()):
        return
    store = dist.distributed_c10d._get_default_store()
    dist.barrier()
    dist.destroy_process_group()
    store.add(_LEFT, 1)
    deadline = time.monotonic() + timeout_s
    while store.add(_LEFT, 0) < processes.world_size and time.monotonic() < deadline:
        time.sleep(0.01)


#: the store key that counts the processes whose group is destroyed (:func:`shutdown`)
_LEFT = "narf/processes_left"
