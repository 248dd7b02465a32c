"""What one more host operation costs inside a forward+backward call (not in a tight loop).

A tight loop keeps the interpreter's and torch's code and data in the CPU's caches; inside a call of the
rasterizer they are not, and the same operation costs several times more. This probe inserts ``--extra``
operations of one kind into each call (before the binning, where the host runs between launches), times
forward+backward calls synchronised one by one with and without them, in interleaved rounds, and prints
the difference of the medians per operation, beside the same operation's cost in a tight loop. It also
splits the forward around the one read-back (host time before it, the wait, host time after).

    python benchmarks/op_costs.py                    # CUDA, 10k Gaussians at 256x256
    python benchmarks/op_costs.py --device cpu --rounds 2
    python benchmarks/op_costs.py --gaussians 100000 --width 1920 --height 1080

Differences of medians of ~1.4 ms calls: read them to +-3 µs.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
import timeit
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).parent))
from raster import camera, make_scene  # noqa: E402

import ssgwarp  # noqa: E402
from ssgwarp.raster import launch as L  # noqa: E402
from ssgwarp.raster import ops  # noqa: E402


@wp.kernel
def nothing(a: wp.array(dtype=wp.int32)):
    """A kernel that does no work: what remains is the launch's own cost."""
    i = wp.tid()
    if i < 0:
        a[0] = 1


def operations(buf: torch.Tensor, n: int) -> dict:
    """One operation of each kind, as a function of no arguments."""
    dev, tg = buf.device, L.target(buf)
    return {
        "torch.empty": lambda: torch.empty(n, dtype=torch.int32, device=dev),
        "slice": lambda: buf[:n],
        "view": lambda: buf.view(-1, 16),
        "split_with_sizes": lambda: buf.split_with_sizes((n, buf.numel() - n)),
        "Warp launch (recorded, empty kernel)": lambda: L.launch(nothing, 1, [*L.arr(buf)], tg),
        "launch.zeros (memset)": lambda: L.zeros((n,), torch.int32, tg),
        "launch.arr (a descriptor)": lambda: L.arr(buf),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--gaussians", type=int, default=10_000)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--extra", type=int, default=10, help="operations inserted per call")
    ap.add_argument("--rounds", type=int, default=16)
    ap.add_argument("--calls", type=int, default=20, help="calls per variant per round")
    args = ap.parse_args(argv)
    if min(args.extra, args.rounds, args.calls, args.gaussians) < 1:
        raise SystemExit("op_costs.py: --extra, --rounds, --calls and --gaussians must be at least 1")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("op_costs.py: no CUDA device here (use --device cpu)")
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    now = time.perf_counter
    n, w, h = args.gaussians, args.width, args.height
    leaves = [p.clone().requires_grad_(True) for p in make_scene(n, device)]
    vm, K = camera(w, h, device)
    buf = torch.empty(max(1 << 16, 2 * n), dtype=torch.int32, device=device)
    ops_by_kind = operations(buf, min(n, buf.numel() // 2))
    state = {"op": None, "k": 0}
    marks: dict = {}
    bin_tiles, start, finish = ops.bin_tiles, L.start_read_int64, L.finish_read_int64

    def probed_bin_tiles(*a, **kw):
        op = state["op"]
        for _ in range(state["k"]):
            op()
        return bin_tiles(*a, **kw)

    def timed_start(*a):
        marks["start"] = now()
        return start(*a)

    def timed_finish(*a):
        v = finish(*a)
        marks["finish"] = now()
        return v

    ops.bin_tiles, L.start_read_int64, L.finish_read_int64 = probed_bin_tiles, timed_start, timed_finish

    def one():
        for p in leaves:
            p.grad = None
        sync()
        t0 = now()
        img, alpha, _ = ssgwarp.rasterization(*leaves, vm, K, w, h, tile_size=16)
        t1 = now()
        (img.sum() + alpha.sum()).backward()
        sync()
        t2 = now()
        return t2 - t0, marks["start"] - t0, marks["finish"] - marks["start"], t1 - marks["finish"]

    try:
        for _ in range(max(20, args.calls)):
            one()
        res: dict = {}
        kinds = list(ops_by_kind)
        for r in range(args.rounds):
            for kind in (kinds if r % 2 == 0 else kinds[::-1]):
                for k in (0, args.extra):
                    state.update(op=ops_by_kind[kind], k=k)
                    res.setdefault((kind, k), []).extend(one() for _ in range(args.calls))
    finally:
        ops.bin_tiles, L.start_read_int64, L.finish_read_int64 = bin_tiles, start, finish
    name = torch.cuda.get_device_name() if device.type == "cuda" else "CPU"
    print(f"{name}; {n:,} Gaussians at {w}x{h}; forward+backward synchronised per call; "
          f"{args.rounds} rounds x {args.calls} calls per variant\n")
    print("| operation | call µs (median) | with the extra ops | µs per extra op | µs in a tight loop |")
    print("|---|---|---|---|---|")
    for kind, op in ops_by_kind.items():
        a = statistics.median(x[0] for x in res[(kind, 0)]) * 1e6
        b = statistics.median(x[0] for x in res[(kind, args.extra)]) * 1e6
        sync()
        tight = timeit.timeit(op, number=2000) / 2000 * 1e6
        sync()
        print(f"| {kind} | {a:.0f} | {b:.0f} | {(b - a) / args.extra:.1f} | {tight:.2f} |")
    base = [x for kind in kinds for x in res[(kind, 0)]]
    before, wait, after = (statistics.median(x[i] for x in base) * 1e6 for i in (1, 2, 3))
    print(f"\nforward: {before:.0f} µs of host time before the read-back, {wait:.0f} µs waiting for it, "
          f"{after:.0f} µs after it")


if __name__ == "__main__":
    main()
