"""Benchmark `ssgwarp stylize` on fern (images_4, 1008x756): seconds per stage and in total.

    python benchmarks/stylize.py                       # reconstruct + group fern, then stylize (defaults)
    python benchmarks/stylize.py --run runs/fern4      # an existing grouped reconstruction of fern images_4
    python benchmarks/stylize.py --synthetic 300000    # no reconstruction: Gaussians from fern's COLMAP points
    python benchmarks/stylize.py --modes ist,global --iters 600
    python benchmarks/stylize.py --synthetic 300000 --random-stage1 sd15   # time Stage 1 without weights

Stage 2 defaults unless flags say otherwise; 4 key views. Stage 1 runs when the
diffusion weights are configured (see docs/stylize.md), otherwise it is skipped
and reported as such. ``--synthetic N`` builds a stand-in scene (N Gaussians
sampled around fern's sparse COLMAP points, 8 groups by k-means on position)
so Stage 2 can be timed at realistic size without a 7k-iteration
reconstruction. ``--random-stage1 sd15`` runs Stage 1 on randomly initialised
SD1.5-size models (``tests/fakeweights.py``: ``random_stage1_components``): the times
are those of the real models, the images are noise — so Stage 2 then times
IST's per-group matching against 4 key views. Results: a markdown table on
stdout and ``OUT/benchmark.json``.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
from shared_data import data_root  # noqa: E402
from ssgwarp.evaluation.features import EXTRACTOR_KINDS  # noqa: E402
sys.path.insert(0, str(ROOT / "tests"))   # fakeweights: random-weight Stage 1 models
DATA = data_root()


def synthetic_run(run: Path, data_dir: Path, images: str, n: int, groups: int = 8, seed: int = 0) -> Path:
    """A grouped run folder whose scene is N Gaussians around the capture's sparse points."""
    from ssgwarp.capture.datasets import data_json, load_dataset
    from ssgwarp.core.fileio import write_json
    from ssgwarp.capture.ply import write_ply
    from ssgwarp.raster.scene import GaussianScene

    data = load_dataset(data_dir, images=images)
    if data.points is None:
        raise SystemExit(f"{data_dir}: no sparse points for --synthetic")
    xyz, rgb = data.points
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, len(xyz), (n,), generator=g)
    spread = torch.cdist(xyz[:2000], xyz[:2000]).topk(4, largest=False).values[:, 1:].mean() * 0.5
    pts = xyz[idx] + torch.randn(n, 3, generator=g) * spread
    # isotropic scales of about the jitter (a k-NN estimate over N points would take minutes on a CPU)
    scale = spread * (0.3 + 0.4 * torch.rand(n, generator=g))
    scene = GaussianScene.from_points(pts, (rgb[idx] + 0.03 * torch.randn(n, 3, generator=g)).clamp(0, 1),
                                      opacity=0.6, sh_degree=3, scale=scale)
    # k-means on positions -> identities (one-hot x 4) and an identity classifier with a background bias
    c = pts[torch.randperm(n, generator=g)[:groups]].clone()
    for _ in range(15):
        lab = torch.cdist(pts, c).argmin(1)
        for k in range(groups):
            if (lab == k).any():
                c[k] = pts[lab == k].mean(0)
    ident = torch.zeros(n, groups)
    ident[torch.arange(n), lab] = 4.0
    scene = scene.replace(identities=ident)
    lin = torch.nn.Linear(groups, groups)
    with torch.no_grad():
        lin.weight.copy_(torch.eye(groups))
        lin.bias.zero_()
    run.mkdir(parents=True, exist_ok=True)
    write_ply(run / "scene.ply", scene)
    data.cameras.save(run / "cameras.json")
    write_json(run / "data.json", data_json(data))
    (run / "groups").mkdir(exist_ok=True)
    torch.save({"dim": groups, "num_groups": groups, "state_dict": lin.state_dict()}, run / "groups" / "classifier.pt")
    return run


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, default=None, help="existing grouped reconstruction of the capture")
    p.add_argument("--data", type=Path, default=DATA / "llff_fern")
    p.add_argument("--images", default="images_4")
    p.add_argument("--recon-iters", type=int, default=7000)
    p.add_argument("--synthetic", type=int, default=0, metavar="N", help="stand-in scene of N Gaussians")
    p.add_argument("--style", type=Path, default=DATA / "styles" / "la_muse.jpg")
    p.add_argument("--modes", default="ist", help="comma-separated Stage 2 modes (ist,global,finetune)")
    p.add_argument("--iters", type=int, default=None, help="Stage 2 steps (default: the CLI default)")
    p.add_argument("--keyviews", type=int, default=4)
    p.add_argument("--stage2", default=None, metavar="K=V,...",
                   help="other Stage 2 options, e.g. blend_weight=0.65,color_max_gain=1.0 (default: the CLI's)")
    p.add_argument("--extractor", default="auto", choices=EXTRACTOR_KINDS)
    p.add_argument("--path-frames", type=int, default=30)
    p.add_argument("--random-stage1", choices=("tiny", "sd15"), default=None,
                   help="run Stage 1 on randomly initialised models of this size (timing only)")
    p.add_argument("--stage1-steps", type=int, default=50)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench_stylize")
    p.add_argument("--device", default="auto")
    args = p.parse_args()

    from ssgwarp.cli import main as cli, resolve_device
    from ssgwarp.stylization.stylize import StylizeOptions, stylize_run
    from ssgwarp.stylization.stage2 import Stage2Config

    device = resolve_device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    prep = {}
    run = args.run
    if run is None:
        t0 = time.perf_counter()
        if args.synthetic:
            run = synthetic_run(args.out / f"synthetic_{args.synthetic}", args.data, args.images, args.synthetic)
            prep["synthetic_scene"] = time.perf_counter() - t0
        else:
            run = args.out / "recon"
            if not (run / "scene.ply").is_file():
                if cli(["reconstruct", str(args.data), "--images", args.images, "--out", str(run),
                        "--iters", str(args.recon_iters), "--device", str(device)]) != 0:
                    return 1
                prep["reconstruct"] = time.perf_counter() - t0
            if not (run / "groups" / "classifier.pt").is_file():
                t1 = time.perf_counter()
                if cli(["group", str(run), "--device", str(device)]) != 0:
                    return 1
                prep["group"] = time.perf_counter() - t1
    models, s1 = None, None
    if args.random_stage1:
        from fakeweights import random_stage1_components
        from ssgwarp.stylization.diffusion_models import Stage1Config, assemble_stage1

        t0 = time.perf_counter()
        dtype = torch.float16 if device.type == "cuda" else torch.float32
        models = assemble_stage1(random_stage1_components(args.random_stage1, device=device), device, dtype)
        prep["random_stage1_models"] = time.perf_counter() - t0
        s1 = Stage1Config(steps=args.stage1_steps)
    results = {}
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        over = {} if args.iters is None else {"iters": args.iters}
        for kv in filter(None, (args.stage2 or "").split(",")):
            k, _, v = kv.partition("=")
            k = k.strip().replace("-", "_")
            kind = type(getattr(Stage2Config(), k, ""))
            over[k] = (v.strip().lower() in ("1", "true", "yes") if kind is bool
                       else float(v) if kind in (float, type(None)) else kind(v))
        s2 = Stage2Config(mode=mode, **over)
        opts = StylizeOptions(keyviews=args.keyviews, extractor=args.extractor, path_frames=args.path_frames)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        m = stylize_run(run, args.style, args.out / f"styled_{mode}", stage2=s2, opts=opts, device=device,
                        force=True, stage1=s1 if mode != "global" else None,
                        stage1_models=models if mode != "global" else None)
        m["peak_gpu_memory_gib"] = (torch.cuda.max_memory_allocated(device) / 2**30) if device.type == "cuda" else None
        results[mode] = m
    dev = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({platform.machine()})"
    rows = ["keyviews", "stage1", "stage2", "stage2_optimisation", "renders", "metrics", "total"]
    print(f"\n`ssgwarp stylize` on {args.data.name} {args.images}, {dev}, {time.strftime('%Y-%m-%d')}")
    if prep:
        print("preparation: " + ", ".join(f"{k} {v:.1f}s" for k, v in prep.items()))
    print("\n| seconds | " + " | ".join(results) + " |")
    print("|---|" + "---|" * len(results))
    for r in rows:
        print(f"| {r} | " + " | ".join(f"{m['seconds'].get(r, float('nan')):.1f}" for m in results.values()) + " |")
    for key in ("gaussians", "views", "resolution", "extractor", "matching", "gram_style_loss_original",
                "gram_style_loss", "content_loss", "peak_gpu_memory_gib"):
        print(f"| {key} | " + " | ".join(str(m.get(key)) for m in results.values()) + " |")
    print("| iters | " + " | ".join(str(m["config"]["iters"]) for m in results.values()) + " |")
    print("| stage 1 ran | " + " | ".join(str(m["stage1"]["ran"]) for m in results.values()) + " |")
    (args.out / "benchmark.json").write_text(json.dumps({"device": dev, "prep_seconds": prep, "runs": results},
                                                        indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
