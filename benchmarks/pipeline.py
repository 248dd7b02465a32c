"""Wall time of the whole pipeline a user runs (``ssgwarp`` commands one after the other, each in its own
process, as from a shell), stage by stage, with the reconstruction's held-out PSNR and Gaussian count.

Each ``--pipeline`` is a label and the commands it runs, ``;``-separated, with ``{data}`` (the capture),
``{run}`` (a fresh run folder) and ``{style}`` (a style image) filled in. The Warp kernel cache is warmed first
(``--warm``: one tiny reconstruction by default, so no pipeline pays for compiling kernels a user compiles only once).

    python benchmarks/pipeline.py --data ../shared/data/llff_fern --style ../shared/data/styles/candy.jpg \\
        --pipeline "30k: reconstruct {data} --images images_4 --out {run}/rec; group {run}/rec; \\
                    stylize {run}/rec --style {style} --out {run}/sty" \\
        --pipeline "default: reconstruct {data} --images images_4 --out {run}/rec --groups auto; \\
                    stylize {run}/rec --style {style} --out {run}/sty"

Prints a markdown table: one row per pipeline, the seconds of each stage, the total, and the held-out PSNR and
Gaussians of ``{run}/rec/metrics.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def ssgwarp(args: list[str], log) -> float:
    """Run ``python -m ssgwarp ARGS`` (output to ``log``); its wall seconds, or SystemExit on failure."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "ssgwarp", *args], stdout=log, stderr=subprocess.STDOUT)
    if r.returncode:
        raise SystemExit(f"failed ({r.returncode}): ssgwarp {' '.join(args)} (log: {log.name})")
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the capture folder")
    ap.add_argument("--style", default="", help="a style image ({style})")
    ap.add_argument("--pipeline", action="append", required=True, help="'LABEL: command; command; ...'")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_pipeline")
    ap.add_argument("--warm", default="reconstruct {data} --out {run} --iters 30 --width 64 --init random "
                    "--random-points 500 --quiet --force",
                    help="the warm-up command ('' to skip; add e.g. --images images_8 where the capture needs it)")
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    log = open(args.work / "log.txt", "a")
    if args.warm:
        secs = ssgwarp(shlex.split(args.warm.format(data=args.data, run=args.work / "warm", style=args.style)), log)
        print(f"warm-up (kernel cache): {secs:.0f} s", flush=True)
    rows = []
    for spec in args.pipeline:
        label, _, body = spec.partition(":")
        run = args.work / label.strip().replace(" ", "_")
        if run.exists():
            shutil.rmtree(run)
        run.mkdir(parents=True)
        stages = []
        for cmd in filter(None, (c.strip() for c in body.split(";"))):
            words = shlex.split(cmd.format(data=args.data, run=run, style=args.style))
            stages.append((words[0], ssgwarp(words, log)))
            print(f"{label.strip()}: {words[0]} {stages[-1][1]:.1f} s", flush=True)
        m = json.loads((run / "rec" / "metrics.json").read_text()) if (run / "rec" / "metrics.json").exists() else {}
        for sub in sorted(p.parent for p in run.glob("*/metrics.json")):   # each stage's own clock, where kept
            secs = json.loads((sub / "metrics.json").read_text()).get("seconds")
            if isinstance(secs, dict):
                print(f"{label.strip()}: {sub.name} seconds: " + ", ".join(
                    f"{k} {v:.1f}" for k, v in secs.items() if isinstance(v, (int, float))), flush=True)
        rows.append((label.strip(), stages, m))
    print("\n| pipeline | stages (s) | total (s) | held-out PSNR | Gaussians | steps |")
    print("|---|---|---:|---:|---:|---:|")
    for label, stages, m in rows:
        st = ", ".join(f"{n} {s:.0f}" for n, s in stages)
        ps = "n/a" if m.get("psnr") is None else f"{m['psnr']:.2f}"
        print(f"| {label} | {st} | {sum(s for _, s in stages):.0f} | {ps} | {m.get('num_gaussians', 'n/a')} | "
              f"{m.get('iters', 'n/a')} |")
    print(f"\n{os.uname().nodename}, {time.strftime('%Y-%m-%d')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
