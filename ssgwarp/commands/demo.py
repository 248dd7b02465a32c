"""``ssgwarp demo``: the whole pipeline on an embedded procedural scene (:func:`ssgwarp.demo.run_demo`)."""
from __future__ import annotations

import gc
import logging
from pathlib import Path

from ..demo import format_summary, run_demo


def add_arguments(parser) -> None:
    parser.add_argument("--out", type=Path, default=Path("ssgwarp-demo"), help="output folder (default ssgwarp-demo)")
    parser.add_argument("--size", choices=("small", "default"), default="default",
                        help="default: 24 views 80x60, about half a minute on 2 idle CPU cores; small: 8 views 48x36, "
                             "well under a minute (what the tests run)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing demo in --out")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted demo in --out")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or stage messages (summary only)")


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="ssgwarp: %(message)s")
    # what the imports made (torch's, Warp's modules: most of the process's objects) is out of the collector's
    # way while the demo runs (its full collections: 0.45 s -> 0.2 s of the default demo on 2 cores); given
    # back before the exit, whose collection frees it (left frozen, extension types report it as leaked)
    gc.freeze()
    try:
        s = run_demo(args.out, args.size, device=args.device, seed=args.seed, force=args.force, resume=args.resume,
                     progress=not args.quiet)
    finally:
        gc.unfreeze()
    print(format_summary(s), flush=True)
    return 0
