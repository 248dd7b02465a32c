"""Where a backward follows on CUDA: the per-intersection gather, or both passes through the sorted ids.

``ssgwarp.raster.blend_ops.IDS_BACKWARD_MAX`` decides, by the call's intersection count, whether the
blending forward gathers each intersection's splat and colour (one launch, two buffers; the
backward then reads them contiguously) or reads the projection's packed splats and the colours
through the sorted ids in both passes (no gather; the backward adds the colours' gradients into rows
of their own). This script times forward+backward both ways on the issue's five cases (``raster.py``),
in one process and in turns, and splits each way's GPU time by kernel: the threshold is where the
backward's slower reads through the ids start to cost more than the gather saves.

    python benchmarks/blend_ids.py                # CUDA only
    python benchmarks/blend_ids.py --repeats 60
"""
from __future__ import annotations

import argparse

import torch

from blend_forward import kernel_split
from raster import CASES, closures, cuda_only, interleaved, with_setting

import ssgwarp
from ssgwarp.raster import blend_ops

WAYS = {"gather": 0, "ids": 1 << 62}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=40)
    args = ap.parse_args()
    dev = cuda_only("blend_ids.py", "compares CUDA kernels")
    lines = ["| N | image | SH | cameras | intersections | fwd+bwd ms, gather | fwd+bwd ms, ids | ids / gather | "
             "GPU ms, gather | GPU ms, ids | blending backward kernel ms, gather / ids | default |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for n, w, h, deg, cams in CASES["issue"]:
        fns = {way: with_setting(closures(ssgwarp.rasterization, n, w, h, dev, sh_degree=deg, cameras=cams)[1],
                                 blend_ops, "IDS_BACKWARD_MAX", limit)
               for way, limit in WAYS.items()}
        t = interleaved(fns, dev, args.repeats)
        gpu = {way: kernel_split(fn) for way, fn in fns.items()}
        back = {way: sum(ms for name, ms in top if name.startswith("reduced_backward")) for way, (_, top) in gpu.items()}
        f, _ = closures(ssgwarp.rasterization, n, w, h, dev, sh_degree=deg, cameras=cams)
        M = f()[2]["flatten_ids"].numel()
        lines.append(f"| {n:,} | {w}x{h} | {deg if deg is not None else 'colours'} | {cams} | {M:,} | "
                     f"{t['gather']:.2f} | {t['ids']:.2f} | {t['ids'] / t['gather']:.3f} | {gpu['gather'][0]:.3f} | "
                     f"{gpu['ids'][0]:.3f} | {back['gather']:.3f} / {back['ids']:.3f} | "
                     f"{'ids' if M <= blend_ops.IDS_BACKWARD_MAX else 'gather'} |")
        print(lines[-1], flush=True)
    print(f"\ndevice: {torch.cuda.get_device_name()}; torch {torch.__version__}; "
          f"IDS_BACKWARD_MAX = {blend_ops.IDS_BACKWARD_MAX:,}\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
