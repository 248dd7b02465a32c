"""The CPU blending kernels on 1 and more threads (``RasterSettings.cpu_threads``), CPU only.

Cases (random scenes sized like the project's CPU runs; tile size 8, the CPU default):

- ``lego-group``: 100,000 Gaussians, 200x200, 16 channels, the colour-only backward (grouping's
  identity training on lego_200: the geometry frozen);
- ``lego-rgb``: the same scene, 3 channels, the full backward (reconstruction);
- ``demo-group`` / ``demo-rgb``: 6,000 Gaussians, 96x72 (``ssgwarp demo``'s default size).

Per case and thread count: the median wall time of ``--repeats`` calls of one forward (no
gradients) and of one forward+backward, the process CPU time of the same calls (the work done) and
their critical path (:class:`CriticalPath`: on a shared machine the wall time of several threads
depends on what else runs; the critical path estimates it with a free core per thread). ``--sweep`` times small images at 1 and 2 threads with the work threshold off, to place
``cpu_threads.MIN_WORK`` (the break-even).

    python benchmarks/cpu_threads.py                        # all cases, 1 and 2 threads
    python benchmarks/cpu_threads.py --cases demo-rgb --threads 1 2 4 --repeats 9
    python benchmarks/cpu_threads.py --sweep --out sweep.json
    python benchmarks/cpu_threads.py --torch-threads 1      # torch's own pool at 1 thread
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import ssgwarp  # noqa: E402,F401  (before torch, as the CLI: its OpenMP wait policy, ssgwarp/__init__.py)
import torch  # noqa: E402
import ssgwarp.raster.cpu_threads as CT  # noqa: E402
from ssgwarp import RasterSettings, rasterization  # noqa: E402

# name: (Gaussians, width, height, channels, geometry gradients)
CASES = {
    "lego-group": (100_000, 200, 200, 16, False),
    "lego-rgb": (100_000, 200, 200, 3, True),
    "demo-group": (6_000, 96, 72, 16, False),
    "demo-rgb": (6_000, 96, 72, 3, True),
}
# (Gaussians, width, height): small scenes around the break-even
SWEEP = [(50, 16, 16), (100, 24, 16), (150, 24, 24), (200, 32, 24), (500, 48, 36), (1000, 64, 48), (3000, 96, 72),
         (6000, 128, 96)]


def scene(n: int, w: int, h: int, channels: int, seed: int = 0):
    """A ball of ``n`` Gaussians filling the middle of a ``w x h`` view (about 3 tiles of 8 pixels
    each at 200x200 and 100,000 Gaussians, as lego_200 after 100 steps of reconstruction)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.6
    means[:, 2] += 4.0
    quats = torch.randn(n, 4, generator=g)
    # scale ~ one tile at 200 px for 100k Gaussians; the same screen size per Gaussian elsewhere
    s = 0.012 * (200.0 / w) * math.sqrt(100_000 / n) ** 0.5
    scales = torch.rand(n, 3, generator=g) * s + 0.2 * s
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    colors = torch.rand(n, channels, generator=g)
    f = 0.5 * w / math.tan(math.radians(25.0))
    K = torch.tensor([[[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]])
    return [means, quats, scales, opac, colors], torch.eye(4)[None], K


def closures(params, vm, K, w, h, geometry: bool, settings: RasterSettings, deterministic=False):
    leaves = [p.clone().requires_grad_(geometry or i == 4) for i, p in enumerate(params)]
    g = torch.Generator().manual_seed(1)
    cot = None

    def fwd():
        with torch.no_grad():
            return rasterization(*params, vm, K, w, h, settings=settings, deterministic=deterministic)

    def fwd_bwd():
        nonlocal cot
        for p in leaves:
            p.grad = None
        img, alpha, meta = rasterization(*leaves, vm, K, w, h, settings=settings, deterministic=deterministic)
        if cot is None:
            cot = torch.rand(img.shape, generator=g)
        (img * cot).sum().backward()
        return meta

    return fwd, fwd_bwd


class CriticalPath:
    """Wraps ``cpu_threads.run`` to time each of its calls in its own thread's CPU time, so that a call's
    critical path (the calling thread's CPU time, plus for every split launch how much longer its slowest
    other run took than the calling thread's own) estimates the wall time with a free core per thread on a
    machine that other jobs keep busy (an estimate: the pool's wake-up latency is not in it)."""

    def __init__(self):
        self.extra = 0.0
        self.run = CT.run

    def __enter__(self):
        def run(calls):
            times = [0.0] * len(calls)

            def timed_call(i, c):
                def f():
                    t0 = time.thread_time()
                    c()
                    times[i] = time.thread_time() - t0
                return f
            self.run([timed_call(i, c) for i, c in enumerate(calls)])
            self.extra += max(0.0, max(times) - times[0])
        CT.run = run
        return self

    def __exit__(self, *exc):
        CT.run = self.run


def timed(fn, repeats: int) -> tuple[float, float, float]:
    """Median (wall ms, process CPU ms, critical path ms) of ``repeats`` calls after a warm-up call."""
    fn()
    wall, cpu, crit = [], [], []
    with CriticalPath() as cp:
        for _ in range(repeats):
            cp.extra = 0.0
            w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
            fn()
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            crit.append(time.thread_time() - t0 + cp.extra)
    return 1e3 * statistics.median(wall), 1e3 * statistics.median(cpu), 1e3 * statistics.median(crit)


def run_cases(names, threads, repeats, deterministic=False) -> list[dict]:
    rows = []
    for name in names:
        n, w, h, ch, geometry = CASES[name]
        params, vm, K = scene(n, w, h, ch)
        for t in threads:
            st = RasterSettings(cpu_threads=t)
            fwd, fwd_bwd = closures(params, vm, K, w, h, geometry, st, deterministic)
            f_wall, f_cpu, f_crit = timed(fwd, repeats)
            fb_wall, fb_cpu, fb_crit = timed(fwd_bwd, repeats)
            meta = fwd_bwd()
            used = CT.count(t, -(-w // 8) * -(-h // 8), int(meta["flatten_ids"].numel()), 64)
            rows.append({"case": name, "gaussians": n, "image": f"{w}x{h}", "channels": ch,
                         "backward": "full" if geometry else "colour-only", "threads": t, "threads_used": used,
                         "intersections": int(meta["flatten_ids"].numel()),
                         "fwd_ms": f_wall, "fwd_cpu_ms": f_cpu, "fwd_crit_ms": f_crit, "fwd_bwd_ms": fb_wall,
                         "fwd_bwd_cpu_ms": fb_cpu, "fwd_bwd_crit_ms": fb_crit})
            print(f"  {name} threads {t}: fwd {f_wall:.1f} ms, fwd+bwd {fb_wall:.1f} ms", file=sys.stderr, flush=True)
    return rows


def run_sweep(repeats) -> list[dict]:
    saved = CT.MIN_WORK
    CT.MIN_WORK = 1  # split whatever the size
    rows = []
    try:
        for n, w, h in SWEEP:
            params, vm, K = scene(n, w, h, 3)
            res = {}
            for t in (1, 2):
                fwd, fwd_bwd = closures(params, vm, K, w, h, True, RasterSettings(cpu_threads=t))
                res[t] = timed(fwd_bwd, repeats)
            meta = fwd_bwd()
            m = int(meta["flatten_ids"].numel())
            tiles = -(-w // 8) * -(-h // 8)
            rows.append({"gaussians": n, "image": f"{w}x{h}", "tiles": tiles, "intersections": m,
                         "work": (m + CT.TILE_COST * tiles) * 64, "fwd_bwd_ms_1": res[1][0], "fwd_bwd_ms_2": res[2][0],
                         "fwd_bwd_cpu_ms_1": res[1][1], "fwd_bwd_cpu_ms_2": res[2][1],
                         "fwd_bwd_crit_ms_1": res[1][2], "fwd_bwd_crit_ms_2": res[2][2]})
            print(f"  sweep {w}x{h}: {res[1][0]:.2f} / {res[2][0]:.2f} ms", file=sys.stderr, flush=True)
    finally:
        CT.MIN_WORK = saved
    return rows


def machine() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), load average {load:.2f} at the start")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--deterministic", action="store_true", help="the deterministic backward")
    ap.add_argument("--torch-threads", type=int, default=0, help="torch's intra-op threads (0: leave torch's default)")
    ap.add_argument("--sweep", action="store_true", help="also the break-even sweep of small images")
    ap.add_argument("--out", default=None, help="raw results as JSON")
    args = ap.parse_args()
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    info = {"date": datetime.date.today().isoformat(), "machine": machine(), "deterministic": args.deterministic}
    rows = run_cases(args.cases, args.threads, args.repeats, args.deterministic)
    print(f"\n{info['date']}, {info['machine']}; median of {args.repeats}"
          f"{', deterministic backward' if args.deterministic else ''}\n")
    print("| case | Gaussians | image | channels | backward | intersections | threads | fwd ms wall / CPU / path "
          "| fwd+bwd ms wall / CPU / path | fwd+bwd speed-up wall / path |")
    print("|---|---:|---|---:|---|---:|---:|---:|---:|---:|")
    base = {}
    for r in rows:
        b = base.setdefault(r["case"], r)
        print(f"| {r['case']} | {r['gaussians']:,} | {r['image']} | {r['channels']} | {r['backward']} | "
              f"{r['intersections']:,} | {r['threads']} | {r['fwd_ms']:.1f} / {r['fwd_cpu_ms']:.1f} / "
              f"{r['fwd_crit_ms']:.1f} | {r['fwd_bwd_ms']:.1f} / {r['fwd_bwd_cpu_ms']:.1f} / {r['fwd_bwd_crit_ms']:.1f} | "
              f"{b['fwd_bwd_ms'] / r['fwd_bwd_ms']:.2f}x / {b['fwd_bwd_crit_ms'] / r['fwd_bwd_crit_ms']:.2f}x |")
    sweep = run_sweep(args.repeats) if args.sweep else []
    if sweep:
        print("\nBreak-even (forward+backward, 3 channels, split whatever the size):\n")
        print("| image | Gaussians | tiles | intersections | work (pixel-intersections) | 1 thread ms wall / CPU "
              "| 2 threads ms wall / CPU / path |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for r in sweep:
            print(f"| {r['image']} | {r['gaussians']:,} | {r['tiles']} | {r['intersections']:,} | {r['work']:,} | "
                  f"{r['fwd_bwd_ms_1']:.2f} / {r['fwd_bwd_cpu_ms_1']:.2f} | {r['fwd_bwd_ms_2']:.2f} / "
                  f"{r['fwd_bwd_cpu_ms_2']:.2f} / {r['fwd_bwd_crit_ms_2']:.2f} |")
    if args.out:
        Path(args.out).write_text(json.dumps({**info, "rows": rows, "sweep": sweep}, indent=1))


if __name__ == "__main__":
    main()
