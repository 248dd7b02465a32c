"""Initial points and held-out quality: each capture reconstructed from each kind of initial points.

For every ``--scenes`` entry and every ``--init`` mode, one ``ssgwarp reconstruct`` run (the command's own
function, same seed and schedule), then a table of held-out PSNR, Gaussians, the initial points (source,
count, median reprojection error of triangulated points) and the time to load + triangulate and to train.

``--init``: ``capture`` (the capture's own COLMAP points; captures without points fall back to random, as
before triangulation existed), ``triangulate`` (points from the images and known poses, even where the
capture has COLMAP points), ``random``, ``auto`` (the default of ``ssgwarp reconstruct``).

Scenes: ``fern8`` (LLFF fern ``images_8``, COLMAP points), ``cup`` (colmap_cup, COLMAP points), ``lego``
(lego_200, no points, white background), ``living`` (livingroom_360: a 360° room capture without points),
or ``PATH[:IMAGES]``.

    python benchmarks/init_points.py --scenes fern8 cup --init capture triangulate random --iters 7000
    python benchmarks/init_points.py --scenes living lego --init auto random --iters 7000 --out init.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from shared_data import data_root  # noqa: E402

from ssgwarp.capture.datasets import load_dataset  # noqa: E402
from ssgwarp.core.fileio import write_json  # noqa: E402
from ssgwarp.reconstruction.reconstruct import reconstruct  # noqa: E402

SCENES = {"fern8": ("llff_fern", "images_8", None), "cup": ("colmap_cup", "images", None),
          "lego": ("lego_200", "images", (1.0, 1.0, 1.0)), "living": ("livingroom_360", "images", None)}


def scene_args(name: str):
    if name in SCENES:
        folder, images, background = SCENES[name]
        return data_root() / folder, images, background
    path, _, images = name.partition(":")
    return Path(path), images or "images", None


def run_one(name: str, init: str, iters: int, device, out_dir: Path, seed: int) -> dict:
    path, images, background = scene_args(name)
    t0 = time.perf_counter()
    data = load_dataset(path, images=images, init=init, seed=seed, progress=False,
                        **({} if background is None else {"background": background}))
    load_s = time.perf_counter() - t0
    out = out_dir / f"{name}-{init}"
    m = reconstruct(path, out, iters=iters, images=images, device=device, seed=seed, data=data, init=init,
                    progress=False, force=True, checkpoint_every=10 ** 9,
                    **({} if background is None else {"background": background}))
    dj = json.loads((out / "data.json").read_text())
    return dict(scene=name, init=init, iters=iters, psnr=m["psnr"], ssim=m["ssim"], gaussians=m["num_gaussians"],
                points_source=dj.get("points_source"), points_count=dj.get("points_count"),
                reprojection_px=dj.get("points_reprojection_error_px"), load_seconds=round(load_s, 1),
                train_seconds=m["train_seconds"])


def table(rows: list[dict]) -> str:
    head = ("| scene | --init | points (source) | reproj. px | steps | held-out PSNR | Gaussians | load+init s | "
            "train s |\n|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        rp = "–" if r["reprojection_px"] is None else f"{r['reprojection_px']:.2f}"
        ps = "n/a" if r["psnr"] is None else f"{r['psnr']:.2f}"
        lines.append(f"| {r['scene']} | {r['init']} | {r['points_count']:,} ({r['points_source']}) | {rp} | "
                     f"{r['iters']} | {ps} | {r['gaussians']:,} | {r['load_seconds']:.1f} | {r['train_seconds']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", default=["fern8", "cup"])
    p.add_argument("--init", nargs="+", default=["capture", "triangulate", "random"])
    p.add_argument("--iters", type=int, default=7000)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="JSON file of the rows (written atomically)")
    p.add_argument("--runs", type=Path, default=None, help="keep the run folders here (default: a temporary folder)")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        runs = args.runs or Path(tmp)
        for name in args.scenes:
            for init in args.init:
                rows.append(run_one(name, init, args.iters, torch.device(args.device), runs, args.seed))
                print(table(rows[-1:]).splitlines()[-1], flush=True)
                if args.out:
                    write_json(args.out, {"device": str(args.device), "rows": rows})
    if torch.cuda.is_available():
        print(f"\n{torch.cuda.get_device_name()}, torch {torch.__version__}")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
