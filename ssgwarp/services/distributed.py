"""Data-parallel training through ``torch.distributed`` (launched by ``torchrun``).

``torchrun --nproc_per_node N -m ssgwarp reconstruct ...`` starts N processes with ``RANK``,
``WORLD_SIZE``, ``LOCAL_RANK`` and a rendezvous address in their environment;
:func:`from_env` joins them into one process group (NCCL on CUDA, each rank on
``cuda:LOCAL_RANK``; gloo on the CPU). Every rank holds the whole scene and its Adam state;
a training step's batch of views is split between the ranks, each renders and back-propagates
its share, and the :class:`Group` methods below make the ranks agree:

* :meth:`Group.average_grads`: the gradients of every parameter summed across ranks (one flat
  all-reduce) and divided by the world size, so each rank steps with the gradient of the loss
  averaged over the whole batch; a few host flags (Ctrl-C on any rank) ride along as extra
  elements, so all ranks stop at the same step;
* :meth:`Group.reduce_stats`: densification statistics gathered from every rank's views
  (sums for gradient norms and counts, maxima for screen radii), so every rank takes the same
  densify / prune decisions;
* :meth:`Group.check_identical`: a checksum of the scene, its Adam state and statistics
  compared across ranks (debug: every ``SSGWARP_DDP_CHECK`` steps).

Outside ``torchrun`` (or with one process) :data:`SINGLE` is used: every method is a no-op, so
a plain run is unchanged. Only the main rank (0) writes files and shows progress.
"""
from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from ..errors import InputError, SsgwarpError

CHECK_ENV = "SSGWARP_DDP_CHECK"  # steps between cross-rank scene checksums (0 / unset: never)


@dataclass(frozen=True)
class Group:
    """This process's place among the training processes (world size 1: alone)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: Optional[str] = None

    @property
    def is_main(self) -> bool:
        """True on the rank that writes outputs, checkpoints and progress."""
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world_size > 1

    def share(self, items: Sequence) -> list:
        """This rank's contiguous share of a global batch (its length must divide by the world size)."""
        n = len(items)
        if n % self.world_size:
            raise InputError(f"a batch of {n} views cannot be split evenly between {self.world_size} processes; "
                             f"make --batch-size a multiple of the number of processes")
        b = n // self.world_size
        return list(items[self.rank * b:(self.rank + 1) * b])

    # -- collectives (no-ops alone) ------------------------------------------------------------
    def average_grads(self, params: Sequence[torch.Tensor], flags: Sequence[float] = ()) -> list[float]:
        """Replace each parameter's ``.grad`` by its mean over the ranks; return ``flags`` summed over ranks.

        Parameters whose ``.grad`` is None are skipped (the same on every rank: every rank renders
        at the same SH degree with the same hooks). The flags are float host values packed in the
        same all-reduce (no extra round trip)."""
        if not self.active:
            return [float(f) for f in flags]
        import torch.distributed as dist

        grads = [p.grad for p in params if p.grad is not None]
        dev = params[0].device
        parts = [g.reshape(-1).to(torch.float32) for g in grads]
        parts.append(torch.tensor([float(f) for f in flags], dtype=torch.float32, device=dev))
        flat = torch.cat(parts)
        dist.all_reduce(flat)
        n = flat.numel() - len(flags)
        body = flat[:n] / self.world_size
        off = 0
        for g in grads:
            k = g.numel()
            g.copy_(body[off:off + k].view_as(g))
            off += k
        return flat[n:].tolist()

    def reduce_stats(self, stats: dict[str, torch.Tensor], ops: dict[str, str]) -> None:
        """Combine per-rank statistics in place: ``ops[name]`` is ``"sum"`` (default) or ``"max"``."""
        if not self.active or not stats:
            return
        import torch.distributed as dist

        for op in ("sum", "max"):
            names = [k for k in sorted(stats) if ops.get(k, "sum") == op]
            if not names:
                continue
            flat = torch.cat([stats[k].reshape(-1).to(torch.float32) for k in names])
            dist.all_reduce(flat, op=dist.ReduceOp.SUM if op == "sum" else dist.ReduceOp.MAX)
            off = 0
            for k in names:
                v = stats[k]
                v.copy_(flat[off:off + v.numel()].view_as(v))
                off += v.numel()

    def check_identical(self, named: dict[str, torch.Tensor], step: int) -> None:
        """Raise :class:`SsgwarpError` unless every tensor in ``named`` is the same on every rank.

        Compares, per tensor, its row count and three float64 checksums (sum, sum of squares and a
        position-weighted sum, which catches permuted rows) gathered from all ranks; equal tensors
        give bitwise equal checksums."""
        if not self.active:
            return
        import torch.distributed as dist

        keys = sorted(named)
        rows = []
        for k in keys:
            v = named[k].detach().reshape(-1).to(torch.float64)
            w = torch.arange(1, v.numel() + 1, dtype=torch.float64, device=v.device)
            rows.append(torch.stack([torch.tensor(float(v.numel()), dtype=torch.float64, device=v.device),
                                     v.sum(), (v * v).sum(), (v * w).sum()]))
        mine = torch.stack(rows) if rows else torch.zeros(0, 4, dtype=torch.float64)
        everyone = [torch.empty_like(mine) for _ in range(self.world_size)]
        dist.all_gather(everyone, mine)
        for r, theirs in enumerate(everyone):
            diff = (theirs != everyone[0]).any(dim=1)
            if bool(diff.any()):
                bad = [keys[i] for i in torch.nonzero(diff)[:, 0].tolist()]
                raise SsgwarpError(f"step {step}: rank {r}'s {', '.join(bad)} differ from rank 0's: the ranks' "
                                   f"scenes diverged (report this with the command line)")

    def gather(self, value: float) -> list[float]:
        """``value`` from every rank, in rank order (alone: ``[value]``)."""
        if not self.active:
            return [float(value)]
        import torch.distributed as dist

        dev = torch.device("cuda", torch.cuda.current_device()) if self.backend == "nccl" else torch.device("cpu")
        mine = torch.tensor([float(value)], dtype=torch.float64, device=dev)
        everyone = [torch.empty_like(mine) for _ in range(self.world_size)]
        dist.all_gather(everyone, mine)
        return [float(v) for v in everyone]

    def barrier(self) -> None:
        if self.active:
            import torch.distributed as dist

            dist.barrier()

    def broadcast(self, obj):
        """``obj`` as rank 0 has it (any picklable object)."""
        if not self.active:
            return obj
        import torch.distributed as dist

        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]


