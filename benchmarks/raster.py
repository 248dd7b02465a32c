"""The rasterizer against gsplat 1.5.3: speed and agreement, ssgwarp (CUDA, CPU) side by side in one run.

Issue 16's scene (docs/benchmarks.md). Per case: forward and forward+backward ms (median / min / max of
``--repeats`` synchronised calls, ssgwarp and gsplat in turns), the ratio to gsplat, the image difference and each
float32 image's distance to the float64 render. ``--cases``: a set name or ``[ball:|ball2:]NxWxH[:SH[:CAMERAS]]``
(``ball``: tradeoffs.py's scene of larger Gaussians).

    python benchmarks/raster.py --cases quick --no-gsplat --device cpu          # CPU smoke run
    python benchmarks/raster.py --agreement        # + share of bit-identical projected Gaussians against gsplat's
    python benchmarks/raster.py --profile --cases 1000000x1920x1080     # per-kernel GPU time, host Python functions
    python benchmarks/raster.py --device cpu --clock cpu --repeats 15 --tile 4 6 8 12 16 --threads 1 2 \
        --cases ball:20000x256x192 ball:100000x200x200 10000x256x256 ball2:20000x256x192
"""
from __future__ import annotations

import argparse
import cProfile
import io
import math
import pstats
import time

import torch

import ssgwarp
from harness import append_jsonl, header, interleaved, measure, optional_gsplat, passes, table, warm_gpu

C0 = 0.28209479177387814
# (N, width, height, SH degree or None for colours, cameras)
CASES = {
    "issue": [(10_000, 256, 256, None, 1), (100_000, 1920, 1080, None, 1), (1_000_000, 1920, 1080, None, 1),
              (200_000, 504, 378, 3, 1), (300_000, 1008, 756, 3, 4)],
    "grid": [(n, w, h, None, 1) for n in (10_000, 100_000, 1_000_000) for (w, h) in ((256, 256), (1920, 1080))],
    "quick": [(1_000, 128, 128, None, 1), (10_000, 256, 256, None, 1), (2_000, 128, 96, 3, 2)],
}
META_KEYS = ("radii", "means2d", "conics", "opacities", "depths")


def parse_cases(specs: list[str]) -> list[tuple]:
    out = []
    for s in specs:
        if s in CASES:
            out += CASES[s]
            continue
        kind, _, spec = s.partition(":") if s.startswith("ball") else ("", "", s)
        size, *rest = spec.split(":")
        try:
            n, w, h = (int(v) for v in size.split("x"))
            deg = 3 if kind else int(rest[0]) if rest and rest[0] not in ("", "rgb") else None
            out.append((n, w, h, deg, int(rest[1]) if len(rest) > 1 else 1) + ((kind,) if kind else ()))
        except ValueError:
            raise SystemExit(f"--cases: {s!r} is neither {'/'.join(CASES)} nor NxWxH[:SH[:CAMERAS]]") from None
    return out


def make_scene(n: int, device, dtype=torch.float32, seed: int = 0, sh_degree=None):
    g = torch.Generator(device="cpu").manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 2.0
    means[:, 2] += 8.0
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.02
    opac = torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    if sh_degree is not None:
        k = (sh_degree + 1) ** 2
        colors = torch.cat([colors[:, None] / C0, torch.randn(n, k - 1, 3, generator=g) * 0.1], dim=1)
    return [t.to(device=device, dtype=dtype) for t in (means, quats, scales, opac, colors)]


def camera(width: int, height: int, device, dtype=torch.float32, cameras: int = 1):
    f = 0.5 * width / math.tan(math.radians(30.0))
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype, device=device)
    vm = torch.eye(4, dtype=dtype, device=device).repeat(cameras, 1, 1)
    if cameras > 1:
        shift = torch.tensor([[0.5, 0.5], [-0.5, 0.5], [0.5, -0.5], [-0.5, -0.5]], dtype=dtype, device=device)
        vm[:, :2, 3] = shift[torch.arange(cameras) % 4]
    return vm, K[None].repeat(cameras, 1, 1)


def ball(n, w, h, device, grow: float = 1.0):
    """tradeoffs.py's scene and camera: ``(params, viewmats, Ks)``."""
    from tradeoffs import synthetic_cameras, synthetic_scene

    sc = synthetic_scene(n, 3, seed=0).to(device=device, dtype=torch.float32)
    cams = synthetic_cameras(1, w, h)
    params = [sc.means, sc.quats, sc.scales * grow, sc.opacities, sc.sh_coeffs.contiguous()]
    return [p.detach().contiguous() for p in params], cams.viewmats.to(device), cams.Ks.to(device)


