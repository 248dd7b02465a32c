"""The 3DGS photometric loss (0.8 L1 + 0.2 (1 - SSIM)): the torch reference against the fused Warp kernels.

Per image size, forward alone and forward + backward (the gradient of the rendered image, as a
training step takes it), median milliseconds of synchronised calls, the two taken in turns so that
load on the machine hits both alike; on CUDA also the host's microseconds per forward + backward
with one synchronisation per block of calls (what a training loop bound by its host work pays), and
the GPU time of the kernels a forward + backward launches (torch profiler; with their count).
Prints a markdown table.

    python benchmarks/loss.py --device cpu                     # OMP_NUM_THREADS sets the CPU threads
    OMP_NUM_THREADS=1 python benchmarks/loss.py --device cpu --clock cpu   # on a loaded machine
    python benchmarks/loss.py --device cuda --repeats 50
    python benchmarks/loss.py --sizes 504x378 --views 2 --dtype float64
"""
from __future__ import annotations

import argparse
import datetime
import platform
import statistics
import time

import torch
import warp

from timing import cuda_kernel_ms, per_call_us, sync

from ssgwarp.services.losses import photometric

SIZES = ("504x378", "1008x756", "1920x1080")


def images(w: int, h: int, views: int, dtype, device):
    """A render-like pair: the target and a noisy, slightly blurred copy (the render, needing a gradient)."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(views, h, w, 3, generator=g).to(dtype)
    img = (0.9 * gt + 0.1 * torch.rand(views, h, w, 3, generator=g).to(dtype)).clamp(0, 1)
    return img.to(device).requires_grad_(True), gt.to(device)


def closures(img, gt, fused: bool):
    def forward():
        with torch.no_grad():
            photometric(img, gt, fused=fused)

    def both():
        img.grad = None
        photometric(img, gt, fused=fused).backward()
    return forward, both


def in_turns(fns: list, device, repeats: int, now=time.perf_counter) -> list[float]:
    """Median ms of each of ``fns``, called in turns ``repeats`` times after one warm-up each (``now``:
    the clock)."""
    for f in fns:
        f()
    sync(device)
    times = [[] for _ in fns]
    for _ in range(repeats):
        for f, t in zip(fns, times):
            t0 = now()
            f()
            sync(device)
            t.append((now() - t0) * 1e3)
    return [statistics.median(t) for t in times]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=("cpu", "cuda"), default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--sizes", nargs="+", default=list(SIZES), help="WxH (default: %(default)s)")
    p.add_argument("--views", type=int, default=1, help="images per call ([V, H, W, 3])")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--repeats", type=int, default=None, help="timed calls per case (default: 5 CPU, 50 CUDA)")
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                   help="wall-clock time, or this process's CPU time (a shared machine's load does not count; "
                        "with one thread what an idle machine's wall clock shows, with more their sum)")
    args = p.parse_args()
    dev = torch.device(args.device)
    repeats = args.repeats or (5 if dev.type == "cpu" else 50)
    dtype = getattr(torch, args.dtype)
    where = (torch.cuda.get_device_name(dev) if dev.type == "cuda" else
             f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread(s)")
    now = time.process_time if args.clock == "cpu" else time.perf_counter
    print(f"photometric loss, {args.views} view(s) x 3 channels, {args.dtype}, {where}; torch {torch.__version__}, "
          f"warp {warp.__version__}; {datetime.date.today()}; median of {repeats}, {args.clock} clock\n")
    cols = ["size", "pass", "reference ms", "fused ms", "fused / reference"]
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for size in args.sizes:
        w, h = (int(v) for v in size.lower().split("x"))
        img, gt = images(w, h, args.views, dtype, dev)
        ref_f, ref_b = closures(img, gt, False)
        fus_f, fus_b = closures(img, gt, True)
        rows = [("forward", *in_turns([ref_f, fus_f], dev, repeats, now)),
                ("forward+backward", *in_turns([ref_b, fus_b], dev, repeats, now))]
        if dev.type == "cuda":  # host cost per step: one synchronisation per block of 20 calls
            r, f = (per_call_us(fn, dev, 20, max(3, repeats // 10)) / 1e3 for fn in (ref_b, fus_b))
            rows.append(("fwd+bwd, 20 queued", r, f))
            kr, kf = (cuda_kernel_ms(fn) for fn in (ref_b, fus_b))
            rows.append((f"fwd+bwd GPU kernels ({len(kr)} / {len(kf)} kinds)", sum(kr.values()), sum(kf.values())))
        for name, r, f in rows:
            print(f"| {w}x{h} | {name} | {r:.3f} | {f:.3f} | {f / r:.2f} |")
        del img, gt


if __name__ == "__main__":
    main()
