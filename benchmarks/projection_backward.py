"""The projection backward on CUDA: the hand-written kernel against Warp's generated adjoint, with gsplat.

On the issue's five cases (``raster.py``), in one process and in turns:

1. the projection alone (``ssgwarp.raster.ops.project_warp`` forward + backward of fixed random output
   gradients; gsplat's ``fully_fused_projection``, which takes no opacities, the same way): milliseconds per
   call and the backward kernel's GPU time (torch profiler);
2. whole renders, forward+backward (``image.sum() + alpha.sum()``): ssgwarp with the hand kernel
   (``ops.HAND_BACKWARD = True``, the default) and with Warp's adjoint, and gsplat; ratios to gsplat.

    python benchmarks/projection_backward.py
    python benchmarks/projection_backward.py --repeats 60 --no-gsplat
"""
from __future__ import annotations

import argparse

import torch

from raster import CASES, camera, closures, cuda_only, interleaved, make_scene, optional_gsplat, with_setting
from timing import cuda_kernel_ms

import ssgwarp
from ssgwarp import RasterSettings
from ssgwarp.raster import ops


KINDS = (("hand", True), ("adj", False))  # the two projection backwards: ops.HAND_BACKWARD on / off


def projection_closure(gsplat, n, w, h, cameras, dev):
    """Forward + backward of the projection alone (ssgwarp's, or gsplat's with ``gsplat``)."""
    params = make_scene(n, dev)
    vm, K = camera(w, h, dev, cameras=cameras)
    means, quats, scales, opac = [p.clone().requires_grad_(True) for p in params[:4]]
    g = torch.Generator(device="cpu").manual_seed(1)
    grads = [torch.randn(cameras, n, k, generator=g).to(dev).squeeze(-1) for k in (2, 1, 3, 1)]

    def run():
        for p in (means, quats, scales, opac):
            p.grad = None
        if gsplat is None:
            _, m2, d, con, op = ops.project_warp(means, quats, scales, opac, vm, K, w, h, settings=RasterSettings())
            torch.autograd.backward([m2, d, con, op], grads)
        else:
            _, m2, d, con, _ = gsplat.fully_fused_projection(means, None, quats, scales, vm, K, w, h, packed=False)
            torch.autograd.backward([m2, d, con], grads[:3])
    return run


def backward_kernel_ms(fn, calls: int = 5) -> float:
    """GPU milliseconds per call of ``fn``'s projection backward kernels (torch profiler)."""
    return sum(ms for name, ms in cuda_kernel_ms(fn, calls).items() if "backward" in name or "bwd" in name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--no-gsplat", action="store_true")
    args = ap.parse_args()
    dev = cuda_only("projection_backward.py", "compares CUDA kernels")
    gsplat = optional_gsplat(args.no_gsplat)
    proj = ["| N | cameras | projection fwd+bwd ms: hand / Warp adjoint / gsplat | backward kernel ms: hand / "
            "Warp adjoint / gsplat |", "|---|---|---|---|"]
    full = ["| N | image | SH | cameras | fwd+bwd ms: hand / Warp adjoint / gsplat | ratio to gsplat: hand / "
            "Warp adjoint |", "|---|---|---|---|---|---|"]
    profiled = []  # (the profiler runs last: it slows the host side of later calls in the process)
    for n, w, h, deg, cams in CASES["issue"]:
        fns = {k: with_setting(projection_closure(None, n, w, h, cams, dev), ops, "HAND_BACKWARD", hand)
               for k, hand in KINDS}
        if gsplat is not None:
            fns["gs"] = projection_closure(gsplat, n, w, h, cams, dev)
        t = interleaved(fns, dev, args.repeats)
        profiled.append((n, cams, t, fns))

        case = dict(sh_degree=deg, cameras=cams)
        fns = {k: with_setting(closures(ssgwarp.rasterization, n, w, h, dev, **case)[1], ops, "HAND_BACKWARD", hand)
               for k, hand in KINDS}
        if gsplat is not None:
            fns["gs"] = closures(gsplat.rasterization, n, w, h, dev, packed=False, **case)[1]
        t = interleaved(fns, dev, args.repeats)
        cell = " / ".join(f"{t[k]:.2f}" if k in t else "-" for k in ("hand", "adj", "gs"))
        ratio = f"{t['hand'] / t['gs']:.2f} / {t['adj'] / t['gs']:.2f}" if "gs" in t else "-"
        full.append(f"| {n:,} | {w}x{h} | {deg if deg is not None else 'colours'} | {cams} | {cell} | {ratio} |")
        print(full[-1], flush=True)
    for n, cams, t, fns in profiled:
        kern = {k: backward_kernel_ms(fn) for k, fn in fns.items()}
        cell = " / ".join(f"{t[k]:.3f}" if k in t else "-" for k in ("hand", "adj", "gs"))
        kcell = " / ".join(f"{kern[k]:.3f}" if k in kern else "-" for k in ("hand", "adj", "gs"))
        proj.append(f"| {n:,} | {cams} | {cell} | {kcell} |")
        print(proj[-1], flush=True)
    print(f"\ndevice: {torch.cuda.get_device_name()}; torch {torch.__version__}; "
          f"gsplat {getattr(gsplat, '__version__', 'n/a')}\n")
    print("\n".join(proj) + "\n\n" + "\n".join(full))


if __name__ == "__main__":
    main()
