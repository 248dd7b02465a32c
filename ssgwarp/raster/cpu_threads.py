"""The CPU kernels on several cores: one launch per thread, each over a run of whole tiles (blending)
or of elements (the per-Gaussian and per-intersection kernels).

Warp's CPU backend runs a launch's threads one after the other on the calling core. The blending
kernels (forward and backward) are almost all of a CPU render's time, and their launches hold no
Python lock (a ctypes call releases the GIL), so :func:`run` issues one launch per thread from a
small pool, each covering a run of whole tiles (the kernels' ``first`` argument). Tiles are cut so
that every run holds about the same work (:func:`split`: intersections of its tiles plus a
per-tile constant), which follows the scene instead of the image's area.

How many threads (:func:`count`): ``RasterSettings.cpu_threads``, by default
``torch.get_num_threads()`` (so ``OMP_NUM_THREADS`` and ``torch.set_num_threads`` govern it as they
govern torch), at most one per tile, and only as many as the work pays for (:data:`MIN_WORK`: a
launch on another thread costs tens of microseconds). One thread is the single launch of before.

The per-element kernels (projection and its adjoint, SH colours and theirs, the tile binning's key
writes and range offsets, the blending's gather) split their index range into equal runs
(:func:`ranges`, at least :data:`MIN_ITEMS` elements a thread), with the same ``first`` argument:
each element is computed by one thread with the same operations and written to its own slots, so
their results are bit-identical for any number of threads.

What stays the same: every pixel is computed by one thread with the same operations, so images
are bit-identical for any number of threads; the deterministic backward's per-intersection slots
belong to one tile each, so its gradients are bit-identical too. The default backward adds into
per-Gaussian rows: each thread gets its own rows (its own zeroed buffer), summed afterwards, so
its gradients differ from one thread's by the rounding of that summation order only.
"""
from __future__ import annotations

import concurrent.futures as cf
import os
import threading
from functools import partial
from typing import Callable

import torch

from . import launch as L

# pixel-intersection pairs (tile intersections x pixels of a tile) each thread needs: with less, one
# more thread costs more than it saves (2-core machine, idle, forward+backward: 2 threads 1.4x slower
# at 13,000 pairs, 1.1x faster at 35,000; docs/notes/benchmarks-history.md "Blending on several CPU cores")
MIN_WORK = 15_000
# elements each thread of a per-element kernel needs: a launch on another thread costs ~30-60 us on
# the 2-core machine; a projected Gaussian ~80 ns, a Gaussian's key writes ~10-20 ns (lego_200, 2026-11-23)
MIN_ITEMS = 4096
# the same for kernels of a few ns an element (the binning's range offsets, one per intersection)
MIN_ITEMS_LIGHT = 8 * MIN_ITEMS
# an empty tile's cost in intersections (its pixels are still read and written)
TILE_COST = 2
# the default backward's extra per-thread gradient buffers: at most this many bytes in all
MAX_EXTRA_BYTES = 512 * 2**20

_POOL: cf.ThreadPoolExecutor | None = None
_POOL_KEY = (0, 0)  # (process id, workers): a forked child makes its own pool
_LOCK = threading.Lock()


def wanted(cpu_threads: int | None) -> int:
    """The threads asked for: ``cpu_threads`` or, when None, ``torch.get_num_threads()``."""
    return max(1, int(cpu_threads) if cpu_threads is not None else torch.get_num_threads())


