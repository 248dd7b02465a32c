"""What texture costs in the consistency metric when the texture is consistent by construction.

Paints a scene's Gaussians with a probe colour that is a fixed function of 3-D position (a sum of six
seeded sinusoids, ``period`` pixels at the scene's median depth, grey, standard deviation ``amplitude``
added to the base colour; view-dependent SH bands zeroed), renders ``ssgwarp evaluate``'s novel path views
and scores them as ``evaluate`` does: short/long-range reprojection RMSE as a ratio to the unpainted scene's,
and the weight-free texture distance to a style image per filter scale (change against the unpainted scene).
No optimisation: every colour here is view-independent and attached to the surface, so what the ratio
shows is what the scene's geometry (blends of Gaussians at several depths, expected depth at edges) makes
of painted contrast, the floor under any Stage 2 that paints texture of that contrast. Also reports how
concentrated the squared error is (share in the worst 10 % / 25 % of the scored pixels).

``--truth`` (a run made by ``ssgwarp demo``: ``OUT/scene``) scores the procedural scene that made the demo's
capture too, the true geometry, with the same cameras and probes: what painted contrast costs where the
reconstruction is not to blame.

    python benchmarks/stylize_consistency.py --run RUN --style ../shared/data/styles/candy.jpg
    python benchmarks/stylize_consistency.py --run RUN --periods 2,8 --amplitudes 0.15,0.3 --frames 30
    python benchmarks/stylize_consistency.py --run ssgwarp-demo/scene --truth --periods 2,8,32
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def probe_scene(scene, period_px: float, amplitude: float, pixel: float, seed: int = 0):
    """``scene`` with ``amplitude`` x a unit-variance sum of six 3-D sinusoids of ``period_px`` pixels added to
    its base colour (grey) and its SH bands above 0 zeroed."""
    from ssgwarp.raster.scene import SH_C0

    g = torch.Generator().manual_seed(seed)
    xyz = scene.means.detach().double().cpu()
    k = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=1)
    k = k * (2 * math.pi / (period_px * pixel))
    phase = torch.rand(6, generator=g, dtype=torch.float64) * 2 * math.pi
    pattern = (torch.sin(xyz @ k.T + phase).sum(1) / math.sqrt(3)).to(scene.sh_dc)
    rest = None if scene.sh_rest is None else torch.zeros_like(scene.sh_rest)
    return scene.replace(sh_dc=scene.sh_dc + (amplitude * pattern / SH_C0)[:, None], sh_rest=rest)


def pixel_size(scene, cams) -> float:
    """World size of one pixel at the scene's median depth in the first camera."""
    xyz = scene.means.detach().double().cpu()
    X = torch.cat([xyz, torch.ones(len(xyz), 1, dtype=xyz.dtype)], 1) @ cams.viewmats[0].double().cpu().T
    z = X[:, 2][X[:, 2] > 0]
    return float(z.median() if len(z) else 1.0) / float(cams.Ks[0, 0, 0])


def demo_truth(run: Path):
    """The procedural scene that made the capture of the demo whose reconstruction is ``run`` (``OUT/scene``;
    size and seed from ``OUT/summary.json``)."""
    from ssgwarp import procedural as P
    from ssgwarp.core.fileio import read_json
    from ssgwarp.errors import InputError

    summary = Path(run).resolve().parent / "summary.json"
    if not summary.is_file():
        raise InputError(f"--truth: {summary} not found; pass the scene folder of an `ssgwarp demo` output (OUT/scene)")
    info = read_json(summary)
    size = P.SIZES.get(info.get("size"))
    if size is None:
        raise InputError(f"--truth: {summary} names demo size {info.get('size')!r}; use one of {', '.join(P.SIZES)}")
    return P.build_scene(size.density, seed=int(info.get("seed", 0))).scene


