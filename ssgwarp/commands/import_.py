"""``ssgwarp import``: splats trained elsewhere as a run (:func:`ssgwarp.reconstruction.importer.import_splats`)."""
from __future__ import annotations

import logging
from pathlib import Path

from ..errors import InputError
from ..reconstruction.importer import TOOLS, ImportConfig, import_splats


def add_arguments(parser) -> None:
    from .reconstruct import parse_background as _background

    parser.add_argument("source", type=Path, help="a graphdeco 3DGS output folder, a gsplat result folder or "
                        "checkpoint (.pt), a nerfstudio `ns-export gaussian-splat` PLY, or any splat file (3DGS "
                        "PLY, compressed PLY, SPZ, .splat; without --data: cameras made around its splats)")
    parser.add_argument("--out", type=Path, required=True, help="run folder to write")
    parser.add_argument("--data", type=Path, default=None,
                        help="the capture the splats were trained on (COLMAP, LLFF or transforms.json folder); "
                             "graphdeco: default cfg_args' source_path; gsplat: default cfg.yml's data_dir")
    parser.add_argument("--tool", choices=TOOLS, default=None, help="the layout of SOURCE (default: detected)")
    parser.add_argument("--iteration", type=int, default=None,
                        help="graphdeco iteration / gsplat step to import (default: the last)")
    parser.add_argument("--dataparser-transforms", type=Path, default=None,
                        help="nerfstudio: the training run's dataparser_transforms.json (default: beside the PLY)")
    parser.add_argument("--images", default=None, help="image sub-folder of the capture (default: the tool's: "
                        "cfg_args' images, gsplat's images_<data_factor>, else images)")
    parser.add_argument("--width", type=int, default=None,
                        help="resize the images to this width (default: graphdeco's --resolution rule, else as loaded)")
    parser.add_argument("--split-every", type=int, default=None,
                        help="hold out every N-th view (default: the tool's split: graphdeco --eval 8 else 0, "
                             "gsplat test_every, else 8)")
    parser.add_argument("--background", type=_background, default=None,
                        help="white, black or R,G,B (default: graphdeco's white_background, else white)")
    parser.add_argument("--views", type=int, default=24,
                        help="a splat file without --data: the cameras made around its splats (default 24)")
    parser.add_argument("--up", default="auto", help="a splat file without --data: its up axis: auto (default: the "
                        "thinnest principal axis of a layer of splats, else the file's -y), +z, -y ... or x,y,z")
    parser.add_argument("--force", action="store_true", help="overwrite an existing run in OUT")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format="ssgwarp: %(message)s")
    if args.split_every is not None and args.split_every < 0:
        raise InputError(f"--split-every must be >= 0, got {args.split_every}")
    config = ImportConfig(data=args.data, tool=args.tool, iteration=args.iteration, images=args.images,
                          width=args.width, split_every=args.split_every, background=args.background,
                          dataparser_transforms=args.dataparser_transforms, up=args.up, views=args.views,
                          seed=args.seed)
    m = import_splats(args.source, args.out, config, force=args.force, device=args.device, progress=not args.quiet)
    fmt = lambda v: "n/a" if v is None else f"{v:.2f} dB"  # noqa: E731
    print(f"{args.out}: {m['num_gaussians']} Gaussians imported from {m['imported']['tool']} "
          f"({m['imported']['frame']}), held-out PSNR {fmt(m['psnr'])}, train PSNR {fmt(m['train_psnr'])}")
    return 0
