"""Timing of ``ssgwarp masks``: Segment Anything on every training view + cross-view association.

Target (issue 19): masks + association for LLFF fern ``images_4`` (17 training views, 1008x756) under
2 minutes on one H100 with Segment Anything at ViT-B sizes. Random weights time the same as trained ones
(the same layers run); the weights are a ``SamModel(SamConfig())`` (ViT-B image encoder at 1024², the
``facebook/sam-vit-base`` architecture) saved with ``save_pretrained`` and loaded back as ``ssgwarp masks``
loads it.

A random model's predicted IoUs are tiny, so the paper's filters (predicted IoU > 0.88, stability > 0.95)
drop every candidate and the association has nothing to do. The ``all candidates`` rows therefore turn
the filters off: every one of the 32x32 x 3 candidates of a view goes through non-maximum suppression and
the surviving masks (hundreds per view) through the association, more work than trained weights cause.
The ``paper filters`` row keeps the defaults.

The reconstruction is given (``--run``) or made first (``--recon-iters`` steps of ``ssgwarp reconstruct``,
not timed). Prints a markdown table and writes it with the raw records to ``--out``.

    python benchmarks/masks.py --out masks.json                                        # GPU: fern images_4
    python benchmarks/masks.py --run runs/fern4 --out masks.json                       # an existing run
    python benchmarks/masks.py --images images_8 --views 3 --size tiny --recon-iters 30 --points 8   # CPU check
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]

from shared_data import data_root  # noqa: E402
from ssgwarp.core.fileio import atomic_path  # noqa: E402
from ssgwarp.grouping.segment import MaskConfig, load_sam, make_masks  # noqa: E402

DEFAULT_DATA = data_root() / "llff_fern"


def save_random_sam(size: str, folder: Path) -> None:
    """A random-weight SamModel in ``folder`` (``save_pretrained``): ``SamConfig()`` is ViT-B
    (``facebook/sam-vit-base``'s sizes); ``tiny`` is the tests' 64 px model (CPU checks)."""
    if size == "tiny":
        sys.path.insert(0, str(ROOT / "tests"))
        from fakeweights import save_tiny_sam

        save_tiny_sam(folder)
        return
    from transformers import SamConfig, SamModel

    torch.manual_seed(0)
    SamModel(SamConfig()).save_pretrained(folder)


def build_run(args, work: Path, device: torch.device) -> Path:
    from ssgwarp.reconstruction.reconstruct import reconstruct

    run = work / f"run_{args.images}_{args.recon_iters}"
    if (run / "scene.ply").is_file():
        print(f"reusing the reconstruction {run}")
        return run
    t0 = time.perf_counter()
    m = reconstruct(args.data, run, images=args.images, iters=args.recon_iters, max_images=args.views,
                    device=device, progress=True, force=True)
    print(f"reconstructed {args.data.name}/{args.images} in {time.perf_counter() - t0:.1f} s: "
          f"{m['num_gaussians']} Gaussians, held-out PSNR {m['psnr']:.2f} dB")
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the capture (default: shared fern)")
    ap.add_argument("--images", default="images_4", help="image folder (default images_4: 1008x756)")
    ap.add_argument("--views", type=int, default=None, help="use only the first N images (CPU checks)")
    ap.add_argument("--run", type=Path, default=None, help="an existing reconstruction of the capture")
    ap.add_argument("--recon-iters", type=int, default=3000, help="steps of the quick reconstruction (default 3000)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/ssgwarp-bench-masks"), help="scratch folder")
    ap.add_argument("--size", choices=("vit-b", "tiny"), default="vit-b", help="SamModel sizes (default vit-b)")
    ap.add_argument("--points", type=int, default=32, help="prompt grid points per side (default 32)")
    ap.add_argument("--batch", type=int, default=64, help="prompts decoded together (default 64)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", type=Path, default=None, help="write the table and raw records (JSON) here")
    args = ap.parse_args()
    device = torch.device(args.device)
    args.work.mkdir(parents=True, exist_ok=True)
    run = args.run if args.run is not None else build_run(args, args.work, device)

    sam_dir = args.work / f"sam-{args.size}"
    if not (sam_dir / "config.json").is_file():
        save_random_sam(args.size, sam_dir)
    t0 = time.perf_counter()
    sam = load_sam(sam_dir, device)
    load_s = time.perf_counter() - t0
    params = sum(p.numel() for p in sam.model.parameters())

    everything = MaskConfig(points_per_side=args.points, points_per_batch=args.batch, pred_iou_thresh=0.0,
                            stability_thresh=0.0)
    paper = MaskConfig(points_per_side=args.points, points_per_batch=args.batch)
    rows, records = [], []
    for name, cfg in (("all candidates (cold)", everything), ("all candidates", everything),
                      ("paper filters", paper)):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            torch.cuda.reset_peak_memory_stats(device)
        rec = make_masks(run, config=cfg, segmenter=sam, device=device, force=True, progress=False)
        peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None
        sec = rec["seconds"]
        views = rec["segmented_views"]
        masks = sum(v["masks"] for v in views)
        a = rec["association"]
        row = {"setting": name, "views": len(views), "size": f"{len(rec['views'])} cameras",
               "masks_per_view": masks / max(1, len(views)), "instances": rec["num_instances"],
               "gaussians": a["gaussians"], "segment_s": sec["segment"], "associate_s": sec["associate"],
               "masks_plus_association_s": sec["segment"] + sec["associate"], "total_s": sec["total"],
               "peak_gib": peak}
        rows.append(row)
        records.append({"setting": name, "record": rec})
        print(f"{name}: {row['masks_plus_association_s']:.1f} s (SAM {sec['segment']:.1f} s, "
              f"association {sec['associate']:.1f} s), {masks} masks -> {rec['num_instances']} instances")

    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    head = (f"`ssgwarp masks` on {args.data.name}/{args.images} ({rows[0]['views']} training views), SamModel "
            f"{args.size} ({params / 1e6:.1f} M parameters, random weights, loaded in {load_s:.1f} s), "
            f"{args.points}x{args.points} prompts in batches of {args.batch}, {dev_name}\n\n")
    table = ("| setting | masks / view | instances | Gaussians | SAM s | association s | masks + association s "
             "| peak GiB |\n|---|---|---|---|---|---|---|---|\n")
    for r in rows:
        pk = "n/a" if r["peak_gib"] is None else f"{r['peak_gib']:.1f}"
        table += (f"| {r['setting']} | {r['masks_per_view']:.0f} | {r['instances']} | {r['gaussians']} | "
                  f"{r['segment_s']:.1f} | {r['associate_s']:.1f} | {r['masks_plus_association_s']:.1f} | {pk} |\n")
    print("\n" + head + table)
    if args.out is not None:
        with atomic_path(args.out) as tmp:
            tmp.write_text(json.dumps({"table": head + table, "rows": rows, "device": dev_name,
                                       "sam_parameters": params, "sam_load_s": load_s,
                                       "records": records}, indent=1, default=str))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
