"""Rasterizer speed and agreement: ssgwarp (CUDA, CPU) side by side with gsplat 1.5.3 in one run.

Scene (the issue's): N Gaussians with means ~ N(0, 2) around z = 8 in front of
the cameras (60 deg horizontal field of view), scales ~ U(0, 0.02), random
quaternions and opacities; colours U(0, 1), or SH coefficients (degree 3: DC
term U(0, 1) / C0, higher bands N(0, 0.1)); one camera at the origin or four
(translated by +-0.5 in x and y). For each case: forward and forward+backward
milliseconds (median of repeats, CUDA-synchronised; on CUDA ssgwarp and gsplat
are timed in turns, after a warm-up that brings the GPU's clocks up, so that
drift affects both alike), the ratio to gsplat, the
image difference against gsplat, and how far each float32 image is from the
same scene rendered by ssgwarp in float64 under the same rules (the float32
rounding both renderers share: a contribution at the 1/255 alpha threshold can
land on either side of it).

    python benchmarks/raster.py                    # the issue's five cases, CUDA if present
    python benchmarks/raster.py --cases grid       # 10k/100k/1M Gaussians x 256^2/1080p, colours
    python benchmarks/raster.py --cases quick      # small sizes only (CPU smoke run)
    python benchmarks/raster.py --markdown out.md  # also write the table
"""
from __future__ import annotations

import argparse
import datetime
import math
import statistics
import time

import torch

import ssgwarp
from timing import sync, timed


C0 = 0.28209479177387814
# (N, width, height, SH degree or None for colours, cameras)
CASES = {
    "issue": [(10_000, 256, 256, None, 1), (100_000, 1920, 1080, None, 1), (1_000_000, 1920, 1080, None, 1),
              (200_000, 504, 378, 3, 1), (300_000, 1008, 756, 3, 4)],
    "grid": [(n, w, h, None, 1) for n in (10_000, 100_000, 1_000_000) for (w, h) in ((256, 256), (1920, 1080))],
    "quick": [(1_000, 128, 128, None, 1), (10_000, 256, 256, None, 1), (2_000, 128, 96, 3, 2)],
}


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


def closures(raster, n, w, h, device, sh_degree=None, cameras=1, **kw):
    """``(fwd, fwd_bwd)`` of one renderer on the case's scene."""
    params = make_scene(n, device, sh_degree=sh_degree)
    vm, K = camera(w, h, device, cameras=cameras)
    if sh_degree is not None:
        kw["sh_degree"] = sh_degree
    return pass_closures(raster, params, vm, K, w, h, **kw)


def pass_closures(raster, params, vm, K, w, h, **kw):
    """``(fwd, fwd_bwd)``: one call of ``raster`` on ``params`` without gradients, and one with the
    backward of ``image.sum() + alpha.sum()`` into copies of ``params`` (made once, here)."""
    leaves = [p.clone().requires_grad_(True) for p in params]

    def fwd():
        with torch.no_grad():
            return raster(*params, vm, K, w, h, **kw)

    def fwd_bwd():
        for p in leaves:
            p.grad = None
        img, alpha, _ = raster(*leaves, vm, K, w, h, **kw)
        (img.sum() + alpha.sum()).backward()

    return fwd, fwd_bwd


def run_case(raster, n, w, h, device, repeats, sh_degree=None, cameras=1, **kw):
    fwd, fwd_bwd = closures(raster, n, w, h, device, sh_degree, cameras, **kw)
    t_f = timed(fwd, device, repeats)
    t_fb = timed(fwd_bwd, device, repeats)
    img = fwd()[0]
    return t_f, t_fb, img


