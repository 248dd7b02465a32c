"""``ssgwarp reconstruct``: 3DGS reconstruction of a capture (:func:`ssgwarp.reconstruction.reconstruct.reconstruct`);
``--groups`` also trains Gaussian Grouping in the same loop (:mod:`ssgwarp.grouping.joint`)."""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from ..capture.datasets import check_init
from ..core.fileio import read_json
from ..core.presets import AtMost
from ..errors import InputError
from ..grouping.joint import GroupsDuringReconstruction, parse_groups
from ..grouping.model import DEFAULT_DIM, GroupConfig
from ..reconstruction.recipe import Recipe
from ..reconstruction.reconstruct import ReconstructConfig, reconstruct
from ..reconstruction.schedules import AUTO
from ..reconstruction.strategy import STRATEGIES
from ..services import distributed

def parse_background(s: str) -> tuple[float, float, float]:
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
    if s in named:
        return named[s]
    try:
        v = tuple(float(x) for x in s.split(","))
    except ValueError:
        v = ()
    if len(v) != 3:
        raise InputError(f"--background {s!r}: expected white, black or R,G,B in [0, 1]")
    return v  # type: ignore[return-value]


def _iters(s: str) -> int | str:
    if s == AUTO:
        return AUTO
    try:
        n = int(s)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{s!r}: expected a number of steps >= 1 or 'auto'")
    return n


def _factor(s: str) -> float:
    try:
        f = float(s)
    except ValueError:
        f = 0.0
    if not f >= 1.0:
        raise argparse.ArgumentTypeError(f"{s!r}: expected a downsampling factor >= 1 (1: off), e.g. 4")
    return f


def _reconstruction_arguments(parser) -> None:
    parser.add_argument("data_dir", type=Path, help="the capture: COLMAP (sparse/0), LLFF (poses_bounds.npy) "
                        "or NeRF/instant-ngp (transforms*.json) folder")
    parser.add_argument("--out", type=Path, required=True, help="run folder to write")
    parser.add_argument("--iters", type=_iters, default="auto", metavar="N|auto",
                        help="training steps, or auto (default): the 3DGS 30000-step schedule, ended once the PSNR "
                             "of a few training views stops improving (docs/reconstruction.md; hours on a CPU: 7000 "
                             "steps take about 30-50 min for fern images_8 on 2 CPU cores; see --quick)")
    parser.add_argument("--coarse-to-fine", type=_factor, default=1.0, metavar="F",
                        help="train on the images downsampled by F at first, raised to full resolution by the end "
                             "of densification (default 1: off; e.g. 4)")
    parser.add_argument("--images", default="images", help="image sub-folder, e.g. images_4 or images_8 (default images)")
    parser.add_argument("--width", type=int, default=None, help="resize images to this width (default: as loaded)")
    parser.add_argument("--sh-degree", type=int, default=3, help="final SH degree 0..3 (default 3)")
    parser.add_argument("--strategy", choices=("default", "mcmc"), default="default",
                        help="densification: default (3DGS: clone/split/prune, opacity reset) or mcmc "
                             "(3DGS-MCMC: relocation, a fixed budget of --max-gaussians, position noise)")
    parser.add_argument("--max-gaussians", type=int, default=1_000_000,
                        help="cap on the number of Gaussians; with --strategy mcmc the budget it grows to "
                             "(default 1000000)")
    parser.add_argument("--split-every", type=int, default=8,
                        help="hold out every N-th image for testing (default 8, the LLFF convention; 0: none)")
    parser.add_argument("--max-images", type=int, default=None, help="use at most this many images (evenly spaced)")
    parser.add_argument("--background", type=parse_background, default=None,
                        help="white, black or R,G,B: what RGBA images are composited on (default white)")
    parser.add_argument("--random-points", type=int, default=100_000,
                        help="number of random initial points (--init random, or when triangulation fails; "
                             "default 100000)")
    parser.add_argument("--init", default="auto", metavar="auto|triangulate|random|PATH.ply",
                        help="initial points: auto (default: the capture's COLMAP points, else points "
                             "triangulated from the images and their poses), triangulate (even when the capture "
                             "has points), random, or a .ply point cloud")
    parser.add_argument("--backdrop", choices=("auto", "on", "off"), default="auto",
                        help="far points along the training rays and a far shell (sky) added to the initial "
                             "points: auto (default: when the cameras look outward, or the photos show far "
                             "content where the points leave the images uncovered; docs/reconstruction.md), on "
                             "or off")
    parser.add_argument("--appearance", choices=("auto", "on", "off"), default="auto",
                        help="per-image exposure and white balance (an affine colour transform per training image, "
                             "not part of the scene): auto (default: on when a probe finds the photos' exposures "
                             "differ; docs/reconstruction.md), on or off. When on, held-out views are scored on "
                             "their right half after a colour transform fitted on their left half")
    parser.add_argument("--sky", choices=("auto", "on", "off"), default="auto",
                        help="an environment colour field (a colour per direction, OUT/environment.json) behind the "
                             "splats instead of the constant background: auto (default: on when the cameras look "
                             "outward and no backdrop stands for the sky), on or off")
    parser.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints (default 500)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="training views per step, over all processes (default: one per process; on "
                             "--resume the checkpoint's); the default schedule counts images, so --iters N "
                             "--batch-size B trains on N x B images (docs/scaling.md)")
    parser.add_argument("--batch-scaling", choices=("sqrt", "linear", "none"), default="sqrt",
                        help="Adam for batches: learning rates x sqrt(B) (default) or x B with betas ** B, "
                             "or none (one view's settings)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--force", action="store_true", help="overwrite an existing run in OUT")
    parser.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true",
                        help="no progress bar (as the other commands' --quiet)")
    from ..core.presets import add_quick
    add_quick(parser, QUICK, QUICK_MEASURED)


