"""The blending forward on CUDA: one block per tile (the default) against the per-pixel walk, with gsplat.

On the issue's five cases (``raster.py``), in one process and in turns: ssgwarp with
``ssgwarp.raster.blend_ops.BATCHED`` off (the per-intersection gather, then one thread per pixel walking
it) and on (one block per tile: through the sorted ids without a gather when no backward can follow,
else from the gather), and gsplat 1.5.3. Per case: forward and
forward+backward milliseconds (median of synchronised calls), their ratios to gsplat, the largest
image difference between the two ssgwarp paths (0: they are bit-identical) and, with ``--kernels``,
each pass's GPU kernel time split by kernel (torch profiler).

    python benchmarks/blend_forward.py                # CUDA only
    python benchmarks/blend_forward.py --repeats 40 --kernels
"""
from __future__ import annotations

import argparse

import torch

from raster import CASES, closures, cuda_only, interleaved, optional_gsplat, with_setting
from timing import cuda_kernel_ms

import ssgwarp
from ssgwarp.raster import blend_ops


def kernel_split(fn, calls: int = 5) -> tuple[float, list]:
    """(GPU milliseconds per call, the six longest kernels with their milliseconds per call)."""
    per: dict = {}
    for name, ms in cuda_kernel_ms(fn, calls).items():
        per[name[:50]] = per.get(name[:50], 0.0) + ms
    return sum(per.values()), sorted(per.items(), key=lambda kv: -kv[1])[:6]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--kernels", action="store_true", help="also split each pass's GPU time by kernel")
    ap.add_argument("--no-gsplat", action="store_true")
    args = ap.parse_args()
    dev = cuda_only("blend_forward.py", "compares CUDA kernels")
    gsplat = optional_gsplat(args.no_gsplat)
    lines = ["| N | image | SH | cameras | per-pixel walk fwd / fwd+bwd ms | block per tile fwd / fwd+bwd ms | "
             "gsplat fwd / fwd+bwd ms | walk ratio fwd / fwd+bwd | block ratio fwd / fwd+bwd | max image diff walk vs block |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for n, w, h, deg, cams in CASES["issue"]:
        case = dict(sh_degree=deg, cameras=cams)
        fns = {}
        for on, name in ((False, "walk"), (True, "block")):
            f, fb = closures(ssgwarp.rasterization, n, w, h, dev, packed=False, **case)
            fns[name + "_f"], fns[name + "_fb"] = (with_setting(f, blend_ops, "BATCHED", on),
                                                   with_setting(fb, blend_ops, "BATCHED", on))
        if gsplat is not None:
            fns.update(zip(("gs_f", "gs_fb"), closures(gsplat.rasterization, n, w, h, dev, packed=False, **case)))
        t = interleaved(fns, dev, args.repeats)
        diff = float((fns["walk_f"]()[0] - fns["block_f"]()[0]).abs().max())

        def ratio(k):
            return f"{t[k + '_f'] / t['gs_f']:.2f} / {t[k + '_fb'] / t['gs_fb']:.2f}" if gsplat is not None else "-"

        gs = f"{t['gs_f']:.2f} / {t['gs_fb']:.2f}" if gsplat is not None else "-"
        lines.append(f"| {n:,} | {w}x{h} | {deg if deg is not None else 'colours'} | {cams} | "
                     f"{t['walk_f']:.2f} / {t['walk_fb']:.2f} | {t['block_f']:.2f} / {t['block_fb']:.2f} | {gs} | "
                     f"{ratio('walk')} | {ratio('block')} | {diff:.1e} |")
        print(lines[-1], flush=True)
        if args.kernels:
            for name in [k for k in fns if not k.startswith("gs")] + [k for k in fns if k.startswith("gs")]:
                total, top = kernel_split(fns[name])
                print(f"    {name}: GPU {total:.3f} ms; " + "; ".join(f"{k} {v:.3f}" for k, v in top), flush=True)
    print(f"\ndevice: {torch.cuda.get_device_name()}; torch {torch.__version__}; "
          f"gsplat {getattr(gsplat, '__version__', 'n/a')}\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
