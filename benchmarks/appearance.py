"""Per-image appearance (``reconstruct --appearance``), measured: the check of issue 64 on ``lego_200``.

A copy of ``lego_200`` whose photos get a seeded exposure and white balance each
(:func:`ssgwarp.procedural.vary_exposures`: gain 0.6-1.4, tint +-10 % per channel) is reconstructed
with the defaults at ``--iters`` steps; its renders of the training views (the scene itself, no per-image
transform: what ``ssgwarp render --split train`` writes) are scored against the UNMODIFIED images and
compared with the run on the unmodified capture. Each ``--runs`` entry is ``CAPTURE:MODE`` with CAPTURE
``orig`` (lego_200) or ``exp`` (the varied copy, written once into ``--work``) and MODE ``auto`` / ``on`` /
``off``. One row per run: the training views' PSNR against the unmodified images, the held-out PSNR under
the run's protocol (``eval_protocol``), the appearance decision and its evidence.

    python benchmarks/appearance.py --runs orig:auto exp:auto exp:off --iters 600 --device cpu
    python benchmarks/appearance.py --runs orig:auto exp:auto --iters 600 --width 100   # a faster look

Target (issue 64): ``exp:auto`` within 0.3 dB of ``orig:auto`` (before: 24.46 against 25.41 dB), and
``orig:auto`` decides off.
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
sys.path.insert(0, str(ROOT))
from shared_data import data_root  # noqa: E402

from ssgwarp.capture.datasets import load_dataset  # noqa: E402
from ssgwarp.procedural import vary_exposures  # noqa: E402
from ssgwarp.reconstruction.trainer import Trainer  # noqa: E402
from ssgwarp.services.losses import psnr  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=["orig:auto", "exp:auto", "exp:off"])
    ap.add_argument("--iters", type=int, default=600)
    ap.add_argument("--width", type=int, default=None, help="resize the images (default: as stored, 200)")
    ap.add_argument("--seed", type=int, default=0, help="the exposures' seed (default 0)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "ssgwarp_appearance")
    ap.add_argument("--out", type=Path, default=None, help="append JSON lines here")
    args = ap.parse_args(argv)
    src = data_root() / "lego_200"
    varied = args.work / f"lego_200_exposures_{args.seed}"
    if not varied.is_dir():
        args.work.mkdir(parents=True, exist_ok=True)
        vary_exposures(src, varied, seed=args.seed)
    machine = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else platform.processor() or "cpu"
    cache = {}

    def data(name):
        if name not in cache:
            cache[name] = load_dataset(src if name == "orig" else varied, width=args.width, progress=False,
                                       device=args.device)
        return cache[name]

    print("| capture | --appearance | decision | train views vs unmodified (dB) | held-out (dB, protocol) | "
          "Gaussians | train (s) | machine |")
    print("|---|---|---|---|---|---|---|---|")
    for spec in args.runs:
        name, mode = spec.split(":")
        d, truth = data(name), data("orig")
        tr = Trainer(d, iters=args.iters, device=args.device, progress=False, appearance=mode)
        tr.train()
        ids = list(d.train_ids)
        train_psnr = sum(float(psnr(tr.render([i]), truth.images[i][None])) for i in ids) / len(ids)
        ev = tr.evaluate()
        rec = tr.appearance_record or {"use": False, "why": "run ended before the probe"}
        proto = "half" if tr.appearance is not None else "full"
        row = {"capture": name, "mode": mode, "iters": args.iters, "width": d.width, "train_psnr_vs_unmodified":
               train_psnr, "heldout_psnr": ev["psnr"], "eval_protocol": tr.eval_protocol, "appearance": rec,
               "fitted": tr.appearance.summary() if tr.appearance is not None else None,
               "gaussians": tr.num_gaussians, "train_seconds": round(tr.elapsed, 1), "machine": machine,
               "date": time.strftime("%Y-%m-%d")}
        print(f"| lego_200 {'(varied exposures)' if name == 'exp' else ''} {d.width}px | {mode} | "
              f"{'on' if rec['use'] else 'off'} ({rec.get('exposure_spread', '-')}) | {train_psnr:.2f} | "
              f"{ev['psnr']:.2f} ({proto}) | {tr.num_gaussians} | {tr.elapsed:.0f} | {machine} |", flush=True)
        print("   ", rec.get("why"), flush=True)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