# the CPU-sized preset (`--quick`) and what it cost, measured (README, docs)
QUICK = {"iters": 1500, "width": AtMost(252), "max_gaussians": 60_000}   # (252 px wide at most: never wider)
QUICK_MEASURED = ("fern images_8 (17 training views, resized to 252x188): 20 min on 2 CPU cores shared with other "
                  "work (6.5 min of CPU time), held-out PSNR 26.6 dB, 2026-11-28")


def config_from_args(args, init=None) -> ReconstructConfig:
    """The :class:`ReconstructConfig` of the command's options."""
    return ReconstructConfig(
        iters=args.iters, images=args.images, seed=args.seed, split_every=args.split_every, width=args.width,
        max_images=args.max_images, background=args.background, checkpoint_every=args.checkpoint_every,
        num_random_points=args.random_points, batch_size=args.batch_size, backdrop=args.backdrop,
        appearance=args.appearance, sky=args.sky, init=args.init if init is None else init,
        strategy=STRATEGIES[args.strategy](max_gaussians=args.max_gaussians),
        recipe=Recipe(sh_degree=args.sh_degree, batch_scaling=args.batch_scaling, res_start=args.coarse_to_fine))


def _run(args, **extra) -> int:
    """The command; ``extra`` goes to :func:`reconstruct` (``attach``: ``reconstruct --groups``)."""
    if args.batch_size is not None and args.batch_size < 1:
        raise InputError(f"--batch-size must be >= 1, got {args.batch_size}")
    init = check_init(args.init)
    group, device = distributed.from_env(args.device)  # under torchrun: join the others
    logging.basicConfig(level=logging.INFO if group.is_main else logging.WARNING, format="ssgwarp: %(message)s")
    try:
        m = reconstruct(args.data_dir, args.out, config_from_args(args, init), resume=args.resume, force=args.force,
                        device=device, progress=not args.quiet, group=group, **extra)
    finally:
        distributed.shutdown(group)
    if not group.is_main:
        return 0
    ps = "n/a" if m["psnr"] is None else f"{m['psnr']:.2f} dB"
    ss = "n/a" if m["ssim"] is None else f"{m['ssim']:.4f}"
    print(f"{args.out}: {m['num_gaussians']} Gaussians, held-out PSNR {ps}, SSIM {ss}, "
          f"{m['train_seconds']:.0f} s, {m['iters']} steps")
    return 0


def add_arguments(parser) -> None:
    _reconstruction_arguments(parser)
    g = parser.add_argument_group("groups in the same training (Gaussian Grouping; docs/grouping.md)")
    g.add_argument("--groups", nargs="?", const="auto", default=None, metavar="K|auto",
                   help="also train identity encodings and K groups in this training (auto, or --groups alone: "
                        "the masks' ids, or chosen per scene when mask-free); writes RUN/groups as `ssgwarp group` "
                        "does")
    g.add_argument("--masks", default="auto",
                   help="with --groups: folder of instance masks <image stem>.png (ids consistent across views; "
                        "`ssgwarp masks` writes them), 'auto' (default: <data_dir>/object_mask when it exists, "
                        "else mask-free) or 'none'")
    g.add_argument("--max-groups", type=int, default=8, metavar="CAP",
                   help="with --groups, mask-free: the largest K considered (default 8)")
    g.add_argument("--group-start", type=float, default=None, metavar="F",
                   help="with --groups: start grouping after this share of the run (default: at once with masks; "
                        f"mask-free the last {GroupConfig.iters} steps, not before densification stops)")
    g.add_argument("--group-dim", type=int, default=DEFAULT_DIM, metavar="E",
                   help="with --groups: identity length (default 16)")


def run(args) -> int:
    if args.groups is None:
        given = [f for f, v in (("--masks", args.masks != "auto"), ("--max-groups", args.max_groups != 8),
                                ("--group-start", args.group_start is not None),
                                ("--group-dim", args.group_dim != DEFAULT_DIM)) if v]
        if given:
            raise InputError(f"{', '.join(given)}: only with --groups (train groups in this reconstruction)")
        return _run(args)
    attach = GroupsDuringReconstruction(args.out, num_groups=parse_groups(args.groups), masks=args.masks,
                                        max_groups=args.max_groups, start=args.group_start,
                                        config=GroupConfig(dim=args.group_dim), seed=args.seed, force=args.force,
                                        resume=args.resume, progress=not args.quiet)
    code = _run(args, attach=attach)
    if code == 0 and attach.hook is not None and (Path(args.out) / "groups" / "groups.json").is_file():
        info = read_json(Path(args.out) / "groups" / "groups.json")
        ra = info.get("reprojection_agreement", {}).get("mean")
        print(f"grouped in the same training from step {info['start_step']}: K={info['num_groups']} {info['kind']}; "
              f"cross-view agreement {ra if ra is None else f'{ra:.3f}'}; wrote {Path(args.out) / 'groups'}")
    return code