def score(scene, cams, bg, opts, style_distance, alpha0=None) -> dict:
    """Consistency, error concentration and texture per scale of ``scene``'s renders; the texture is taken over
    the pixels where ``alpha0`` (the unpainted scene's alpha; default: these renders') is at least 0.5."""
    from ssgwarp.evaluation import metrics as M
    from ssgwarp.evaluation.style_distance import sliced_wasserstein
    from ssgwarp.evaluation.evaluate import consistency
    from ssgwarp.raster.rendering import render_views

    rgb, depth, alpha = render_views(scene, cams, bg)
    alpha0 = alpha if alpha0 is None else alpha0
    rep = consistency(rgb, depth, alpha, cams, opts)["reprojection"]
    sq = []
    for a, b in M.consistency_pairs(len(cams), "short", opts.gap, opts.max_pairs or None):
        res = M.reprojection_warp(M.View(rgb[a], depth[a], alpha[a], cams.viewmats[a], cams.Ks[a]),
                                  M.View(rgb[b], depth[b], alpha[b], cams.viewmats[b], cams.Ks[b]),
                                  rel_tol=opts.depth_tol, alpha_min=opts.alpha_min)
        sq.append(((res.warped - rgb[b]) ** 2).sum(-1)[res.mask])
    e = torch.cat(sq).sort(descending=True).values
    share = [float(e[: max(1, int(f * len(e)))].sum() / e.sum().clamp_min(1e-12)) for f in (0.10, 0.25)]
    levels = None
    if style_distance is not None:
        per = []
        H, W = rgb.shape[1:3]
        _, s_lab, s_resp = style_distance._style_at(H, W, rgb.device)
        n = style_distance.levels_for(H, W)
        for v in range(len(rgb)):
            _, resp = style_distance._features(rgb[v], n, alpha0[v] >= 0.5)
            per.append([float(sliced_wasserstein(x, None, style_distance.texture_projections, style_distance.seed, y))
                        for x, y in zip(resp, s_resp)])
        levels = torch.tensor(per).mean(0).tolist()
    return {"short": rep["short"]["rmse"], "long": rep["long"]["rmse"], "share10": share[0], "share25": share[1],
            "levels": levels, "alpha": alpha}


def probe_table(name, scene, cams, bg, opts, sd, args, described) -> dict:
    """Prints and returns the unpainted scene's error and one row per probe period and amplitude."""
    base = score(scene, cams, bg, opts, sd)
    alpha0 = base.pop("alpha")
    pixel = pixel_size(scene, cams)
    print(f"{name}: {len(scene)} Gaussians, {described}, {cams.width}x{cams.height}; unpainted short/long "
          f"RMSE {base['short']:.4f} / {base['long']:.4f}; worst 10 % / 25 % of pixels hold {100 * base['share10']:.0f} / "
          f"{100 * base['share25']:.0f} % of the squared error")
    print("| period (px) | amplitude | short (x) | long (x) | texture change per scale | worst 10 % / 25 % share |")
    print("|---|---|---|---|---|---|")
    rows = []
    for period in [float(x) for x in args.periods.split(",")]:
        for amp in [float(x) for x in args.amplitudes.split(",")]:
            r = score(probe_scene(scene, period, amp, pixel), cams, bg, opts, sd, alpha0)
            r.pop("alpha")
            lv = "-" if r["levels"] is None else " / ".join(
                f"{100 * (a / b - 1):+.0f} %" for a, b in zip(r["levels"], base["levels"]))
            print(f"| {period:g} | {amp:g} | {r['short'] / base['short']:.2f} | {r['long'] / base['long']:.2f} | {lv} | "
                  f"{100 * r['share10']:.0f} / {100 * r['share25']:.0f} % |", flush=True)
            rows.append({"period_px": period, "amplitude": amp, **r})
    return {"base": base, "rows": rows}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, required=True, help="a reconstruction run folder")
    p.add_argument("--style", type=Path, default=None, help="style image: texture distance per filter scale too")
    p.add_argument("--periods", default="1,2,4,8,16", help="probe periods in pixels")
    p.add_argument("--amplitudes", default="0.15,0.3", help="probe standard deviations (colour, 0..1)")
    p.add_argument("--frames", type=int, default=30, help="path views scored (ssgwarp evaluate's default)")
    p.add_argument("--device", default="auto")
    p.add_argument("--truth", action="store_true",
                   help="a demo's run (OUT/scene): also score the procedural scene that made its capture")
    p.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = p.parse_args()
    from ssgwarp.errors import InputError

    try:
        return probe(args)
    except InputError as e:     # a bad run folder, style image or --truth on a run that is not a demo's: one line
        print(f"stylize_consistency: {e}", file=sys.stderr)
        return 2


def probe(args) -> int:
    """Every probe on the run's scene (and on the demo's true scene with ``--truth``)."""
    from ssgwarp.cli import resolve_device
    from ssgwarp.core.fileio import read_image, write_json
    from ssgwarp.evaluation.evaluate import EvalOptions, inspect_run, scored_cameras
    from ssgwarp.evaluation.style_distance import StyleDistance

    device = resolve_device(args.device)
    info = inspect_run(args.run)
    scene, data = info.load(device, load_images=False)
    opts = EvalOptions(path_frames=args.frames, max_pairs=16, save_pairs=0)
    cams, _, described = scored_cameras(data.cameras, data.train_ids, data.test_ids, opts)
    cams = cams.to(device)
    bg = list(data.background)
    sd = None if args.style is None else StyleDistance(torch.from_numpy(read_image(args.style, 3)).to(device))
    scenes = [("reconstruction", scene)] + ([("truth", demo_truth(args.run).to(device))] if args.truth else [])
    print(f"run {args.run}")
    out = {"run": str(args.run)}
    for name, sc in scenes:
        out[name] = probe_table(name, sc, cams, bg, opts, sd, args, described)
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
