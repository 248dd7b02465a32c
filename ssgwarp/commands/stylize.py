"""The ``ssgwarp stylize`` command line: its options, the CPU-sized ``--quick`` and the ``--paint`` presets, the
CPU hint and :func:`run`, which calls :func:`ssgwarp.stylization.stylize.stylize_run`."""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Optional

import torch

from ..evaluation.features import EXTRACTOR_KINDS
from ..stylization.feature_defaults import CONTENT_WEIGHT, CONTENT_WEIGHT_PATCHES
from ..stylization.stage2 import BACKGROUNDS, COLOR_DETAIL, COLOR_TRANSFER, MODES, SH_REST, STYLE_LOSSES, Stage2Config
from ..stylization.feature_defaults import BLEND_WEIGHT_EDGES, COLOR_GAIN_EDGES, COLOR_GAIN_OTHER, TV_WEIGHT_FREE, TV_WEIGHT_VGG
from ..capture.orbit import MAX_WIDTH, MAX_WIDTH as ORBIT_MAX_WIDTH, VIEWS, VIEWS as ORBIT_VIEWS
from ..errors import InputError
from ..from_splats import SOURCE, add_record, prepare_source
from ..stylization import stylize as _stylize      # (stylize_run looked up at call time: tests replace it)
from ..stylization.stylize import StylizeOptions, _say

__all__ = ["add_arguments", "run", "run_stage", "QUICK", "PAINT", "cpu_hint"]


