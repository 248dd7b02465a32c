"""Wall time of the whole pipeline a user runs (``ssgwarp`` commands one after the other, each in its own
process, as from a shell), stage by stage, with the reconstruction's held-out PSNR and Gaussian count.

Each ``--pipeline`` is ``LABEL: COMMAND; COMMAND ...`` with ``{data}`` (the capture), ``{run}`` (a fresh run folder),
``{style}`` and ``{sam}`` filled in; the Warp kernel cache is warmed first (``--warm``). ``--data``: a capture
folder, a folder of the shared data (``llff_fern``, ...) or a procedural capture written once into ``--work``
(``demo:WIDTH``, ``insideout:WIDTH``). ``--random-sam vit-b``: a Segment Anything model with random weights for
``{sam}`` (timed as trained ones; pass ``--pred-iou-thresh 0 --stability-thresh 0`` to ``masks``).

    python benchmarks/pipeline.py --data ../shared/data/llff_fern --style ../shared/data/styles/candy.jpg \
        --pipeline "default: reconstruct {data} --images images_4 --out {run}/rec --groups; \
                    stylize {run}/rec --style {style} --out {run}/sty"
    python benchmarks/pipeline.py --data insideout:256 --pipeline "auto: reconstruct {data} --iters 7000 --out {run}/rec" \
        --pipeline "off: reconstruct {data} --iters 7000 --backdrop off --out {run}/rec"
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

from harness import ROOT, append_jsonl, data_root, header, table


def ssgwarp(args: list[str], log) -> float:
    """Run ``python -m ssgwarp ARGS`` (output to ``log``); its wall seconds, or SystemExit on failure."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "ssgwarp", *args], stdout=log, stderr=subprocess.STDOUT)
    if r.returncode:
        raise SystemExit(f"failed ({r.returncode}): ssgwarp {' '.join(args)} (log: {log.name})")
    return time.perf_counter() - t0


def procedural_capture(spec: str, work: Path) -> Path:
    """The procedural capture ``demo:WIDTH`` or ``insideout:WIDTH`` (4:3 views), written into ``work`` once."""
    from ssgwarp import procedural as P

    kind, _, width = spec.partition(":")
    w = int(width or 96)
    out = work / f"{kind}_{w}"
    if not (out / "transforms.json").is_file():
        gt, cams = ((P.build_scene(1.0), P.ring_cameras(24, w, w * 3 // 4)) if kind == "demo" else
                    (P.build_inside_out(1.0), P.rig_cameras(40, w, w * 3 // 4)))
        bg = {} if kind == "demo" else {"background": (1.0, 1.0, 1.0)}
        P.write_transforms_dataset(out, P.render_views(gt, cams, **bg)[0], cams)
    return out


def random_sam(size: str, work: Path) -> Path:
    """A random-weight ``SamModel`` saved in ``work`` once: ViT-B (``SamConfig()``) or the tests' tiny one."""
    folder = work / f"sam-{size}"
    if not (folder / "config.json").is_file():
        sys.path.insert(0, str(ROOT / "tests"))   # fakeweights: the tests' random-weight models
        from fakeweights import save_tiny_sam

        if size == "tiny":
            save_tiny_sam(folder)
        else:
            from transformers import SamConfig, SamModel

            torch.manual_seed(0)
            SamModel(SamConfig()).save_pretrained(folder)
    return folder


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the capture folder, or its name in the shared data folder")
    ap.add_argument("--style", default="", help="a style image ({style})")
    ap.add_argument("--pipeline", action="append", required=True, help="'LABEL: command; command; ...'")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_pipeline")
    ap.add_argument("--warm", default="reconstruct {data} --out {run} --iters 30 --width 64 --init random "
                    "--random-points 500 --quiet --force",
                    help="the warm-up command ('' to skip; add e.g. --images images_8 where the capture needs it)")
    ap.add_argument("--random-sam", choices=("vit-b", "tiny"), default=None,
                    help="save a random-weight Segment Anything model for {sam}")
    ap.add_argument("--out", default=None, help="append the rows as JSON lines")
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    if args.data.split(":")[0] in ("demo", "insideout"):
        args.data = str(procedural_capture(args.data, args.work))
    elif not Path(args.data).is_dir() and (data_root() / args.data).is_dir():
        args.data = str(data_root() / args.data)
    sam = random_sam(args.random_sam, args.work) if args.random_sam else ""
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
            words = shlex.split(cmd.format(data=args.data, run=run, style=args.style, sam=sam))
            stages.append((words[0], ssgwarp(words, log)))
            print(f"{label.strip()}: {words[0]} {stages[-1][1]:.1f} s", flush=True)
        m = json.loads((run / "rec" / "metrics.json").read_text()) if (run / "rec" / "metrics.json").exists() else {}
        for rec in sorted([*run.glob("*/metrics.json"), *run.glob("*/masks.json")]):   # each stage's own clock
            secs = json.loads(rec.read_text()).get("seconds")
            if isinstance(secs, dict):
                print(f"{label.strip()}: {rec.parent.name}/{rec.name} seconds: " + ", ".join(
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
