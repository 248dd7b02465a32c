"""Training schedules (ssgwarp.reconstruction.schedules) measured: held-out PSNR, Gaussians, train time and steps of
`reconstruct` runs with a coarse-to-fine resolution schedule, an SH-degree schedule and the stop rule (--iters auto),
one row per run.

Each ``--runs`` entry is ``SCENE:ITERS[:OPTIONS]``. SCENE: ``fern4`` / ``fern8`` (LLFF fern images_4 / images_8),
``livingroom`` (livingroom_360), ``cup`` (colmap_cup), ``demo`` (the procedural demo scene, 24 ring views written once
per width into ``--work``, 2,000 random initial points, SH degree 0, as ``ssgwarp demo``) or a capture folder. ITERS: a step count or ``auto``. OPTIONS, comma-separated ``key=value``:

* ``c2f=F``: coarse-to-fine from downsampling factor F (``Recipe.res_start``); ``c2f_until=N``: full resolution
  from step N (default: the end of densification);
* ``sh_start=N``: the first SH-degree raise at step N (``Recipe.sh_start``), ``sh_interval=N``: then one every N;
  ``sh=D``: final SH degree D (default 3);
* ``tol=DB``, ``patience=K``, ``every=N``, ``tail=FRACTION``, ``views=K``: the stop rule's (``--iters auto``);
* ``refine_start=N``, ``refine_stop=N``, ``refine_every=N``, ``reset_every=N``: the densification schedule;
* ``max_g=N``: at most N Gaussians (default 1,000,000; demo: 6,000); ``width=W``: images resized to width W; ``trace=N``: every N steps, the stop rule's training-view PSNR and the
  held-out PSNR are measured (outside the timed training) and printed, with the steps the stop rule would have
  stopped at for a few tolerances (the tail not included).

Rows go to stdout (a markdown table) and ``--out`` (JSON lines).

    python benchmarks/schedules.py --runs demo:600:width=96 demo:600:width=96,c2f=4 demo:auto:width=96 --device cpu
    python benchmarks/schedules.py --runs fern4:7000 fern4:7000:c2f=4 fern4:7000:sh_start=3000 fern4:auto \
        fern4:auto:c2f=4 --out runs/schedules.jsonl       # one H100: about 6 minutes
    python benchmarks/schedules.py --runs fern4:30000:trace=1000   # the curves the stop rule sees (about 5.5 min)
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
from shared_data import data_root  # noqa: E402

from ssgwarp.capture.datasets import load_dataset  # noqa: E402
from ssgwarp.reconstruction.recipe import Recipe  # noqa: E402
from ssgwarp.reconstruction.schedules import AUTO, check_views, plateaued  # noqa: E402
from ssgwarp.reconstruction.trainer import Trainer  # noqa: E402

SHARED = {"livingroom": ("livingroom_360", "images"), "fern4": ("llff_fern", "images_4"),
          "fern8": ("llff_fern", "images_8"), "cup": ("colmap_cup", "images")}
RECIPE_KEYS = {"c2f": ("res_start", float), "c2f_until": ("res_until", int), "sh_start": ("sh_start", int),
               "sh_interval": ("sh_interval", int), "tol": ("stop_tol", float), "patience": ("stop_patience", int),
               "every": ("stop_every", int), "tail": ("stop_tail", float), "views": ("stop_views", int),
               "refine_start": ("refine_start", int), "refine_stop": ("refine_stop", int),
               "refine_every": ("refine_every", int), "reset_every": ("reset_every", int)}
OTHER_KEYS = {"width": int, "trace": int, "sh": int, "max_g": int}


def demo_capture(folder: Path, width: int) -> Path:
    """The procedural demo scene seen by 24 ring cameras at ``width`` (4:3), written once."""
    from ssgwarp.procedural import build_scene, render_views, ring_cameras, write_transforms_dataset

    out = folder / f"demo_{width}"
    if not (out / "transforms.json").is_file():
        cams = ring_cameras(24, width, width * 3 // 4)
        images, _ = render_views(build_scene(1.0), cams)
        write_transforms_dataset(out, images, cams)
    return out


def load(scene: str, width, work: Path):
    if scene in SHARED:
        name, images = SHARED[scene]
        return load_dataset(data_root() / name, images=images, width=width, progress=False)
    if scene == "demo":   # as `ssgwarp demo` trains it: from 2,000 random points
        return load_dataset(demo_capture(work, width or 96), progress=False, init="random", num_random_points=2000)
    return load_dataset(scene, width=width, progress=False)


def parse(spec: str) -> tuple[str, object, dict, dict]:
    """``(scene, iters, recipe fields, other options)`` of a ``--runs`` entry."""
    parts = spec.split(":")
    if len(parts) < 2:
        raise SystemExit(f"--runs {spec!r}: expected SCENE:ITERS[:OPTIONS]")
    scene, iters = parts[0], (AUTO if parts[1] == AUTO else int(parts[1]))
    recipe, other = {}, {}
    for kv in filter(None, (parts[2] if len(parts) > 2 else "").split(",")):
        k, _, v = kv.partition("=")
        if k in RECIPE_KEYS:
            field, kind = RECIPE_KEYS[k]
            recipe[field] = kind(v)
        elif k in OTHER_KEYS:
            other[k] = OTHER_KEYS[k](v)
        else:
            raise SystemExit(f"--runs {spec!r}: unknown option {k!r} (known: "
                             f"{', '.join([*RECIPE_KEYS, *OTHER_KEYS])})")
    return scene, iters, recipe, other


def replay(trace: list[dict], recipe: Recipe) -> list[dict]:
    """Where the stop rule would have seen a plateau on a traced run (checks at the traced steps from the
    end of densification on), for the run's patience and a few tolerances."""
    out = []
    first = [t for t in trace if t["step"] >= recipe.refine_stop]
    for tol in sorted({recipe.stop_tol, 0.05, 0.1, 0.2, 0.3}):
        hit = next((t for i, t in enumerate(first)
                    if plateaued([u["train_psnr"] for u in first[:i + 1]], recipe.stop_patience, tol)), None)
        out.append({"tol": tol, "patience": recipe.stop_patience, "step": None if hit is None else hit["step"],
                    "heldout_psnr": None if hit is None else hit["heldout_psnr"]})
    return out