def interleaved(fns: dict, device, repeats: int, rounds: int = 4) -> dict:
    """Median milliseconds of each function, timed in turns (``rounds`` rounds of
    ``repeats / rounds`` synchronised calls each) so that a drifting GPU clock or host load
    affects all of them alike."""
    for fn in fns.values():
        fn()
    sync(device)
    out = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            for _ in range(max(1, repeats // rounds)):
                t0 = time.perf_counter()
                fn()
                sync(device)
                out[k].append((time.perf_counter() - t0) * 1e3)
    return {k: statistics.median(v) for k, v in out.items()}


def optional_gsplat(skip: bool = False):
    """The gsplat module, or None (asked to skip it, or not importable: then said so once)."""
    if skip:
        return None
    try:
        import gsplat
    except Exception as e:  # noqa: BLE001
        print(f"gsplat not available ({e}); its columns stay empty")
        return None
    return gsplat


def with_setting(fn, owner, name: str, value):
    """``fn`` run with ``owner.name`` set to ``value`` for the call (restored after it): one
    function, two code paths of a switch such as ``blend_ops.BATCHED``."""
    def run():
        saved = getattr(owner, name)
        setattr(owner, name, value)
        try:
            return fn()
        finally:
            setattr(owner, name, saved)
    return run


def warm_gpu(seconds: float = 1.0) -> None:
    """Busy the GPU for a moment so its clocks are up before the first timing."""
    x = torch.randn(4096, 4096, device="cuda")
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        x = (x @ x).clamp_(-1, 1)
    torch.cuda.synchronize()


def cuda_only(script: str, measures: str) -> torch.device:
    """The CUDA device, its clocks warmed (:func:`warm_gpu`), for a script that only measures CUDA;
    without a GPU, exit saying so (``measures``: what the script measures)."""
    if not torch.cuda.is_available():
        raise SystemExit(f"{script} {measures}: run it on a machine with a GPU")
    warm_gpu()
    return torch.device("cuda")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", choices=sorted(CASES), default="issue")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--no-cpu", action="store_true")
    ap.add_argument("--cpu-max", type=int, default=10_000, help="largest N also timed on the CPU")
    ap.add_argument("--deterministic", action="store_true", help="also time deterministic=True")
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args()

    gsplat = optional_gsplat(args.no_gsplat)
    cuda = torch.cuda.is_available()
    dev_name = torch.cuda.get_device_name() if cuda else "cpu only"
    rows = []
    for n, w, h, deg, cams in CASES[args.cases]:
        row = {"N": n, "res": f"{w}x{h}", "sh": "colours" if deg is None else str(deg), "cams": cams}
        case = dict(sh_degree=deg, cameras=cams)
        if cuda:
            dev = torch.device("cuda")
            if not rows:
                warm_gpu()
            # ssgwarp and gsplat timed in turns on the same scene
            fns = dict(zip(("ssg_f", "ssg_fb"), closures(ssgwarp.rasterization, n, w, h, dev, packed=False, **case)))
            if gsplat is not None:
                fns.update(zip(("gs_f", "gs_fb"), closures(gsplat.rasterization, n, w, h, dev, packed=False, **case)))
            t = interleaved(fns, dev, args.repeats)
            f, fb = t["ssg_f"], t["ssg_fb"]
            img = fns["ssg_f"]()[0]
            row.update(ssg_f=f, ssg_fb=fb)
            if args.deterministic:
                _, fbd, _ = run_case(ssgwarp.rasterization, n, w, h, dev, max(3, args.repeats // 3),
                                     deterministic=True, **case)
                row.update(ssg_det_fb=fbd)
            # the same scene and rules in float64: how far each float32 renderer is from it
            params64 = [p.double() for p in make_scene(n, dev, sh_degree=deg)]
            vm64, K64 = camera(w, h, dev, torch.float64, cameras=cams)
            with torch.no_grad():
                img64 = ssgwarp.rasterization(*params64, vm64, K64, w, h, sh_degree=deg)[0]
            row.update(f64diff=float((img.double() - img64).abs().max()))
            if gsplat is not None:
                gf, gfb, gimg = t["gs_f"], t["gs_fb"], fns["gs_f"]()[0]
                diff = (img - gimg).abs()
                row.update(gs_f=gf, gs_fb=gfb, ratio_f=f / gf, ratio_fb=fb / gfb,
                           maxdiff=float(diff.max()), meandiff=float(diff.mean()),
                           over=float((diff > 1e-4).float().mean()),
                           gs64diff=float((gimg.double() - img64).abs().max()))
            del params64, img64, fns
        if not args.no_cpu and n * cams <= args.cpu_max:
            f, fb, _ = run_case(ssgwarp.rasterization, n, w, h, torch.device("cpu"), max(2, args.repeats // 5),
                                **case)
            row.update(cpu_f=f, cpu_fb=fb)
        rows.append(row)
        print(row, flush=True)

    cols = [("N", "N"), ("res", "resolution"), ("sh", "SH degree"), ("cams", "cameras"), ("ssg_f", "ssgwarp CUDA fwd ms"), ("ssg_fb", "ssgwarp CUDA fwd+bwd ms"),
            ("gs_f", "gsplat fwd ms"), ("gs_fb", "gsplat fwd+bwd ms"), ("ratio_f", "fwd ratio"),
            ("ratio_fb", "fwd+bwd ratio"), ("maxdiff", "max abs image diff"), ("meandiff", "mean abs image diff"),
            ("over", "share of values off by > 1e-4"), ("f64diff", "ssgwarp max abs diff to float64"),
            ("gs64diff", "gsplat max abs diff to float64"), ("ssg_det_fb", "deterministic fwd+bwd ms"),
            ("cpu_f", "ssgwarp CPU fwd ms"), ("cpu_fb", "ssgwarp CPU fwd+bwd ms")]
    cols = [c for c in cols if any(c[0] in r for r in rows)]

    def fmt(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.2e}" if abs(v) < 1e-2 and v != 0 else f"{v:.2f}"
        return f"{v:,}" if isinstance(v, int) else str(v)

    lines = [f"device: {dev_name}; torch {torch.__version__}; gsplat {getattr(gsplat, '__version__', 'n/a')}; "
             f"{datetime.date.today().isoformat()}", "",
             "| " + " | ".join(c[1] for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        if len(r) > 4:  # something was measured for this case
            lines.append("| " + " | ".join(fmt(r.get(c[0])) for c in cols) + " |")
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(table + "\n")


if __name__ == "__main__":
    main()
