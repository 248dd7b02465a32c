"""Cost of one step of our training loop with each rasterizer: milliseconds per step, the device
synchronisations a step makes (and where), and the host ops that cost the most.

One :class:`ssgwarp.reconstruction.reconstruct.Trainer` per backend on the same capture, seed and recipe
(the loop of ``benchmarks/reconstruct.py``): ``--warm`` steps first (past the first refinements, so the
Gaussian count is a trained scene's), then ``--steps`` timed steps between two refinements. On CUDA the
synchronisations come from torch's sync debug mode (each synchronising call and the ssgwarp / kornia /
gsplat / torch.optim frames that made it); ``--profile`` adds torch.profiler's top host ops.

    python benchmarks/train_step.py                              # fern images_8, ssgwarp and gsplat
    python benchmarks/train_step.py --scene fern4 --backend ssgwarp --profile
    python benchmarks/train_step.py --scene PATH:images --warm 100 --steps 20 --device cpu
"""
from __future__ import annotations

import argparse
import collections
import sys
import time
import traceback
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from reconstruct import load_scene, rasterizer, warm_up  # noqa: E402
from shared_data import data_root  # noqa: E402

from ssgwarp.reconstruction.reconstruct import Trainer  # noqa: E402

FRAMES = ("ssgwarp", "kornia", "gsplat", "torch/optim")  # the frames a synchronisation is attributed to


def sync_sites(step, steps: int = 3) -> collections.Counter:
    """``{(message, 'file:line:function <- ...'): count}`` of the synchronising CUDA calls ``steps``
    calls of ``step()`` make (torch's sync debug mode, as warnings)."""
    sites: collections.Counter = collections.Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack()[:-2] if any(k in f.filename for k in FRAMES)]
        where = " <- ".join(f"{Path(f.filename).name}:{f.lineno}:{f.name}" for f in frames[-3:])
        sites[(str(message).split("(")[0].strip()[:50], where)] += 1

    with warnings.catch_warnings():  # (restores the filters and showwarning)
        warnings.simplefilter("always")
        warnings.showwarning = record
        torch.cuda.set_sync_debug_mode(1)
        try:
            for _ in range(steps):
                step()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    return sites


def measure(data, backend: str, args, device: torch.device) -> dict:
    fn, kw = rasterizer(backend)
    torch.manual_seed(args.seed)
    t = Trainer(data, iters=args.iters, sh_degree=3, rasterize=fn, raster_kwargs=kw, device=device, seed=args.seed,
                progress=False)
    warm_up(t)
    for _ in range(args.warm):
        t.train_step()
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        t.train_step()
    sync()
    row = {"backend": backend, "ms_per_step": (time.perf_counter() - t0) / args.steps * 1e3, "step": t.step,
           "gaussians": t.num_gaussians, "syncs": []}
    if device.type == "cuda":
        for (msg, where), n in sorted(sync_sites(t.train_step).items(), key=lambda kv: kv[0][1]):
            if "prototype" not in msg:
                row["syncs"].append(f"{n // 3} per step: {where or '(no ssgwarp frame)'}")
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=acts) as p:
            for _ in range(5):
                t.train_step()
            sync()
        row["profile"] = p.key_averages().table(sort_by="cpu_time_total", row_limit=60)
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="fern8", help="fern8, fern4, cup, lego or PATH[:IMAGES]")
    p.add_argument("--data-root", type=Path, default=None)
    p.add_argument("--backend", nargs="+", choices=("ssgwarp", "gsplat"), default=["ssgwarp", "gsplat"])
    p.add_argument("--warm", type=int, default=700,
                   help="steps before the timing (default 700: past the 7k schedule's refinements at 117..700)")
    p.add_argument("--steps", type=int, default=90, help="timed steps (default 90: up to the next refinement)")
    p.add_argument("--iters", type=int, default=7000, help="the run's length, which sets the schedule")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's top host ops")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    data = load_scene(args.scene, args.data_root or data_root(), device)
    rows = [measure(data, b, args, device) for b in args.backend]
    print(f"\n{args.scene}, {device.type}: steps {args.warm + 1}-{args.warm + args.steps} of a {args.iters}-step run\n")
    print("| backend | ms per step | Gaussians | synchronisations per step |")
    print("|---|---:|---:|---|")
    for r in rows:
        print(f"| {r['backend']} | {r['ms_per_step']:.2f} | {r['gaussians']:,} | {'; '.join(r['syncs']) or '-'} |")
    if len(rows) == 2:
        print(f"\nratio {rows[0]['backend']} / {rows[1]['backend']}: {rows[0]['ms_per_step'] / rows[1]['ms_per_step']:.2f}x")
    for r in rows:
        if "profile" in r:
            print(f"\n{r['backend']}: top host ops over 5 steps\n{r['profile']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
