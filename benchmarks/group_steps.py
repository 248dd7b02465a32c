"""Grouping's identity training steps per second at several CPU thread counts (issue 16's CPU target).

Runs ``train_identities`` (the frozen-geometry stage of ``ssgwarp group``) for ``--steps`` and for 2 steps on a
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

import ssgwarp  # noqa: E402,F401  (before torch, as the CLI: its OpenMP wait policy, ssgwarp/__init__.py)
import torch  # noqa: E402
import ssgwarp.raster.cpu_threads as CT  # noqa: E402
from ssgwarp.capture.ply import read_ply  # noqa: E402
from ssgwarp.grouping.train import train_identities  # noqa: E402
from ssgwarp.grouping.model import GroupConfig
from ssgwarp.services.runs import Run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a reconstructed run folder (scene.ply, cameras.json)")
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--blend-threads", type=int, default=None,
                    help="pin the blending's threads to this count (default: torch's, as ssgwarp does)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.blend_threads is not None:
        CT.wanted = lambda _cpu_threads: args.blend_threads
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
            times = []
            for iters in (2, 2, args.steps):  # (a warm-up; then 2 steps: the one-off neighbour table's share)
                w0, c0 = time.perf_counter(), time.process_time()
                train_identities(scene, cams, targets, 2, config=replace(cfg, iters=iters), progress=False)
                times.append((time.perf_counter() - w0, time.process_time() - c0))
            wall, cpu = times[2]
            per_step = (times[2][0] - times[1][0]) / (args.steps - 2)
            rows.append({"threads": t, "steps": args.steps, "wall_s": wall, "cpu_s": cpu, "steps_per_s": 1 / per_step,
                         "two_steps_s": times[1][0]})
            print(f"  threads {t}: {1 / per_step:.2f} steps/s", file=sys.stderr, flush=True)
    finally:
        torch.set_num_threads(saved)
    load = os.getloadavg()[0]
    pinned = f"blending pinned to {args.blend_threads} thread(s), " if args.blend_threads else ""
    print(f"\n{datetime.date.today()}, {os.cpu_count()} cores, {pinned}OMP_WAIT_POLICY "
          f"{os.environ.get('OMP_WAIT_POLICY')}, load average {load:.2f} at the end; "
          f"{len(scene):,} Gaussians, {C} views {W}x{H}; steps/s from a {args.steps}-step and a 2-step run "
          f"(without the one-off start: neighbour table, allocations)\n")
    print("| threads | wall s | process CPU s | steps/s | speed-up |")
    print("|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['threads']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['steps_per_s']:.2f} | "
              f"{r['steps_per_s'] / rows[0]['steps_per_s']:.2f}x |")
    if args.out:
        Path(args.out).write_text(json.dumps({"date": str(datetime.date.today()), "gaussians": len(scene),
                                              "blend_threads": args.blend_threads,
                                              "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                                              "views": C, "size": [W, H], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