SINGLE = Group()


def launched() -> bool:
    """True inside a ``torchrun`` launch of more than one process."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def check_every() -> int:
    """Steps between cross-rank checksums (``SSGWARP_DDP_CHECK``; 0: off)."""
    v = os.environ.get(CHECK_ENV, "0").strip() or "0"
    try:
        k = int(v)
    except ValueError:
        raise InputError(f"{CHECK_ENV}={v!r}: expected a number of steps") from None
    return max(0, k)


def from_env(device: Optional[torch.device] = None, timeout_s: float = 1800.0) -> tuple[Group, torch.device]:
    """Join the process group ``torchrun`` describes in the environment.

    Returns ``(group, device)``: the device this rank trains on (``cuda:LOCAL_RANK`` when
    ``device`` is CUDA or None and CUDA is available, else the CPU) and the group. Alone (no
    ``torchrun``, or one process) returns ``(SINGLE, device)`` and starts nothing."""
    if device is None:
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(device)
    if not launched():
        return SINGLE, device
    import torch.distributed as dist

    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    local = int(os.environ.get("LOCAL_RANK", rank))
    if device.type == "cuda":
        if local >= torch.cuda.device_count():
            raise InputError(f"process {rank} has LOCAL_RANK {local} but this machine has "
                             f"{torch.cuda.device_count()} CUDA device(s); use --nproc_per_node <= that")
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
        backend = "nccl"
    else:
        backend = "gloo"
    if not dist.is_initialized():
        kw = {"device_id": device} if backend == "nccl" else {}
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s), **kw)
    return Group(rank=rank, world_size=world, local_rank=local, backend=backend), device


_LEFT = False  # set once this process has torn down a real process group


def shutdown(group: Group) -> None:
    """Leave the process group (no-op alone)."""
    global _LEFT
    if group.active:
        import torch.distributed as dist

        if dist.is_initialized():
            dist.destroy_process_group()
            _LEFT = True


def exit_after_group(code: int) -> None:
    """End a process that has left a process group (under torchrun) with ``code``, skipping the
    interpreter's teardown; does nothing in a process that never joined one.

    Measured on the 2-core CPU machine (gloo, 2026-11-23): in about 1 run in 8 under load, a rank
    that had finished, written everything and destroyed its process group still died at interpreter
    exit with "terminate called without an active exception" (SIGABRT), because gloo's network and
    worker threads, kept alive on torch's C++ side after ``destroy_process_group``, were torn down
    with the interpreter; torchrun then reports the whole run as failed. Everything a stage writes
    is written atomically and closed before this point, so the process flushes its streams and
    leaves with ``os._exit``.
    """
    if not _LEFT:
        return
    import sys

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001  (a closed stream: nothing left to say)
            pass
    os._exit(code)
