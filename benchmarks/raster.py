"""Rasterizer speed and agreement: ssgwarp (CUDA, CPU) side by side with gsplat 1.5.3 in one run.

Scene (the issue's): N Gaussians with means ~ N(0, 2) around z = 8 in front of
one camera (60 deg horizontal field of view), scales ~ U(0, 0.02), random
quaternions, colours and opacities. For each (N, resolution): forward and
forward+backward milliseconds (median of repeats, CUDA-synchronised), the
ratio to gsplat, the image difference against gsplat, and how far each float32
image is from the same scene rendered by ssgwarp in float64 under the same rules
(the float32 rounding both renderers share: a contribution at the 1/255 alpha
threshold can land on either side of it).

    python benchmarks/raster.py                    # all sizes, CUDA if present
    python benchmarks/raster.py --quick            # small sizes only (CPU smoke run)
    python benchmarks/raster.py --markdown out.md  # also write the table
"""
from __future__ import annotations

import argparse
import datetime
import math

import torch

import ssgwarp
from timing import timed


def make_scene(n: int, device, dtype=torch.float32, seed: int = 0):
    g = torch.Generator(device="cpu").manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 2.0
    means[:, 2] += 8.0
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.02
    opac = torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [t.to(device=device, dtype=dtype) for t in (means, quats, scales, opac, colors)]


def camera(width: int, height: int, device, dtype=torch.float32):
    f = 0.5 * width / math.tan(math.radians(30.0))
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype, device=device)[None]
    return torch.eye(4, dtype=dtype, device=device)[None], K


def run_case(raster, n, w, h, device, repeats, **kw):
    params = make_scene(n, device)
    vm, K = camera(w, h, device)
    leaves = [p.clone().requires_grad_(True) for p in params]

    def fwd():
        with torch.no_grad():
            return raster(*params, vm, K, w, h, **kw)

    def fwd_bwd():
        for p in leaves:
            p.grad = None
        img, alpha, _ = raster(*leaves, vm, K, w, h, **kw)
        (img.sum() + alpha.sum()).backward()

    t_f = timed(fwd, device, repeats)
    t_fb = timed(fwd_bwd, device, repeats)
    img = fwd()[0]
    return t_f, t_fb, img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--no-cpu", action="store_true")
    ap.add_argument("--deterministic", action="store_true", help="also time deterministic=True")
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args()

    gsplat = None
    if not args.no_gsplat:
        try:
            import gsplat as _g
            gsplat = _g
        except Exception as e:  # noqa: BLE001
            print(f"gsplat not available ({e}); its columns stay empty")
    cuda = torch.cuda.is_available()
    dev_name = torch.cuda.get_device_name() if cuda else "cpu only"
    sizes_n = [10_000, 100_000, 1_000_000] if not args.quick else [1_000, 10_000]
    sizes_r = [(256, 256), (1920, 1080)] if not args.quick else [(128, 128), (256, 256)]
    rows = []
    for n in sizes_n:
        for (w, h) in sizes_r:
            row = {"N": n, "res": f"{w}x{h}"}
            if cuda:
                dev = torch.device("cuda")
                f, fb, img = run_case(ssgwarp.rasterization, n, w, h, dev, args.repeats, packed=False)
                row.update(ssg_f=f, ssg_fb=fb)
                if args.deterministic:
                    _, fbd, _ = run_case(ssgwarp.rasterization, n, w, h, dev, max(3, args.repeats // 3),
                                         deterministic=True)
                    row.update(ssg_det_fb=fbd)
                # the same scene and rules in float64: how far each float32 renderer is from it
                params64 = [p.double() for p in make_scene(n, dev)]
                vm64, K64 = camera(w, h, dev, torch.float64)
                with torch.no_grad():
                    img64 = ssgwarp.rasterization(*params64, vm64, K64, w, h)[0]
                row.update(f64diff=float((img.double() - img64).abs().max()))
                if gsplat is not None:
                    gf, gfb, gimg = run_case(gsplat.rasterization, n, w, h, dev, args.repeats, packed=False)
                    diff = (img - gimg).abs()
                    row.update(gs_f=gf, gs_fb=gfb, ratio_f=f / gf, ratio_fb=fb / gfb,
                               maxdiff=float(diff.max()), meandiff=float(diff.mean()),
                               over=float((diff > 1e-4).float().mean()),
                               gs64diff=float((gimg.double() - img64).abs().max()))
                del params64, img64
            if not args.no_cpu and n <= 10_000:
                f, fb, _ = run_case(ssgwarp.rasterization, n, w, h, torch.device("cpu"), max(2, args.repeats // 5))
                row.update(cpu_f=f, cpu_fb=fb)
            rows.append(row)
            print(row, flush=True)

    cols = [("N", "N"), ("res", "resolution"), ("ssg_f", "ssgwarp CUDA fwd ms"), ("ssg_fb", "ssgwarp CUDA fwd+bwd ms"),
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
        if len(r) > 2:  # something was measured for this size
            lines.append("| " + " | ".join(fmt(r.get(c[0])) for c in cols) + " |")
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(table + "\n")


if __name__ == "__main__":
    main()
