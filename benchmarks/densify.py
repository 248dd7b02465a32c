"""Densification rules measured across resolutions: resolution x rule -> Gaussians, held-out PSNR, time.

The same scene at 0.2, 0.5, 1 and 2 megapixels (``--megapixels``): the procedural demo scene
(:mod:`ssgwarp.procedural`, ``--density`` times its Gaussians; sharp edges and a checkerboard, so every
resolution has real detail rather than upsampled pixels), rendered from a ring of ``--views`` cameras
(4:3, every 8th held out) and reconstructed from ``--init-points`` random points with our loop and the
default strategy, once per rule (``--rules``):

* ``3dgs``: the defaults (gradient threshold 2e-4 in NDC units, world-size prune 0.1 x extent after the
  first reset, no screen-size prune);
* ``grad-x0.5``, ``grad-x2``: the NDC threshold halved / doubled. If NDC units were wrong across
  resolutions, the best multiplier would move with the resolution;
* ``grad-px``: a threshold fixed in pixels instead (2e-4 NDC at the 0.5 MP width, i.e. scaled by
  ``W / W(0.5 MP)`` in NDC);
* ``screen-20px``: screen-size prune of INRIA's code (radius > 20 px; a bug keeps it from ever running
  there, gsplat leaves it off); ``screen-0.15``: gsplat's ``prune_scale2d`` (radius > 0.15 x max(W, H));
* ``no-world-prune``: no world-size prune.

Why NDC: the loss is a mean over pixels and a Gaussian of a given world size covers a fixed fraction of
the image, so its positional gradient in pixels scales as 1/W and, times W/2, is resolution-free;
a Gaussian of a fixed *pixel* footprint is a finer Gaussian at a higher resolution and gets a smaller
NDC gradient. The table says whether that holds in training.

    python benchmarks/densify.py                                        # GPU: 4 resolutions x 6 rules
    python benchmarks/densify.py --megapixels 1 --rules 3dgs grad-x2 screen-20px no-world-prune --iters 1500
    python benchmarks/densify.py --megapixels 0.005 0.01 --iters 120 --device cpu --rules 3dgs screen-20px  # smoke
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from reconstruct import _f, report, train_and_measure  # noqa: E402  (benchmarks/reconstruct.py)
from ssgwarp import procedural as P  # noqa: E402
from ssgwarp.capture.datasets import SceneData  # noqa: E402
from ssgwarp.core.fileio import write_json  # noqa: E402
from ssgwarp.reconstruction.recipe import Recipe  # noqa: E402

ASPECT = 4 / 3


def size_for(megapixels: float) -> tuple[int, int]:
    h = max(8, round(math.sqrt(megapixels * 1e6 / ASPECT)))
    return round(h * ASPECT), h


RULES = {
    "3dgs": lambda w, h: {},
    "grad-x0.5": lambda w, h: {"grad_threshold": 1e-4},
    "grad-x2": lambda w, h: {"grad_threshold": 4e-4},
    "grad-px": lambda w, h: {"grad_threshold": 2e-4 * w / size_for(0.5)[0]},
    "screen-20px": lambda w, h: {"prune_screen": 20.0 / max(w, h)},
    "screen-0.15": lambda w, h: {"prune_screen": 0.15},
    "no-world-prune": lambda w, h: {"prune_world": 1e9},
}


def capture(megapixels: float, views: int, density: float, init_points: int, seed: int, device) -> SceneData:
    """The procedural scene rendered at ``megapixels``, with random initial points in its bounding box."""
    w, h = size_for(megapixels)
    gt = P.build_scene(density, seed=seed)
    gt = P.ProceduralScene(gt.scene.to(device), gt.object_ids.to(device), gt.names)
    cams = P.ring_cameras(views, w, h).to(device)
    images, _ = P.render_views(gt, cams)
    test = list(range(0, views, 8))
    g = torch.Generator().manual_seed(seed)
    lo, hi = gt.scene.means.min(dim=0).values.cpu(), gt.scene.means.max(dim=0).values.cpu()
    xyz = lo + (hi - lo) * torch.rand(init_points, 3, generator=g)
    rgb = torch.rand(init_points, 3, generator=g)
    return SceneData(cams, images.float(), list(cams.names), [i for i in range(views) if i not in test], test,
                     points=(xyz.to(device), rgb.to(device)), points_source="random", background=P.BACKGROUND)


def table(rows: list[dict]) -> str:
    lines = ["| megapixels | resolution | rule | Gaussians | held-out PSNR (dB) | SSIM | train time (s) |",
             "|---:|---|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['megapixels']:g} | {r['resolution']} | {r['rule']} | {r['gaussians']:,} | "
                     f"{_f(r['psnr'])} | {_f(r['ssim'], '.4f')} | {r['seconds']:.1f} |")
    # per resolution: each rule relative to 3dgs
    base = {r["megapixels"]: r for r in rows if r["rule"] == "3dgs"}
    rel = []
    for r in rows:
        b = base.get(r["megapixels"])
        if b and r["rule"] != "3dgs":
            rel.append(f"| {r['megapixels']:g} | {r['rule']} | {r['psnr'] - b['psnr']:+.2f} dB | "
                       f"{r['gaussians'] / max(1, b['gaussians']):.2f}x | {r['seconds'] / b['seconds']:.2f}x |")
    if rel:
        lines += ["", "| megapixels | rule | PSNR - 3dgs | Gaussians / 3dgs | time / 3dgs |",
                  "|---:|---|---:|---:|---:|"] + rel
    grad = [r for r in rows if r["rule"] in ("3dgs", "grad-x0.5", "grad-x2", "grad-px")]
    if len({r["rule"] for r in grad}) > 1:
        lines += ["", "| megapixels | best gradient rule (PSNR) | its Gaussians |", "|---:|---|---:|"]
        for mp in dict.fromkeys(r["megapixels"] for r in grad):
            best = max((r for r in grad if r["megapixels"] == mp), key=lambda r: r["psnr"])
            lines.append(f"| {mp:g} | {best['rule']} ({best['psnr']:.2f} dB) | {best['gaussians']:,} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--megapixels", nargs="+", type=float, default=[0.2, 0.5, 1.0, 2.0])
    p.add_argument("--rules", nargs="+", choices=tuple(RULES), default=["3dgs", "grad-x0.5", "grad-x2", "screen-20px",
                                                                        "screen-0.15", "no-world-prune"])
    p.add_argument("--iters", type=int, default=2000)
    p.add_argument("--views", type=int, default=24)
    p.add_argument("--density", type=float, default=4.0, help="procedural scene density (4: ~11.6k Gaussians)")
    p.add_argument("--init-points", type=int, default=20000)
    p.add_argument("--sh-degree", type=int, default=0, help="the scene has no view dependence (default 0)")
    p.add_argument("--max-gaussians", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", type=Path, default=Path("benchmark-densify"))
    a = p.parse_args(argv)
    device = torch.device(a.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("CUDA is not available (pass --device cpu with tiny --megapixels for a smoke test)")
    rows = []
    for mp in a.megapixels:
        data = capture(mp, a.views, a.density, a.init_points, a.seed, device)
        for rule in a.rules:
            recipe = Recipe(**RULES[rule](data.width, data.height))
            r = train_and_measure(data, strategy="default", iters=a.iters, sh_degree=a.sh_degree, seed=a.seed,
                                  max_gaussians=a.max_gaussians, recipe=recipe, device=device)
            r = {"megapixels": mp, "rule": rule, **r}
            print(json.dumps(r), flush=True)
            rows.append(r)
            write_json(a.out / "results.json", {"rows": rows})
        del data
    report(a.out, f"procedural scene (density {a.density:g}), {a.views} views (every 8th held out), "
                  f"{a.init_points} random initial points, {a.iters} steps, SH degree {a.sh_degree}, default "
                  f"strategy, seed {a.seed}", table(rows), rows, device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