def closures(raster, n, w, h, device, sh_degree=None, cameras=1, kind="", **kw):
    """``(fwd, fwd_bwd)``: one call of ``raster`` on the case's scene without gradients, and one with the
    backward of ``image.sum() + alpha.sum()`` into copies of the parameters (made once, here)."""
    if kind:
        params, vm, K = ball(n, w, h, device, 2.0 if kind == "ball2" else 1.0)
    else:
        params = make_scene(n, device, sh_degree=sh_degree)
        vm, K = camera(w, h, device, cameras=cameras)
    if sh_degree is not None:
        kw["sh_degree"] = sh_degree
    return passes(raster, params, (vm, K, w, h), **kw)[:2]


def profile_pass(name: str, fn, iters: int, host_rows: int, kernel_rows: int = 14) -> None:
    """Print ``fn``'s GPU kernels (torch profiler; kernel time per call against wall time: the rest is the GPU
    waiting for the host) and the Python functions with the most host time (cProfile)."""
    from torch.profiler import ProfilerActivity, profile

    wall = measure(fn, "cuda", iters)["median"]
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(iters):
            fn()
        torch.cuda.synchronize()
    ka = prof.key_averages()
    gpu = sum(e.self_device_time_total for e in ka if str(e.device_type).endswith("CUDA")) / iters / 1e3
    print(f"--- {name}: wall {wall:.2f} ms, GPU kernel time {gpu:.2f} ms per call")
    print(ka.table(sort_by="self_device_time_total", row_limit=kernel_rows, max_name_column_width=60))
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(iters):
        fn()
    torch.cuda.synchronize()
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(host_rows)
    print("\n".join(s.getvalue().splitlines()[:host_rows + 12]))


def agreement(row: dict, n, w, h, deg, cams, dev, gsplat) -> None:
    """The share of Gaussians visible in both whose projected values are bit-identical to gsplat's."""
    params = make_scene(n, dev, sh_degree=deg)
    vm, K = camera(w, h, dev, cameras=cams)
    kw = {} if deg is None else {"sh_degree": deg}
    with torch.no_grad():
        ours = ssgwarp.rasterization(*params, vm, K, w, h, packed=False, **kw)[2]
        theirs = gsplat.rasterization(*params, vm, K, w, h, packed=False, **kw)[2]
    vis = (ours["radii"] > 0).all(-1) & (theirs["radii"] > 0).all(-1)
    row["visible"] = int(vis.sum())
    for key in META_KEYS:
        a, b = ours[key][vis], theirs[key][vis]
        row[f"same_{key}"] = float((a == b).reshape(a.shape[0], -1).all(-1).float().mean())


def cuda_row(row, case, args, gsplat) -> None:
    n, w, h, deg, cams, *kind = case
    if kind:
        raise SystemExit("raster.py: the ball scenes are CPU cases (--device cpu)")
    dev = torch.device("cuda")
    kw = dict(sh_degree=deg, cameras=cams, packed=False)
    fns = dict(zip(("ssg_f", "ssg_fb"), closures(ssgwarp.rasterization, n, w, h, dev, **kw)))
    if gsplat is not None:
        fns.update(zip(("gs_f", "gs_fb"), closures(gsplat.rasterization, n, w, h, dev, **kw)))
    for k, s in interleaved(fns, dev, args.repeats).items():
        row.update({k: s["median"], f"{k}_range": f"{s['min']:.2f}-{s['max']:.2f}"})
    img = fns["ssg_f"]()[0]
    params64 = [p.double() for p in make_scene(n, dev, sh_degree=deg)]
    vm64, K64 = camera(w, h, dev, torch.float64, cameras=cams)
    with torch.no_grad():
        img64 = ssgwarp.rasterization(*params64, vm64, K64, w, h, sh_degree=deg)[0]
    row["f64diff"] = float((img.double() - img64).abs().max())
    if gsplat is not None:
        gimg = fns["gs_f"]()[0]
        diff = (img - gimg).abs()
        row.update(ratio_f=row["ssg_f"] / row["gs_f"], ratio_fb=row["ssg_fb"] / row["gs_fb"],
                   maxdiff=float(diff.max()), over=float((diff > 1e-4).float().mean()),
                   gs64diff=float((gimg.double() - img64).abs().max()))
        if args.agreement:
            agreement(row, n, w, h, deg, cams, dev, gsplat)
    for lib, key in (("ssgwarp", "ssg"), ("gsplat", "gs")):
        if args.profile and f"{key}_f" in fns:
            print(f"\n=== {lib}: N={n:,} {w}x{h}")
            profile_pass(f"{lib} forward", fns[f"{key}_f"], args.repeats, 15)
            profile_pass(f"{lib} forward+backward", fns[f"{key}_fb"], args.repeats, 15)