def run_one(spec: str, args, machine: str) -> dict:
    scene, iters, fields, other = parse(spec)
    t0 = time.time()
    data = load(scene, other.get("width"), args.work)
    load_seconds = time.time() - t0
    demo = scene == "demo"   # (the demo's SH degree 0 and budget of 6,000 Gaussians unless given)
    tr = Trainer(data, iters=iters, sh_degree=other.get("sh", 0 if demo else 3), device=args.device,
                 max_gaussians=other.get("max_g", 6000 if demo else 1_000_000), recipe=Recipe(**fields), progress=False)
    trace = []
    every = other.get("trace")
    while not tr.finished:
        tr.train(until=tr.step + every if every else None)
        if every:
            ids = check_views(data.train_ids, tr.recipe.stop_views)
            trace.append({"step": tr.step, "train_psnr": tr.evaluate(ids)["psnr"],
                          "heldout_psnr": tr.evaluate()["psnr"], "gaussians": tr.num_gaussians,
                          "seconds": round(tr.elapsed, 1)})
            print(f"  {spec} step {tr.step}: training views {trace[-1]['train_psnr']:.2f} dB, held-out "
                  f"{trace[-1]['heldout_psnr']:.2f} dB, {tr.num_gaussians} Gaussians, {tr.elapsed:.0f} s", flush=True)
    ev = tr.evaluate()
    rec = tr.schedules.record(tr.step)
    row = {"capture": scene, "width": data.width, "height": data.height, "views": len(data.train_ids),
           "iters": iters, "options": fields | {k: v for k, v in other.items() if k != "width"},
           "steps": tr.step, "stopped": rec["stopped"], "psnr": ev["psnr"], "ssim": ev["ssim"],
           "gaussians": tr.num_gaussians, "train_seconds": round(tr.elapsed, 1),
           "step_ms": round(1000 * tr.elapsed / max(1, tr.step), 2), "load_seconds": round(load_seconds, 1),
           "refine_stop": tr.recipe.refine_stop, "decided_at": rec.get("stop_rule", {}).get("decided_at"),
           "checks": rec.get("stop_rule", {}).get("checks"),
           "machine": machine, "date": time.strftime("%Y-%m-%d")}
    if trace:
        row["trace"] = trace
        row["replay"] = replay(trace, tr.recipe)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_schedules")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    for spec in args.runs:   # bad specs fail before any training
        parse(spec)
    machine = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else platform.processor() or "cpu"
    rows = []
    for spec in args.runs:
        row = run_one(spec, args, machine)
        rows.append(row)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
        for r in row.get("replay", []):
            print(f"  {spec}: the stop rule (patience {r['patience']}, tol {r['tol']} dB) would stop at "
                  f"{r['step']} (held-out {r['heldout_psnr']})", flush=True)
    print("\n| capture | iters | options | steps | held-out PSNR | Gaussians | train (s) | ms/step | plateau at | machine |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        opts = ",".join(f"{k}={v}" for k, v in r["options"].items()) or "-"
        print(f"| {r['capture']} {r['width']}x{r['height']} | {r['iters']} | {opts} | {r['steps']} | "
              f"{r['psnr']:.2f} | {r['gaussians']} | {r['train_seconds']:.0f} | {r['step_ms']:.2f} | "
              f"{r['decided_at'] if r['decided_at'] is not None else '-'} | {r['machine']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
