"""``ssgwarp masks``: instance masks of every training view (:func:`ssgwarp.grouping.segment.make_masks`)."""
from __future__ import annotations

from pathlib import Path

from ..grouping.segment import MaskConfig, make_masks


def add_arguments(parser) -> None:
    d = MaskConfig()
    parser.add_argument("scene_dir", type=Path, help="a reconstructed run (scene.ply, cameras.json, data.json)")
    parser.add_argument("--sam", type=Path, default=None, metavar="PATH",
                        help="Segment Anything weights: a transformers SamModel folder (default: $SSGWARP_SAM, "
                             "$SSGWARP_WEIGHTS/sam-vit-base, or facebook/sam-vit-base from the Hugging Face cache, "
                             "downloaded on first use unless offline; `ssgwarp weights --download sam`)")
    parser.add_argument("--view-masks", type=Path, default=None, metavar="DIR",
                        help="associate these per-view masks (<image stem>.png, ids need not agree between views) "
                             "instead of running Segment Anything")
    parser.add_argument("--points-per-side", type=int, default=d.points_per_side,
                        help=f"prompt grid points per side (default {d.points_per_side})")
    parser.add_argument("--points-per-batch", type=int, default=d.points_per_batch,
                        help=f"prompts decoded together (default {d.points_per_batch})")
    parser.add_argument("--pred-iou-thresh", type=float, default=d.pred_iou_thresh,
                        help=f"keep masks whose predicted IoU exceeds it (default {d.pred_iou_thresh})")
    parser.add_argument("--stability-thresh", type=float, default=d.stability_thresh,
                        help=f"keep masks whose stability score exceeds it (default {d.stability_thresh})")
    parser.add_argument("--nms-thresh", type=float, default=d.nms_thresh,
                        help=f"mask IoU above which the lesser of two masks is dropped (default {d.nms_thresh})")
    parser.add_argument("--min-area", type=float, default=d.min_area,
                        help=f"drop masks smaller than this share of the view (default {d.min_area})")
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="where the run's capture is now (default: the folder recorded in data.json)")
    parser.add_argument("--resume", action="store_true", help="keep the views already segmented (sam_masks/)")
    parser.add_argument("--force", action="store_true", help="make the masks again if the run has them")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args) -> int:
    cfg = MaskConfig(points_per_side=args.points_per_side, points_per_batch=args.points_per_batch,
                     pred_iou_thresh=args.pred_iou_thresh, stability_thresh=args.stability_thresh,
                     nms_thresh=args.nms_thresh, min_area=args.min_area)
    wcfg = getattr(args, "weights", None)
    rec = make_masks(args.scene_dir, sam=args.sam, view_masks=args.view_masks, config=cfg,
                     weights_config=wcfg if isinstance(wcfg, dict) else None, data_dir=args.data_dir,
                     device=args.device, force=args.force, resume=args.resume, progress=not args.quiet)
    n = sum(v["masks"] for v in rec["segmented_views"])
    print(f"masks for {args.scene_dir}: {n} masks in {len(rec['segmented_views'])} views -> "
          f"{rec['num_instances']} instances across views ({rec['source']['kind']}); "
          f"wrote {Path(args.scene_dir) / 'object_mask'} and {Path(args.scene_dir) / 'masks.json'} "
          f"in {rec['seconds']['total']:.1f} s")
    return 0