def cpu_rows(case, args) -> list[dict]:
    """One row per tile size and thread count on the CPU."""
    from ssgwarp import RasterSettings

    n, w, h, deg, cams, *kind = case
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    rows = []
    for tile in args.tile or [None]:
        for threads in args.threads or [None]:
            kw = {} if tile is None else {"tile_size": tile}
            if threads is not None:
                kw["settings"] = RasterSettings(cpu_threads=threads)
            f, fb = closures(ssgwarp.rasterization, n, w, h, torch.device("cpu"), sh_degree=deg, cameras=cams,
                             kind=(kind or [""])[0], **kw)
            t = interleaved({"cpu_f": f, "cpu_fb": fb}, "cpu", max(2, args.repeats // 5), rounds=1, clock=clock)
            rows.append({"tile": tile or "default", "threads": threads or "default"})
            for k, s in t.items():
                rows[-1].update({k: s["median"], f"{k}_range": f"{s['min']:.2f}-{s['max']:.2f}"})
    return rows


COLS = [("scene", "scene"), ("N", "N"), ("res", "resolution"), ("sh", "SH degree"), ("cams", "cameras"), ("tile", "tile"),
        ("threads", "CPU threads"), ("ssg_f", "ssgwarp CUDA fwd ms"), ("ssg_f_range", "min-max"),
        ("ssg_fb", "ssgwarp CUDA fwd+bwd ms"), ("ssg_fb_range", "min-max"), ("gs_f", "gsplat fwd ms"),
        ("gs_fb", "gsplat fwd+bwd ms"), ("ratio_f", "fwd ratio"), ("ratio_fb", "fwd+bwd ratio"),
        ("maxdiff", "max abs image diff"), ("over", "share of values off by > 1e-4"),
        ("f64diff", "ssgwarp max abs diff to float64"), ("gs64diff", "gsplat max abs diff to float64"),
        ("visible", "visible in both")] + [(f"same_{k}", f"{k} bit-identical") for k in META_KEYS] + [
        ("cpu_f", "ssgwarp CPU fwd ms"), ("cpu_f_range", "min-max"), ("cpu_fb", "ssgwarp CPU fwd+bwd ms"),
        ("cpu_fb_range", "min-max")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["issue"], help="issue, grid, quick or NxWxH[:SH[:CAMERAS]]")
    ap.add_argument("--device", choices=("auto", "cuda", "cpu"), default="auto",
                    help="auto (default): CUDA when present, and the CPU for cases up to --cpu-max")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--no-cpu", action="store_true", help="with --device auto: CUDA only")
    ap.add_argument("--cpu-max", type=int, default=10_000, help="largest N x cameras also timed on the CPU")
    ap.add_argument("--agreement", action="store_true", help="CUDA: bit-identical shares of projected Gaussians")
    ap.add_argument("--profile", action="store_true", help="CUDA: per-kernel GPU time and host functions")
    ap.add_argument("--tile", nargs="+", type=int, default=None, help="CPU: tile sizes to time")
    ap.add_argument("--threads", nargs="+", type=int, default=None, help="CPU: blending threads to time")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall", help="CPU: wall or process CPU time")
    ap.add_argument("--out", default=None, help="append the rows as JSON lines")
    args = ap.parse_args(argv)

    cases = parse_cases(args.cases)
    cuda = torch.cuda.is_available() and args.device != "cpu"
    if args.device == "cuda" and not cuda:
        raise SystemExit("raster.py --device cuda: no GPU here (--device cpu times the CPU kernels)")
    gsplat = optional_gsplat(args.no_gsplat or not cuda)
    if cuda:
        warm_gpu()
    rows = []
    for case in cases:
        n, w, h, deg, cams, *kind = case
        row = {"N": n, "res": f"{w}x{h}", "sh": "colours" if deg is None else str(deg), "cams": cams}
        if kind:
            row["scene"] = kind[0]
        cpu_ok = args.device == "cpu" or (args.device == "auto" and not args.no_cpu and n * cams <= args.cpu_max)
        if cuda:
            cuda_row(row, case, args, gsplat)
            if cpu_ok:
                row.update(cpu_rows(case, args)[0])
            new = [row]
        else:
            new = [{**row, **r} for r in cpu_rows(case, args)] if cpu_ok else []
        for r in new:
            append_jsonl(args.out, r)
            print(r, flush=True)
        rows += new

    dev = "cuda" if cuda else "cpu"
    gv = getattr(gsplat, "__version__", "n/a")
    text = f"{header(dev, f'gsplat {gv}')}\n\n{table(rows, COLS)}"
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
