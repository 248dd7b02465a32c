"""Where the rasterizer's time goes on CUDA: per-kernel GPU time and host-side cost, ssgwarp next to gsplat.

    python benchmarks/profile_raster.py                  # 10k @ 256x256 and 1M @ 1920x1080
    python benchmarks/profile_raster.py --cases 1000000x1920x1080 --no-gsplat

For each case and library: the wall time of forward and forward+backward, for each of them the GPU kernel
time per call (torch.profiler; wall minus kernel time is where the GPU waits for the host) and a table of
the kernels and ops (sorted by GPU time), and the Python functions with the most host time in the
forward (cProfile).
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).parent))
from raster import camera, make_scene  # noqa: E402
from timing import timed  # noqa: E402

import ssgwarp  # noqa: E402


def run(name, raster, n, w, h, iters, host_rows, kernel_rows=14):
    dev = torch.device("cuda")
    params = make_scene(n, dev)
    vm, K = camera(w, h, dev)
    leaves = [p.clone().requires_grad_(True) for p in params]

    def fwd():
        with torch.no_grad():
            return raster(*params, vm, K, w, h, packed=False)

    def fwd_bwd():
        for p in leaves:
            p.grad = None
        img, alpha, _ = raster(*leaves, vm, K, w, h, packed=False)
        (img.sum() + alpha.sum()).backward()

    t_f, t_fb = timed(fwd, dev, 10), timed(fwd_bwd, dev, 10)
    print(f"\n=== {name}: N={n:,} {w}x{h}: fwd {t_f:.2f} ms, fwd+bwd {t_fb:.2f} ms")
    for label, fn, wall in (("forward", fwd, t_f), ("forward+backward", fwd_bwd, t_fb)):
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(iters):
                fn()
            torch.cuda.synchronize()
        ka = prof.key_averages()
        # kernels, memsets and copies only (torch ops also carry their kernels' time)
        gpu = sum(e.self_device_time_total for e in ka if str(e.device_type).endswith("CUDA")) / iters / 1e3
        print(f"--- {name} {label}: wall {wall:.2f} ms, GPU kernel time {gpu:.2f} ms per call "
              f"(the rest: GPU idle, waiting for the host)")
        print(ka.table(sort_by="self_device_time_total", row_limit=kernel_rows, max_name_column_width=60))
    pr = cProfile.Profile()
    torch.cuda.synchronize()
    pr.enable()
    for _ in range(iters):
        fwd()
    torch.cuda.synchronize()
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(host_rows)
    print("\n".join(s.getvalue().splitlines()[:host_rows + 12]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=["10000x256x256", "1000000x1920x1080"])
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--host-rows", type=int, default=15)
    ap.add_argument("--no-gsplat", action="store_true")
    args = ap.parse_args()
    libs = [("ssgwarp", ssgwarp.rasterization)]
    if not args.no_gsplat:
        import gsplat
        libs.append(("gsplat", gsplat.rasterization))
    for case in args.cases:
        n, w, h = (int(v) for v in case.split("x"))
        for name, fn in libs:
            run(name, fn, n, w, h, args.iters, args.host_rows)


if __name__ == "__main__":
    main()
