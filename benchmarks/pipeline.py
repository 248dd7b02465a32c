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
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from harness import append_jsonl, data_root, header, table


def ssgwarp(args: list[str], log) -> float:
    """Run ``python -m ssgwarp ARGS`` (output to ``log``); its wall seconds, or SystemExit on failure."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "ssgwarp", *args], stdout=log, stderr=subprocess.STDOUT)
    if r.returncode:
        raise SystemExit(f"failed ({r.returncode}): ssgwarp {' '.join(args)} (log: {log.name})")
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the capture folder, or its name in the shared data folder")
    ap.add_argument("--style", default="", help="a style image ({style})")
    ap.add_argument("--pipeline", action="append", required=True, help="'LABEL: command; command; ...'")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_pipeline")
    ap.add_argument("--warm", default="reconstruct {data} --out {run} --iters 30 --width 64 --init random "
                    "--random-points 500 --quiet --force",
                    help="the warm-up command ('' to skip; add e.g. --images images_8 where the capture needs it)")
    ap.add_argument("--out", default=None, help="append the rows as JSON lines")
    args = ap.parse_args(argv)
    if not Path(args.data).is_dir() and (data_root() / args.data).is_dir():
        args.data = str(data_root() / args.data)
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
        rows.append({"pipeline": label.strip(), "stages": ", ".join(f"{n} {t:.0f}" for n, t in stages),
                     "total": round(sum(t for _, t in stages), 1), "psnr": m.get("psnr"),
                     "gaussians": m.get("num_gaussians"), "steps": m.get("iters"), "seconds": dict(stages)})
        append_jsonl(args.out, {"machine": header("cuda" if torch.cuda.is_available() else "cpu"), **rows[-1]})
    print(f"\n{header('cuda' if torch.cuda.is_available() else 'cpu')}\n")
    print(table(rows, [("pipeline", "pipeline"), ("stages", "stages (s)"), ("total", "total (s)"),
                       ("psnr", "held-out PSNR"), ("gaussians", "Gaussians"), ("steps", "steps")]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
