"""Backdrops (far points and a far shell, ssgwarp.reconstruction.backdrop) and the sparse-capture schedule,
measured: held-out PSNR, Gaussians and time of `reconstruct` runs, one row per run.

Each ``--runs`` entry is ``SCENE:BACKDROP:ITERS[:WIDTH[:INIT]]``: SCENE ``livingroom`` (../shared/data/livingroom_360),
``fern4`` / ``fern8`` (LLFF fern images_4 / images_8), ``cup`` (colmap_cup), ``lego`` (lego_200, white
background), ``insideout`` (the procedural
inside-out scene, written once per width into ``--work``) or ``insideout-true`` (the same capture, initial
points = the true surface: the ground truth's Gaussian centres), or a capture folder; BACKDROP ``auto`` / ``on`` /
``off``; ITERS a step count or ``auto`` (the stop rule; the row gives the steps run); WIDTH ``-`` or left
out: the capture's own; INIT the initial points (``load_dataset``'s ``init``:
``auto`` (default: the capture's points, else triangulated), ``triangulate`` (even where the capture has
COLMAP points), ``random``, ``capture`` (the capture's points, else random: as before triangulation)).
Rows go to stdout (markdown) and ``--out`` (JSON lines).

    python benchmarks/backdrop.py --runs insideout:off:600:64 insideout:auto:600:64 --device cpu
    python benchmarks/backdrop.py --runs livingroom:auto:7000 livingroom:off:7000 insideout:auto:7000:256 \
        insideout-true:off:7000:256 insideout:off:7000:256 --out runs/backdrop.jsonl
    python benchmarks/backdrop.py --runs fern8:auto:7000:-:capture fern8:auto:7000:-:triangulate \
        fern8:auto:7000:-:random cup:auto:7000:-:capture cup:auto:7000:-:triangulate   # initial points compared
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
from shared_data import data_root  # noqa: E402

from ssgwarp.capture.datasets import load_dataset  # noqa: E402
from ssgwarp.reconstruction.trainer import Trainer  # noqa: E402

SHARED = {"livingroom": ("livingroom_360", "images"), "fern4": ("llff_fern", "images_4"),
          "fern8": ("llff_fern", "images_8"), "cup": ("colmap_cup", "images"), "lego": ("lego_200", "images")}


def inside_out_capture(folder: Path, width: int, views: int = 40, device="cpu") -> tuple[Path, torch.Tensor]:
    """The procedural inside-out capture at ``width`` (4:3), written once; returns its folder and the true
    surface points (Gaussian centres) with their colours."""
    from ssgwarp.procedural import ProceduralScene, build_inside_out, render_views, rig_cameras, write_transforms_dataset

    gt = build_inside_out(1.0)
    gt = ProceduralScene(gt.scene.to(device), gt.object_ids.to(device), gt.names)
    out = folder / f"insideout_{width}"
    if not (out / "transforms.json").is_file():
        cams = rig_cameras(views, width, width * 3 // 4)
        images, _ = render_views(gt, cams, background=(1.0, 1.0, 1.0))
        write_transforms_dataset(out, images, cams)
    return out, gt


def load(scene: str, width, work: Path, points: int, device="cpu", init="auto"):
    if scene in SHARED:
        name, images = SHARED[scene]
        bg = {"background": (1.0, 1.0, 1.0)} if scene == "lego" else {}
        return load_dataset(data_root() / name, images=images, width=width, num_random_points=points, init=init,
                            progress=False, **bg)
    if scene.startswith("insideout"):
        folder, gt = inside_out_capture(work, width or 128, device=device)
        data = load_dataset(folder, num_random_points=points, init=init, progress=False)
        if scene == "insideout-true":
            from ssgwarp.raster.scene import sh_dc_to_rgb
            data = replace(data, points=(gt.scene.means.cpu().clone(), sh_dc_to_rgb(gt.scene.sh_dc.cpu()).clamp(0, 1)),
                           points_source="true")
        return data
    return load_dataset(scene, width=width, num_random_points=points, init=init, progress=False)


def save_renders(path: Path, tr: Trainer, data) -> None:
    """Ground truth (top row) over render (bottom row) of up to three held-out views, side by side."""
    from ssgwarp.core.fileio import write_image

    ids = list(data.test_ids)[:3]
    if not ids:
        return
    pred = tr.render(ids).cpu()
    gt = torch.stack([data.images[i] for i in ids]).cpu()
    sheet = torch.cat([torch.cat(list(gt), dim=1), torch.cat(list(pred), dim=1)], dim=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, sheet)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_backdrop")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--random-points", type=int, default=100_000, help="random initial points (default 100000)")
    ap.add_argument("--renders", type=Path, default=None,
                    help="write one PNG per run: held-out views (up to 3), ground truth above, render below")
    args = ap.parse_args(argv)
    machine = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else platform.processor() or "cpu"
    print("| capture | initial points | backdrop | steps | PSNR | Gaussians | load (s) | train (s) | machine |")
    print("|---|---|---|---|---|---|---|---|---|")
    for spec in args.runs:
        parts = spec.split(":")
        scene, mode, iters = parts[0], parts[1], parts[2] if parts[2] == "auto" else int(parts[2])
        width = int(parts[3]) if len(parts) > 3 and parts[3] not in ("", "-") else None
        init = parts[4] if len(parts) > 4 else "auto"
        t0 = time.time()
        data = load(scene, width, args.work, args.random_points, args.device, init)
        load_seconds = time.time() - t0
        tr = Trainer(data, iters=iters, device=args.device, backdrop=mode, progress=False)
        tr.train()
        ev = tr.evaluate()
        row = {"capture": scene, "width": data.width, "init": init, "points": data.points_source,
               "points_count": None if data.points is None else len(data.points[0]),
               "points_reprojection_error_px": data.points_stats.get("median_reprojection_error_px"),
               "load_seconds": round(load_seconds, 1), "backdrop": mode,
               "backdrop_plan": None if tr.backdrop is None else tr.backdrop.record(), "steps": tr.step, "iters": iters,
               "psnr": ev["psnr"], "ssim": ev["ssim"], "gaussians": tr.num_gaussians,
               "train_seconds": round(tr.elapsed, 1), "wall_seconds": round(time.time() - t0, 1),
               "refine_stop": tr.recipe.refine_stop, "machine": machine, "date": time.strftime("%Y-%m-%d")}
        used = "yes" if row["backdrop_plan"] and row["backdrop_plan"]["used"] else "no"
        print(f"| {scene} {data.width}px | {row['points_count']} {data.points_source} ({init}) | {mode} ({used}) | "
              f"{tr.step}{' (auto)' if iters == 'auto' else ''} | {ev['psnr']:.2f} | {tr.num_gaussians} | {load_seconds:.0f} | {tr.elapsed:.0f} | {machine} |",
              flush=True)
        if args.renders:
            save_renders(args.renders / f"{spec.replace(':', '_')}.png", tr, data)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
