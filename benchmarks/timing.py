"""Wall-clock timing shared by the benchmark scripts (run as ``python benchmarks/<name>.py``, which puts
this folder on ``sys.path``)."""
from __future__ import annotations

import statistics
import time

import torch


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA); nothing on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device: torch.device, repeats: int) -> float:
    """Median milliseconds of ``repeats`` synchronised calls of ``fn()``, after one warm-up call
    (kernel compilation, JIT)."""
    fn()
    sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def per_call_us(fn, device: torch.device, calls: int, blocks: int, now=time.perf_counter) -> float:
    """Microseconds per call of the fastest of ``blocks`` blocks of ``calls`` calls, one
    synchronisation per block (so queued GPU work overlaps the host, as in a training loop), after
    ``max(20, calls // 10)`` warm-up calls. ``now``: the clock (CPU time suits a shared CPU)."""
    for _ in range(max(20, calls // 10)):
        fn()
    sync(device)
    best = float("inf")
    for _ in range(blocks):
        t0 = now()
        for _ in range(calls):
            fn()
        sync(device)
        best = min(best, (now() - t0) / calls * 1e6)
    return best


def cuda_kernel_ms(fn, calls: int = 5) -> dict:
    """GPU milliseconds per call of each CUDA kernel ``fn`` launches (torch profiler, after three
    warm-up calls), by kernel name."""
    from torch.profiler import ProfilerActivity, profile

    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as p:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize()
    per: dict = {}
    for e in p.events():
        if e.device_type.name == "CUDA":
            per[e.name] = per.get(e.name, 0.0) + e.device_time / calls / 1e3
    return per
