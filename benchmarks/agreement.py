"""Agreement with gsplat 1.5.3, stage by stage, on the issue's benchmark scene (CUDA + gsplat needed).

For each (N, resolution): the largest image difference and the number of values off by more than
1e-4; the share of visible Gaussians whose projected means, conics, opacities, depths and radii are
bit-identical to gsplat's; and the image difference when gsplat's own projection is fed through
ssgwarp's binning and blending (the blending alone).

    python benchmarks/agreement.py
    python benchmarks/agreement.py --cases 100000x1920x1080
"""
from __future__ import annotations

import argparse
import math

import torch

import ssgwarp
from raster import camera, make_scene
from ssgwarp import RasterSettings
from ssgwarp.raster import blend_ops, ops


def compare(n: int, w: int, h: int, gsplat) -> None:
    dev = torch.device("cuda")
    means, quats, scales, opac, colors = make_scene(n, dev)
    vm, K = camera(w, h, dev)
    with torch.no_grad():
        img, _, ours = ssgwarp.rasterization(means, quats, scales, opac, colors, vm, K, w, h)
        gimg, _, theirs = gsplat.rasterization(means, quats, scales, opac, colors, vm, K, w, h, packed=False)
    d = (img - gimg).abs()
    print(f"\nN={n:,} {w}x{h}: image max abs diff {float(d.max()):.2e}, values off by > 1e-4: {int((d > 1e-4).sum())}")
    vis = (ours["radii"] > 0).all(-1) & (theirs["radii"] > 0).all(-1)
    print(f"  visible: ssgwarp {int((ours['radii'] > 0).all(-1).sum()):,}, gsplat "
          f"{int((theirs['radii'] > 0).all(-1).sum()):,}, both {int(vis.sum()):,}")
    for key in ("radii", "means2d", "conics", "opacities", "depths"):
        a, b = ours[key][vis], theirs[key][vis]
        same = (a == b).reshape(a.shape[0], -1).all(-1).float().mean()
        print(f"  {key:10s} bit-identical share {float(same):.6f}")
    tw, th = math.ceil(w / 16), math.ceil(h / 16)
    with torch.no_grad():
        tiles = ops.bin_tiles(theirs["means2d"].contiguous(), theirs["radii"].to(torch.int32).contiguous(),
                              theirs["depths"].contiguous(), 16, tw, th)
        mixed = blend_ops.blend_warp(theirs["means2d"].contiguous(), theirs["conics"].contiguous(),
                               colors[None].contiguous(), theirs["opacities"].contiguous(), None, tiles, w, h, 16,
                               RasterSettings().for_dtype(torch.float32))[0]
    d = (mixed - gimg).abs()
    print(f"  gsplat's projection through ssgwarp's blending: max abs diff {float(d.max()):.2e}, "
          f"values off by > 1e-4: {int((d > 1e-4).sum())}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=["100000x1920x1080", "1000000x1920x1080"])
    args = ap.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("agreement.py compares CUDA renders with gsplat: it needs a GPU")
    import gsplat
    print(f"device: {torch.cuda.get_device_name()}; gsplat {gsplat.__version__}")
    for case in args.cases:
        compare(*(int(v) for v in case.split("x")), gsplat)


if __name__ == "__main__":
    main()
