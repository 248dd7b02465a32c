"""Inside-out captures with sky, measured: where the held-out error sits, region by region, on the procedural
inside-out capture with known truth (``ssgwarp.procedural.build_inside_out(railing=True)``: ground, a ring of
buildings, a sky dome, a railing close to the rig; cameras in the middle looking outward).

Per held-out view the ground truth's object ids say which region each pixel shows; each row gives the PSNR
over the pixels of each region (ground, buildings, sky, railing), the whole image's, and the floaters: pixels
whose rendered expected depth is less than half the true depth where the render is opaque (alpha > 0.5),
their share of the image and their PSNR. Each ``--runs`` entry is ``SKY:ITERS`` (``SKY``: ``reconstruct
--sky`` auto / on / off).

    python benchmarks/inside_out.py --runs off:600 on:600 --width 96 --views 36 --device cpu
    python benchmarks/inside_out.py --runs off:7000 on:7000 auto:7000 --width 256 --views 40   # GPU
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssgwarp.capture.datasets import load_dataset  # noqa: E402
from ssgwarp.procedural import (build_inside_out, render_views, rig_cameras,  # noqa: E402
                                write_transforms_dataset)
from ssgwarp.raster.rendering import render_views as render_depth  # noqa: E402
from ssgwarp.reconstruction.trainer import Trainer  # noqa: E402

REGIONS = {"ground": 0, "buildings": 1, "sky": 2, "railing": 3}


def capture(work: Path, width: int, views: int, density: float = 1.0):
    """The capture written once into ``work`` (transforms.json), its truth (scene, ids, depths of every view)."""
    gt = build_inside_out(density, railing=True)
    cams = rig_cameras(views, width, width * 3 // 4)
    images, ids = render_views(gt, cams)
    depth = render_depth(gt.scene, cams, depth=True).depth
    folder = work / f"insideout_railing_{width}_{views}"
    if not (folder / "transforms.json").is_file():
        write_transforms_dataset(folder, images, cams)
    return folder, ids, depth


def _psnr(se: torch.Tensor, n: torch.Tensor) -> float:
    return float("nan") if float(n) == 0 else -10.0 * math.log10(max(float(se / (3 * n)), 1e-10))


def breakdown(tr: Trainer, data, ids: torch.Tensor, depth: torch.Tensor) -> dict:
    """Per-region PSNR and floaters over the held-out views (``ids``, ``depth``: the truth of every view)."""
    se = {k: torch.zeros(()) for k in [*REGIONS, "all", "floaters"]}
    n = {k: torch.zeros(()) for k in se}
    for i in data.test_ids:
        pred = tr.render_final([i])[0].cpu() if hasattr(tr, "render_final") else tr.render([i])[0].cpu()
        gt = data.images[i].cpu()
        err = ((pred - gt) ** 2).sum(-1)
        v = render_depth(tr.scene.detach(), data.cameras[i], depth=True)
        d, a = v.depth[0].cpu(), v.alpha[0].cpu()
        regions = {k: ids[i] == r for k, r in REGIONS.items()}
        regions["all"] = torch.ones_like(err, dtype=torch.bool)
        regions["floaters"] = (a > 0.5) & (d < 0.5 * depth[i].cpu())
        for k, m in regions.items():
            se[k] += err[m].sum()
            n[k] += m.sum()
    total = sum(float(n["all"]) for _ in [0])
    out = {f"psnr_{k}": round(_psnr(se[k], n[k]), 2) for k in se}
    out["floater_share"] = round(float(n["floaters"]) / total, 4)
    out["region_share"] = {k: round(float(n[k]) / total, 3) for k in REGIONS}
    out["error_share"] = {k: round(float(se[k] / se["all"]), 3) for k in [*REGIONS, "floaters"]}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=["off:600", "on:600"])
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--views", type=int, default=36, help="views of the rig (every 8th held out)")
    ap.add_argument("--density", type=float, default=1.0, help="ground-truth Gaussians (x about 30,000)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_inside_out")
    ap.add_argument("--out", type=Path, default=None, help="append JSON lines here")
    ap.add_argument("--renders", type=Path, default=None, help="one PNG per run: held-out truth above, render below")
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    folder, ids, depth = capture(args.work, args.width, args.views, args.density)
    data = load_dataset(folder, progress=False, device=args.device)
    machine = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else platform.processor() or "cpu"
    print("| sky | steps | PSNR all | ground | buildings | sky | railing | floaters (share, PSNR) | Gaussians | "
          "train (s) | machine |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for spec in args.runs:
        sky, iters = spec.split(":")
        kw = {} if sky == "none" else {"sky": sky}
        tr = Trainer(data, iters=int(iters), device=args.device, progress=False, **kw)
        tr.train()
        b = breakdown(tr, data, ids, depth)
        ev = tr.evaluate()
        rec = getattr(tr, "sky_record", None)
        row = {"sky": sky, "sky_record": rec, "iters": int(iters), "width": args.width, "views": args.views,
               "psnr": ev["psnr"], **b, "gaussians": tr.num_gaussians, "train_seconds": round(tr.elapsed, 1),
               "backdrop": None if tr.backdrop is None else tr.backdrop.record(), "machine": machine,
               "date": time.strftime("%Y-%m-%d")}
        print(f"| {sky}{'' if rec is None else ' (' + ('on' if rec['use'] else 'off') + ')'} | {iters} | "
              f"{ev['psnr']:.2f} | {b['psnr_ground']:.2f} | {b['psnr_buildings']:.2f} | {b['psnr_sky']:.2f} | "
              f"{b['psnr_railing']:.2f} | {100 * b['floater_share']:.1f} %, {b['psnr_floaters']:.2f} | "
              f"{tr.num_gaussians} | {tr.elapsed:.0f} | {machine} |", flush=True)
        print("    error share:", b["error_share"], "region share:", b["region_share"], flush=True)
        if args.renders:
            from ssgwarp.core.fileio import write_image

            t = list(data.test_ids)[:4]
            pred = torch.cat([tr.render([i])[0].cpu() for i in t], 1)
            truth = torch.cat([data.images[i].cpu() for i in t], 1)
            args.renders.mkdir(parents=True, exist_ok=True)
            write_image(args.renders / f"{spec.replace(':', '_')}.png", torch.cat([truth, pred], 0))
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
