"""``ssgwarp evaluate``: consistency and style / content metrics of runs
(:func:`ssgwarp.evaluation.evaluate.evaluate_run`)."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..core.fileio import atomic_path
from ..errors import SsgwarpError
from ..evaluation.evaluate import (VIEW_SETS, WARPS, EvalOptions, claim_evaluation, evaluate_run, inspect_run,
                                   load_models, style_line)
from ..evaluation.table import comparison_table, default_table_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR",
                   help="reconstruction or stylize output folders (compared side by side)")
    p.add_argument("--style", type=Path, default=None,
                   help="style image for the Gram loss (default: the one a stylize run recorded)")
    p.add_argument("--pairs", default="short,long", help="consistency pairs: short, long or short,long")
    p.add_argument("--gap", type=int, default=7, help="view gap of long-range pairs (clamped to the views)")
    p.add_argument("--max-pairs", type=int, default=16, help="pairs per kind, evenly spread (0: all)")
    p.add_argument("--views", choices=VIEW_SETS, default="path",
                   help="views scored: path = novel views on a smooth path through the training cameras "
                        "(default, as the papers score), test = held-out captured views, train = training views, "
                        "all = every captured view (the former default)")
    p.add_argument("--path-frames", type=int, default=30, help="frames of the novel-view path (--views path)")
    p.add_argument("--max-side", type=int, default=0,
                   help="evaluate at this longer image side (0: the training resolution)")
    p.add_argument("--depth-tol", type=float, default=0.02, help="relative depth tolerance of the occlusion test")
    p.add_argument("--alpha-min", type=float, default=0.9, help="render alpha below this is not compared")
    p.add_argument("--warp", choices=WARPS, default="auto",
                   help="reprojection (exact, no weights), flow (RAFT + softmax splatting), both, or auto "
                        "(reprojection, plus flow when RAFT weights are found)")
    p.add_argument("--flow-iters", type=int, default=12, help="RAFT refinement iterations")
    p.add_argument("--save-pairs", type=int, default=3, help="inspection strips saved per pair kind and warp")
    p.add_argument("--vgg", type=Path, default=None, help="VGG16 torchvision state dict (features, LPIPS trunk)")
    p.add_argument("--lpips", type=Path, default=None, help="LPIPS VGG heads (vgg.pth of the lpips package)")
    p.add_argument("--raft", type=Path, default=None, help="torchvision raft_large state dict")
    p.add_argument("--layers", default=None, help="VGG16 feature layers, comma separated (default conv3)")
    p.add_argument("--data-dir", type=Path, default=None, help="where a reconstruction's capture is now")
    p.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true", help="no progress bars")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier evaluation of these runs (RUN/evaluation/, the 'evaluation' entry of "
                        "RUN/metrics.json) and an existing --table file")
    p.add_argument("--table", type=Path, default=None,
                   help="markdown table path (default: RUN/evaluation/table.md for one run, "
                        "else evaluation.md in the runs' common folder)")


def options_from_args(args: argparse.Namespace) -> EvalOptions:
    cfg = getattr(args, "weights", None)
    return EvalOptions(
        style=str(args.style) if args.style else None,
        pairs=tuple(s.strip() for s in str(args.pairs).split(",") if s.strip()),
        gap=int(args.gap), max_pairs=int(args.max_pairs), views=args.views, path_frames=int(args.path_frames),
        max_side=int(args.max_side),
        depth_tol=float(args.depth_tol), alpha_min=float(args.alpha_min), warp=args.warp,
        flow_iters=int(args.flow_iters), save_pairs=int(args.save_pairs),
        vgg=str(args.vgg) if args.vgg else None, lpips=str(args.lpips) if args.lpips else None,
        raft=str(args.raft) if args.raft else None,
        layers=[s.strip() for s in args.layers.split(",")] if args.layers else None,
        data_dir=str(args.data_dir) if args.data_dir else None,
        weights_config=cfg if isinstance(cfg, dict) else None,
    ).validate()


def run(args: argparse.Namespace) -> int:
    opts = options_from_args(args)
    runs = [Path(r) for r in args.runs]
    infos = [inspect_run(r) for r in runs]          # fail fast on a bad folder, before any rendering
    path = args.table or default_table_path(runs)
    force = bool(getattr(args, "force", False))
    claims = [claim_evaluation(info, force) for info in infos]     # before any weights are fetched
    if path.exists() and not force and not any(path.resolve().is_relative_to((info.path / "evaluation").resolve())
                                                     for info in infos):
        raise SsgwarpError(f"--table {path}: exists; pass --force to overwrite it")
    device = args.device
    extractor, raft, lpips, skipped = load_models(opts, device)
    for k, v in skipped.items():
        print(f"ssgwarp evaluate: {k} skipped: {v}")
    results = []
    for info, c in zip(infos, claims):
        c.clear()
        res = evaluate_run(info.path, opts, device, extractor=extractor, raft=raft, lpips=lpips, skipped=skipped,
                           progress=not getattr(args, "quiet", False))
        results.append(res)
        print(f"{info.path}: metrics written to {info.path / 'metrics.json'} (inspection images in "
              f"{info.path / 'evaluation'})")
        if "views" in res.get("style_content", {}):
            print(f"  {style_line(res['style_content'])}")
    table = comparison_table(results)
    with atomic_path(path) as tmp:
        tmp.write_text(table)
    print()
    print(comparison_table(results, notes=False))      # (what was skipped: said above, and in the file)
    print(f"table written to {path}")
    return 0