def count(cpu_threads: int | None, n_ranges: int, n_isects: int, tile_pixels: int) -> int:
    """Threads for a blending launch over ``n_ranges`` tiles (cameras x tiles) holding ``n_isects``
    intersections of ``tile_pixels`` pixels each: :func:`wanted`, at most one per tile and one per
    :data:`MIN_WORK` pixel-intersection pairs."""
    work = (n_isects + TILE_COST * n_ranges) * tile_pixels
    return max(1, min(wanted(cpu_threads), n_ranges, work // MIN_WORK))


def ranges(cpu_threads: int | None, n: int, min_items: int | None = None) -> list[tuple[int, int]]:
    """``[(first, end), ...]``: ``n`` elements cut into equal consecutive, non-empty runs, one per
    thread (:func:`wanted`, at most one per ``min_items`` elements, default :data:`MIN_ITEMS`);
    ``[(0, n)]`` for one."""
    per = MIN_ITEMS if min_items is None else min_items
    if n < 2 * per:  # (one run whatever the threads: the common small case without asking torch)
        return [(0, n)]
    parts = max(1, min(wanted(cpu_threads), n // max(1, per)))
    cuts = [n * i // parts for i in range(parts + 1)]
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a] or [(0, n)]


def element_runs(tg, cpu_threads: int | None, n: int, min_items: int | None = None) -> list[tuple[int, int]]:
    """The runs of ``n`` elements that a per-element kernel's launches on target ``tg`` cover: on
    the CPU :func:`ranges` (one per thread), on CUDA one."""
    return ranges(cpu_threads, n, min_items) if tg.cpu else [(0, n)]


def launch_runs(kern, lead: tuple, runs: list[tuple[int, int]], args: list, tg, adj: list | None = None) -> None:
    """``kern`` over ``(*lead, end - first)`` for each run ``(first, end)`` of its last dimension,
    side by side (:func:`run`), ``first`` appended to ``args`` as the kernel's last parameter (and 0
    to ``adj``, that parameter's adjoint, for an adjoint launch; :func:`ssgwarp.raster.launch.launch`)."""
    if len(runs) == 1:  # (one run, as on CUDA: launched here, without the thread machinery)
        (a, b), = runs
        L.launch(kern, (*lead, b - a), args + [a], tg, None if adj is None else adj + [0])
        return
    run([partial(L.launch, kern, (*lead, b - a), args + [a], tg, None if adj is None else adj + [0])
         for a, b in runs])


def split(offsets: torch.Tensor, n_ranges: int, parts: int) -> list[tuple[int, int]]:
    """``[(first, end), ...]``: up to ``parts`` consecutive, non-empty runs of the ``n_ranges`` tile
    ranges covering them all, cut where the cumulative cost (intersections, ``offsets [n_ranges+1]``
    their CPU start offsets, plus :data:`TILE_COST` per tile) crosses ``i / parts`` of the total."""
    if parts <= 1 or n_ranges <= 1:
        return [(0, n_ranges)]
    cum = offsets[:n_ranges + 1].to(torch.int64) + TILE_COST * torch.arange(n_ranges + 1, dtype=torch.int64)
    total = int(cum[-1])
    targets = torch.tensor([total * i // parts for i in range(1, parts)], dtype=torch.int64)
    cuts = torch.searchsorted(cum, targets).clamp_(1, n_ranges - 1).tolist()
    bounds = [0] + sorted(set(cuts)) + [n_ranges]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def merge(parts: list, n: int) -> list:
    """``parts`` (consecutive runs of tiles) merged into ``n`` consecutive runs of about equally many."""
    if n >= len(parts):
        return parts
    cuts = [round(i * len(parts) / n) for i in range(n + 1)]
    return [(parts[cuts[i]][0], parts[cuts[i + 1] - 1][1]) for i in range(n)]


def extra_buffers(parts: int, row_bytes: int, rows: int) -> int:
    """How many of ``parts`` threads of the default backward may run, each but the first with its
    own gradient buffer of ``rows`` rows of ``row_bytes``, within :data:`MAX_EXTRA_BYTES`."""
    per = max(1, row_bytes * rows)
    return max(1, min(parts, 1 + MAX_EXTRA_BYTES // per))


def _pool(workers: int) -> cf.ThreadPoolExecutor:
    global _POOL, _POOL_KEY
    key = (os.getpid(), workers)
    with _LOCK:
        if _POOL is None or _POOL_KEY[0] != key[0] or _POOL_KEY[1] < workers:
            old = _POOL if _POOL is not None and _POOL_KEY[0] == key[0] else None
            _POOL, _POOL_KEY = cf.ThreadPoolExecutor(workers, thread_name_prefix="ssgwarp-blend"), key
            if old is not None:
                old.shutdown(wait=False)
        return _POOL


def run(calls: list[Callable[[], None]]) -> None:
    """Run ``calls[0]`` on this thread and the others on the pool, and return once all have
    finished. The launches write into tensors the caller holds, so this waits for every one also
    when interrupted (Ctrl-C) or when one fails, then raises the first error."""
    if len(calls) == 1:
        calls[0]()
        return
    futures = [_pool(len(calls) - 1).submit(c) for c in calls[1:]]
    err: BaseException | None = None
    try:
        calls[0]()
    except BaseException as e:  # noqa: BLE001 - re-raised below, after the other launches end
        err = e
    for f in futures:
        while not f.done():
            try:
                cf.wait([f])
            except KeyboardInterrupt as e:
                err = err or e
        if err is None and f.exception() is not None:
            err = f.exception()
    if err is not None:
        raise err
