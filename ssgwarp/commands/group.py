"""``ssgwarp group``: Gaussian Grouping of a run (:func:`ssgwarp.grouping.stage.group_scene`)."""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..grouping.model import DEFAULT_DIM, GroupConfig
from ..grouping.stage import group_scene


def add_arguments(parser) -> None:
    parser.add_argument("scene_dir", type=Path, help="a reconstructed run (scene.ply, cameras.json, data.json)")
    parser.add_argument("--masks", default="auto",
                        help="folder of instance masks <image stem>.png (integer ids consistent across views); "
                             "'auto' (default): RUN/object_mask (from `ssgwarp masks`), else <data_dir>/object_mask, "
                             "when it exists, else mask-free; 'none': always mask-free")
    parser.add_argument("--groups", type=int, default=None, metavar="K",
                        help="number of groups (default: from the masks, or chosen per scene when mask-free)")
    parser.add_argument("--max-groups", type=int, default=8, metavar="CAP",
                        help="mask-free: the largest K considered (default 8)")
    parser.add_argument("--joint", action="store_true",
                        help="train identities jointly with a new reconstruction (re-runs reconstruct from data_dir)")
    parser.add_argument("--iters", type=int, default=None,
                        help=f"training steps (default {GroupConfig.iters} for the frozen-geometry stage; with "
                             "--joint: the reconstruction's own step count)")
    parser.add_argument("--dim", type=int, default=DEFAULT_DIM, metavar="E", help="identity length (default 16)")
    parser.add_argument("--reg-weight", type=float, default=GroupConfig.reg_weight,
                        help="weight of the 3D KL regulariser (0 = off)")
    parser.add_argument("--ignore-id", type=int, default=None,
                        help="a mask value meaning 'unlabelled' (those pixels are not trained on)")
    parser.add_argument("--resume", action="store_true", help="continue from groups/checkpoint.pt")
    parser.add_argument("--force", action="store_true", help="group again even if groups/ exists")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    from ..core.presets import add_quick
    add_quick(parser, QUICK, QUICK_MEASURED)


# the CPU-sized preset (`--quick`) and what it cost, measured (README, docs)
QUICK = {"iters": 300}


QUICK_MEASURED = ("fern reconstructed with reconstruct --quick (42,688 Gaussians, 17 views 252x188): 6 min on 2 CPU "
                  "cores shared with other work (1.7 min of CPU time), 2026-11-28")


def run(args) -> int:
    if args.iters is not None and args.iters < 0:
        raise InputError(f"--iters must be >= 0, got {args.iters}")
    cfg = GroupConfig(dim=args.dim, reg_weight=args.reg_weight,
                      iters=args.iters if (args.iters is not None and not args.joint) else GroupConfig.iters)
    rk = {"iters": args.iters} if args.joint and args.iters is not None else None
    info = group_scene(args.scene_dir, masks=args.masks, num_groups=args.groups, max_groups=args.max_groups,
                       joint=args.joint, config=cfg, ignore_id=args.ignore_id, force=args.force,
                       resume=args.resume, device=args.device, seed=args.seed, progress=not args.quiet,
                       reconstruct_kwargs=rk)
    ra = info.get("reprojection_agreement", {}).get("mean")
    acc = info.get("train_mask_accuracy")
    print(f"grouped {args.scene_dir}: K={info['num_groups']} {info['kind']} ({info['method']}); "
          f"mask accuracy {acc if acc is None else f'{acc:.3f}'}; "
          f"cross-view agreement {ra if ra is None else f'{ra:.3f}'}; "
          f"wrote {Path(args.scene_dir) / 'groups'}")
    return 0
