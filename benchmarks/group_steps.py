"""Grouping's identity training steps per second at several CPU thread counts (issue 16's CPU target).

Runs ``train_identities`` (the frozen-geometry stage of ``ssgwarp group``) for ``--steps`` steps on a
reconstructed run's scene and training cameras, with targets of K = 2 groups split at the image's middle
(the step's cost does not depend on the targets' content), once per ``--threads`` value, each set as
torch's thread count (which the blending's ``RasterSettings.cpu_threads`` follows by default). Prints a
markdown table; ``--out``: raw JSON.

    ssgwarp reconstruct ../shared/data/lego_200 --out RUN --iters 100 --device cpu
    python benchmarks/group_steps.py RUN --threads 1 2 --steps 60
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ssgwarp.capture.ply import read_ply  # noqa: E402
from ssgwarp.grouping.train import GroupConfig, train_identities  # noqa: E402
from ssgwarp.services.runs import Run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a reconstructed run folder (scene.ply, cameras.json)")
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    run = Run.open(args.run)
    scene = read_ply(args.run / "scene.ply", device="cpu").replace(identities=None)
    cams = run.cameras[run.train_ids]
    C, H, W = len(cams), cams.height, cams.width
    targets = torch.zeros(C, H, W, dtype=torch.long)
    targets[:, :, W // 2:] = 1
    cfg = replace(GroupConfig(), iters=args.steps)
    rows = []
    saved = torch.get_num_threads()
    try:
        for t in args.threads:
            torch.set_num_threads(t)
            train_identities(scene, cams, targets, 2, config=replace(cfg, iters=2), progress=False)  # warm-up
            w0, c0 = time.perf_counter(), time.process_time()
            train_identities(scene, cams, targets, 2, config=cfg, progress=False)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            rows.append({"threads": t, "steps": args.steps, "wall_s": wall, "cpu_s": cpu, "steps_per_s": args.steps / wall})
            print(f"  threads {t}: {args.steps / wall:.2f} steps/s", file=sys.stderr, flush=True)
    finally:
        torch.set_num_threads(saved)
    load = os.getloadavg()[0]
    print(f"\n{datetime.date.today()}, {os.cpu_count()} cores, load average {load:.2f} at the end; "
          f"{len(scene):,} Gaussians, {C} views {W}x{H}, {args.steps} steps (with the one-off neighbour table)\n")
    print("| threads | wall s | process CPU s | steps/s | speed-up |")
    print("|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['threads']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['steps_per_s']:.2f} | "
              f"{r['steps_per_s'] / rows[0]['steps_per_s']:.2f}x |")
    if args.out:
        Path(args.out).write_text(json.dumps({"date": str(datetime.date.today()), "gaussians": len(scene),
                                              "views": C, "size": [W, H], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