def style_scale_arg(text: str) -> float | str:
    """``--style-scale``, ``--paint-strength``: ``auto`` or a number (its range is checked by :meth:`Stage2Config.validate`)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0.25, 4] or auto, got {text!r}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene_dir", type=Path, metavar="RUN_OR_FILE",
                   help="a reconstruction run (scene.ply, cameras.json, data.json; groups/ when grouped), or a splat "
                        "file (PLY, compressed PLY, SPZ, .splat) without a capture: cameras are made around its "
                        "splats and it is grouped mask-free in OUT/source (docs/your_splats.md)")
    p.add_argument("--style", type=Path, required=True, help="style image (PNG/JPG)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or stage messages")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--mode", default="ist", choices=MODES,
                   help="ist: per-group matching to the stylized key views (default; without Stage 1, each "
                        "group to its own region of the style image); finetune: fit the stylized key views "
                        "directly; global: ARF-style matching to the whole style image")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    p.add_argument("--force", action="store_true", help="overwrite an existing output in --out")
    g = p.add_argument_group("key views")
    g.add_argument("--keyviews", type=int, default=4, metavar="K", help="number of key views (default 4)")
    g.add_argument("--ids", default=None, help="comma-separated camera indices of the key views (default: chosen)")
    g.add_argument("--max-side", type=int, default=512, help="key-view (diffusion) longer side (default 512)")
    from ..stylization.diffusion import add_stage1_arguments
    add_stage1_arguments(p)
    d = Stage2Config()
    g = p.add_argument_group("Stage 2 (instance-level style transfer)")
    g.add_argument("--iters", type=int, default=d.iters, help=f"optimisation steps (default {d.iters})")
    g.add_argument("--lr", type=float, default=d.lr, help=f"learning rate of the SH DC colour (default {d.lr})")
    g.add_argument("--style-weight", type=float, default=d.style_weight, help="NNFM style loss weight")
    g.add_argument("--content-weight", type=float, default=d.content_weight,
                   help=f"content loss weight (relative feature MSE; default: {CONTENT_WEIGHT_PATCHES} with "
                        f"--extractor patches, {CONTENT_WEIGHT} with the others; lower paints more texture)")
    g.add_argument("--tv-weight", type=float, default=d.tv_weight,
                   help=f"total variation weight (default: {TV_WEIGHT_FREE} with the weight-free random features, "
                        f"{TV_WEIGHT_VGG} with VGG16)")
    g.add_argument("--blend-weight", type=float, default=d.blend_weight, help="weight of the blend spread (colours "
                   f"mixed on one ray kept alike; default {BLEND_WEIGHT_EDGES} with the edge features, else 0)")
    g.add_argument("--style-loss", default=d.style_loss, choices=STYLE_LOSSES,
                   help="nnfm: nearest-neighbour feature matching (the paper's); sw: sliced Wasserstein "
                        "between feature distributions; auto (default): NNFM on VGG16 features, SW on the "
                        "weight-free random features")
    g.add_argument("--sw-projections", type=int, default=d.sw_projections,
                   help=f"random directions per step of the sw loss (default {d.sw_projections})")
    g.add_argument("--color-transfer", default=d.color_transfer, choices=COLOR_TRANSFER,
                   help="ARF's view-consistent colour transfer (colour mean and covariance matched to the "
                        "stylized key views, per group, or to the style image) before the optimisation, "
                        f"after it, both or off (default {d.color_transfer})")
    g.add_argument("--color-max-gain", type=float, default=d.color_max_gain, help="largest stretch of colour "
                   f"differences by the colour map (default {COLOR_GAIN_EDGES} on edge features, else {COLOR_GAIN_OTHER})")
    g.add_argument("--color-detail", default=d.color_detail, choices=COLOR_DETAIL, help="keep: the colour map does not "
                   "flatten texture below the style's; off: plain map; auto (default): keep on edge features, else off")
    g.add_argument("--sh-rest", default=d.sh_rest, choices=SH_REST,
                   help=f"higher SH bands (view-dependent colour): keep, zero at the start, or optimise "
                        f"(default {d.sh_rest})")
    g.add_argument("--sh-bands", action="store_true", help="same as --sh-rest optimise")
    g.add_argument("--background", default=d.background, choices=BACKGROUNDS, help="the stylized scene's background: "
                   "transfer (default: the capture's, colour-transferred like the scene) or keep (the capture's)")
    g.add_argument("--free-opacity", action="store_true", help="also optimise opacities")
    g.add_argument("--densify", type=float, default=d.densify, metavar="F",
                   help="split Gaussians where the style loss wants finer detail, at most F x their number new "
                        f"ones (0: off; default {d.densify})")
    g.add_argument("--densify-views", type=int, default=d.densify_views,
                   help=f"training views that score the split (default {d.densify_views})")
    g.add_argument("--hold-empty", type=float, default=d.hold_empty, metavar="W",
                   help="weight of the term keeping (nearly) empty pixels as the unstylized scene renders them: "
                        f"no floaters over the background (0: off; default {d.hold_empty})")
    g.add_argument("--consistency-weight", type=float, default=d.consistency_weight, metavar="W",
                   help="weight of the view-pair term: each step's view against a nearby training view warped "
                        f"into it through the depths (0: off; default {d.consistency_weight})")
    g.add_argument("--consistency-budget", type=float, default=d.consistency_budget, metavar="B",
                   help="the view-pair term lets a pair's squared error grow to B x the starting scene's "
                        f"(default {d.consistency_budget}: an RMSE ratio of about 1.4); measured on fern and the demo "
                        "scene, the worst path-view error came out at about 0.9 x sqrt(B) x the unstylized scene's")
    g.add_argument("--consistency-neighbours", type=int, default=d.consistency_neighbours, metavar="K",
                   help=f"nearest training views a view is paired with (default {d.consistency_neighbours})")
    g.add_argument("--label-mode", default=d.label_mode, choices=("majority", "nearest"),
                   help="group maps to feature resolution (default majority)")
    g.add_argument("--feature-scale", type=float, default=d.feature_scale,
                   help="resize images by this factor before the feature extractor (default 1)")
    g.add_argument("--style-scale", type=style_scale_arg, default=d.style_scale, metavar="S|auto",
                   help="size of the style's strokes and patterns in the views: the style image is resized so its "
                        "shorter side is S x the views' (default 1; 2 paints them twice as large; auto: the scale "
                        "that puts the style's measured stroke period inside the features' reach, 6-24 view pixels). "
                        "Without Stage 1")
    g.add_argument("--paint-strength", type=style_scale_arg, default=d.paint_strength, metavar="S|auto",
                   help="painting strength: the smoothing weights (--tv-weight, --blend-weight) are divided by S "
                        "(default 1); auto: S from a 3-D consistency probe of the scene at the start of Stage 2, "
                        "weaker where painted texture costs the scene more consistency (docs/stylize.md)")
    g.add_argument("--region-check", action="store_true",
                   help="without Stage 1: send a group whose style region is a poor match (the view it predicts is "
                        "farther from the style than the style's halves) to the whole style (default off)")
    g.add_argument("--direct", action="store_true", help="direct back-propagation instead of deferred")
    g.add_argument("--chunk", type=int, default=d.chunk, help="similarity entries per nearest-neighbour block")
    g.add_argument("--nn-precision", default=d.nn_precision, choices=("auto", "fp32", "bf16", "fp16"),
                   help="nearest-neighbour search precision (auto: bf16 on CUDA, fp32 on CPU)")
    g.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every, help="steps between checkpoints")
    g.add_argument("--batch-size", type=int, default=None,
                   help="training views per Stage 2 step over all processes, their mean loss (default: one per "
                        "process; on --resume the checkpoint's); under torchrun each process renders its share")
    g.add_argument("--batch-scaling", choices=("sqrt", "linear", "none"), default=d.batch_scaling,
                   help="Adam for batches: learning rates x sqrt(B) (default) or x B with betas ** B, or none")
    g.add_argument("--extractor", default="auto", choices=EXTRACTOR_KINDS, help="features: auto = VGG16 when "
                   "weights are found, else random-edges (weight-free, zero-mean random filters); patches: raw image "
                   "patches on a pyramid (weight-free; with --mode global the most consistent); random: the "
                   "earlier weight-free default (docs/stylize.md)")
    g.add_argument("--vgg16", default=None, help="torchvision VGG16 state dict (or SSGWARP_VGG16)")
    g.add_argument("--layers", default=None, help="VGG16 layers, comma separated (default conv3 = relu3_1..3)")
    g = p.add_argument_group("a splat file without its capture (RUN_OR_FILE a file)")
    g.add_argument("--views", type=int, default=ORBIT_VIEWS,
                   help=f"cameras made around the splats (default {ORBIT_VIEWS}; --quick {QUICK_VIEWS})")
    g.add_argument("--width", type=int, default=None,
                   help=f"their width (default: at most {ORBIT_MAX_WIDTH}, --quick {QUICK_MAX_WIDTH}, and at "
                        "most the width at which the median splat is one pixel across)")
    g.add_argument("--up", default="auto", help="the splats' up axis: auto (default: the thinnest principal axis of "
                   "a layer of splats, else the file's -y), an axis (+z, -y ...) or a vector x,y,z")
    g.add_argument("--group-iters", type=int, default=None,
                   help=f"steps of the mask-free grouping (default the group command's; --quick {GROUP_QUICK_ITERS})")
    g = p.add_argument_group("outputs")
    g.add_argument("--path-frames", type=int, default=60, help="frames along a smooth camera path (0: none)")
    g.add_argument("--sheet-views", type=int, default=3, help="views in the contact sheet")
    from ..core.presets import add_preset, add_quick
    add_quick(p, QUICK, QUICK_MEASURED)
    add_preset(p, "--paint", PAINT, "the weight-free configuration that paints the most texture where the scene "
               "allows it: {values} (options given explicitly win). " + PAINT_MEASURED)


# the CPU-sized preset (`--quick`) and what it and the defaults cost on a CPU, measured (README, docs)
QUICK = {"iters": 150, "path_frames": 20}
QUICK_MEASURED = ("fern from reconstruct --quick (252x188), without Stage 1 weights: 9 min on 2 CPU cores shared "
                  "with other work (2.8 min of CPU time), 2026-11-28")
# a splat file without its capture under --quick: fewer, smaller made views and the group command's --quick
QUICK_VIEWS, QUICK_MAX_WIDTH, GROUP_QUICK_ITERS = 16, 256, 300
CPU_DEFAULT_MEASURED = "2.6 s per step, so about 26 min for 600 steps"
# the weight-free painting configuration (`--paint`) and what it measured (docs/stylize.md)
PAINT = {"mode": "global", "extractor": "patches", "tv_weight": 0.2, "blend_weight": 0.2, "content_weight": 0.0,
         "consistency_weight": 1.0, "consistency_budget": 1.6}
PAINT_MEASURED = ("Fern images_8, 25 styles: texture distance to the style -69 %, colour -70 %, worst consistency "
                  "error 1.16x the unstylized scene's (the default: -49 %, -54 %, 1.10x); Stage 2 at fern images_4 "
                  "19 s on one H200. One match against the whole style image (no groups, no Stage 1); on a scene "
                  "whose Gaussians blend several depths (the demo's) it keeps consistency and paints less.")


def cpu_hint(args) -> Optional[str]:
    """The one line ``stylize`` prints on a CPU: what its settings cost there and the --quick preset."""
    if getattr(args, "quick", False) or getattr(args, "quiet", False) or torch.device(args.device).type != "cpu":
        return None
    from ..core.presets import quick_text

    return (f"on a CPU Stage 2's {args.iters} steps take a while (fern at 252x188 on 2 cores: "
            f"{CPU_DEFAULT_MEASURED}); --quick ({quick_text(QUICK)}) took 9 min there in all")


def run_stage(args, scene_dir=None) -> int:
    """Stylize the run ``scene_dir`` (default ``args.scene_dir``; a splat file is made into a run by
    :func:`run` first)."""
    from ..stylization.diffusion import config_from_args
    from ..stylization.keyviews import parse_ids

    weights = getattr(args, "weights", None)
    weights = weights if isinstance(weights, dict) else None
    over = {"sh_rest": "optimise" if args.sh_bands else args.sh_rest, "deferred": not args.direct}
    s2 = Stage2Config(**{f.name: over[f.name] if f.name in over else getattr(args, f.name)
                         for f in dataclasses.fields(Stage2Config)})    # the flags carry the fields' names
    opts = StylizeOptions(keyviews=args.keyviews, ids=parse_ids(args.ids), max_side=args.max_side,
                          extractor=args.extractor, vgg16=args.vgg16,
                          layers=[s.strip() for s in args.layers.split(",")] if args.layers else None,
                          path_frames=args.path_frames, sheet_views=args.sheet_views, weights=weights)
    s1 = config_from_args(args) if args.mode != "global" else None
    from ..services import distributed

    scene_dir = args.scene_dir if scene_dir is None else scene_dir
    group, device = distributed.from_env(args.device)   # under torchrun: join the others
    hint = cpu_hint(args) if group.is_main else None
    if hint:
        _say(hint, True)
    try:
        _stylize.stylize_run(scene_dir, args.style, args.out, stage2=s2, stage1=s1, opts=opts, device=device,
                    resume=args.resume, force=args.force, progress=not args.quiet, group=group)
    finally:
        distributed.shutdown(group)
    return 0


def run(args) -> int:
    """``ssgwarp stylize RUN_OR_FILE``: a file is made into ``OUT/source`` first (:func:`prepare_source`)."""
    scene_dir = args.scene_dir
    if Path(scene_dir).expanduser().is_file():
        scene_dir = _splat_file_source(args)
    rc = run_stage(args, scene_dir=scene_dir)
    if scene_dir != args.scene_dir and _is_main():
        add_record(args.out, scene_dir)
    return rc


def _is_main() -> bool:
    import os

    return int(os.environ.get("RANK", "0") or 0) == 0


def _splat_file_source(args) -> Path:
    """``stylize FILE``: ``OUT/source``, the splat file's run with cameras made around it, grouped mask-free."""
    import os


    if int(os.environ.get("WORLD_SIZE", "1") or 1) > 1:
        raise InputError(f"{args.scene_dir}: a splat file is stylized by one process; run `ssgwarp stylize` once "
                         f"without torchrun (it writes {args.out / SOURCE}), then give that folder")
    quick = bool(getattr(args, "quick", False))
    views = QUICK_VIEWS if quick and args.views == VIEWS else args.views
    group_iters = args.group_iters if args.group_iters is not None else (GROUP_QUICK_ITERS if quick else None)
    return prepare_source(
        args.scene_dir, args.style, args.out, _stylize.OUTPUTS, views=views, width=args.width,
        max_width=QUICK_MAX_WIDTH if quick else MAX_WIDTH, up=args.up, group_iters=group_iters,
        force=args.force, resume=args.resume, device=args.device, seed=args.seed, progress=not args.quiet)
