"""How far Stage 2's weight-free style loss can take the texture distance with nothing holding it back.

For each style: the reconstruction's colours go through Stage 2's colour transfer (as ``ssgwarp stylize``
does before its optimisation), ``ssgwarp evaluate``'s path views are rendered, and then each view's scene
pixels (alpha >= 0.5) are optimised *freely* with the style loss alone (Adam on the pixels' logits, one view
per step in turn; no 3-D scene, no consistency, no content or smoothing terms unless asked). The views are
scored with ``evaluate``'s weight-free texture distance after ``--steps`` steps per view (several counts show
whether it has converged). Beside them: the colour distance's change (the patch features do not see a patch's
mean colour, so colour drifts; Stage 2 maps it back with its post colour transfer), and half of the style
image against the whole (``StyleDistance.halves``), all against the unstylized scene's distances.

What it is for: the loss's reach with no 3-D scene in its way. A scene's mean texture target beyond it is beyond
the loss, whatever the 3-D side does (Stage 2's closing colour map moves single styles by some points either way).

    python benchmarks/stylize_bound.py --run RUN --styles candy,mosaic --steps 10,100
    python benchmarks/stylize_bound.py --run RUN --device cuda --frames 10 --steps 50,200 --json bound.json
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]

from shared_data import data_root, style_paths  # noqa: E402
from ssgwarp.evaluation.features import EXTRACTOR_KINDS  # noqa: E402

STYLES = data_root() / "styles"


def free_pixels(start: torch.Tensor, alphas: torch.Tensor, loss, counts: list[int], lr: float):
    """Optimise each view's scene pixels with ``loss(image [H, W, 3], view, step)``; yields ``(count, images)``
    after each step count per view in ``counts`` (ascending)."""
    keep = (alphas >= 0.5).to(start)[..., None]
    params = [torch.logit(start[v].clamp(0.01, 0.99)).clone().requires_grad_(True) for v in range(len(start))]
    opts = [torch.optim.Adam([p], lr=lr) for p in params]

    def image(v: int) -> torch.Tensor:
        return torch.sigmoid(params[v]) * keep[v] + start[v] * (1 - keep[v])

    done = 0
    for count in counts:
        for step in range(done, count):
            for v in range(len(start)):
                opts[v].zero_grad(set_to_none=True)
                loss(image(v), v, step).backward()
                opts[v].step()
        done = count
        with torch.no_grad():
            yield count, torch.stack([image(v) for v in range(len(start))])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, required=True, help="a reconstruction run folder")
    p.add_argument("--styles", default="", help="comma-separated style names (in --style-dir) or paths; default: all")
    p.add_argument("--style-dir", type=Path, default=STYLES, help="folder of style images (default ../shared/data/styles)")
    p.add_argument("--steps", default="10,100", help="steps per view at which the views are scored (ascending)")
    p.add_argument("--lr", type=float, default=0.05, help="Adam learning rate on the pixels' logits")
    p.add_argument("--extractor", default="patches", choices=EXTRACTOR_KINDS,
                   help="Stage 2's features (default patches, as --paint)")
    p.add_argument("--tv-weight", type=float, default=0.0, help="add Stage 2's total variation term (default 0)")
    p.add_argument("--frames", type=int, default=30, help="path views (ssgwarp evaluate's default 30)")
    p.add_argument("--device", default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, default=None, help="also write the rows here (after every style)")
    args = p.parse_args()

    from ssgwarp.errors import InputError

    try:
        counts = sorted({int(c) for c in args.steps.split(",")})
    except ValueError:
        counts = [-1]
    if counts[0] < 0:
        print(f"stylize_bound: --steps takes step counts >= 0 such as 10,100, got {args.steps!r}", file=sys.stderr)
        return 2
    try:
        return bound(args, counts, style_paths(args.styles, args.style_dir))
    except InputError as e:     # a style not found, a bad run folder or style image: one line
        print(f"stylize_bound: {e}", file=sys.stderr)
        return 2


def bound(args, counts: list[int], styles: list[Path]) -> int:
    """Score every style (main's table and ``--json``)."""
    from ssgwarp.cli import resolve_device
    from ssgwarp.core.fileio import read_image, write_json
    from ssgwarp.core.imaging import fit_style
    from ssgwarp.evaluation.evaluate import EvalOptions, inspect_run, scored_cameras
    from ssgwarp.raster.rendering import render_views
    from ssgwarp.evaluation.style_distance import StyleDistance
    from ssgwarp.stylization.color import transfer_colors
    from ssgwarp.evaluation.features import load_extractor
    from ssgwarp.stylization.stage2 import Stage2Config, build_targets, extract, tv_loss
    from ssgwarp.stylization.feature_defaults import resolve_for
    device = resolve_device(args.device)
    torch.manual_seed(args.seed)
    scene, data = inspect_run(args.run).load(device, load_images=False)
    scene = scene.replace(sh_rest=None if scene.sh_rest is None else torch.zeros_like(scene.sh_rest))
    cams, _, described = scored_cameras(data.cameras, data.train_ids, data.test_ids,
                                        EvalOptions(path_frames=args.frames, save_pairs=0))
    cams, train = cams.to(device), data.cameras[list(data.train_ids) or list(range(len(data.cameras)))].to(device)
    bg = list(data.background)
    base = render_views(scene, cams, bg)
    H, W = base.rgb.shape[1:3]
    extractor = load_extractor(None, device, None, kind=args.extractor, seed=args.seed, config=None)
    cfg = resolve_for(Stage2Config(mode="global", seed=args.seed), extractor)
    print(f"{args.run}: {len(scene)} Gaussians, {described}, {W}x{H}; features {extractor.name}, style loss alone"
          f"{f' + TV {args.tv_weight:g}' if args.tv_weight else ''}, lr {args.lr:g}; texture / colour change "
          f"against the unstylized scene")
    head = " | ".join(f"{c} steps / view" for c in counts)
    print(f"| style | unstylized texture | colour transfer | {head} | half of the style | colour |")
    print("|---|---|---|" + "---|" * len(counts) + "---|---|")
    rows = []
    for path in styles:
        t0 = time.perf_counter()
        style = torch.from_numpy(read_image(path, 3)).to(device)
        at_views = fit_style(style.to(scene.dtype), H, W).permute(0, 2, 3, 1)
        sd = StyleDistance(style)
        d0 = {k: float(v.mean()) for k, v in sd(base.rgb, base.alpha).items()}
        recoloured, _ = transfer_colors(scene, train, at_views, max_gain=cfg.color_max_gain,
                                        keep_detail=cfg.color_detail == "keep")
        start = render_views(recoloured, cams, bg).rgb
        dct = float(sd(start, base.alpha)["texture"].mean())
        targets = build_targets(extractor, at_views, None, cfg)

        def loss(img, view, step):
            out = targets.loss(extract(extractor, img, 1.0)[0], None, step=step)
            return out + args.tv_weight * tv_loss(img) if args.tv_weight else out

        per = {}
        for count, images in free_pixels(start, base.alpha, loss, counts, args.lr):
            last = sd(images, base.alpha)
            per[count] = float(last["texture"].mean())
        raw_color = float(last["color"].mean())           # after the last step count
        row = {"style": path.stem, "texture": d0["texture"], "color": d0["color"], "color_transfer": dct,
               "free": per, "free_color": raw_color,
               "halves": sd.halves(H, W), "seconds": time.perf_counter() - t0}
        rows.append(row)
        if args.json:      # after every style: a run stopped early keeps the finished ones
            write_json(args.json, {"run": str(args.run), "features": extractor.name, "steps": counts, "lr": args.lr,
                                   "tv_weight": args.tv_weight, "views": len(cams), "rows": rows})

        def ch(x: float, ref: float) -> str:
            return f"{100 * (x / ref - 1):+.1f} %"

        cells = " | ".join(ch(per[c], d0["texture"]) for c in counts)
        print(f"| {path.stem} | {d0['texture']:.3f} | {ch(dct, d0['texture'])} | {cells} | "
              f"{ch(row['halves']['texture'], d0['texture'])} | {ch(raw_color, d0['color'])} |", flush=True)

    def mean(f) -> str:
        return f"{100 * sum(f(r) for r in rows) / len(rows):+.1f} %"

    cells = " | ".join(mean(lambda r, c=c: r["free"][c] / r["texture"] - 1) for c in counts)
    print(f"| **mean of {len(rows)}** | | {mean(lambda r: r['color_transfer'] / r['texture'] - 1)} | {cells} | "
          f"{mean(lambda r: r['halves']['texture'] / r['texture'] - 1)} | {mean(lambda r: r['free_color'] / r['color'] - 1)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
