"""Data-parallel reconstruction: 1 GPU against N GPUs (torchrun), time to equal held-out quality.

Each configuration in its own process(es), same capture, seed and number of images (``--iters`` one-view steps; a
batch of B trains ``--iters / B`` steps): ``1gpu-b1`` (the plain ``ssgwarp reconstruct``, the reference), ``1gpu-bN``
(N views per step: what batching gives) and ``Ngpu-bN`` (``torchrun``, one view per GPU per step, NCCL). Per
configuration: the training time to the reference's final PSNR - 0.1 dB (held-out PSNR every ``--eval-every``
images), the speed-up, final PSNR, Gaussians and peak memory per GPU (docs/scaling.md).

    python benchmarks/ddp.py --data /root/data/llff_fern --images images_4 --iters 7000 --gpus 2 --out ddp_fern4.json
    python benchmarks/ddp.py --data /root/data/colmap_cup --images images --iters 30000 --only 1gpu-bN \
        --no-single-batch --out c.json                 # some configurations, the others read back from --out
    python benchmarks/ddp.py --images images_8 --width 64 --iters 40 --eval-every 20 --device cpu --out /tmp/ddp.json
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from harness import data_root, machine, sync, table


# ----------------------------------------------------------------------------- one configuration
def worker(a) -> int:
    """Train one configuration (alone or as one torchrun rank); the main rank writes ``a.result``."""
    import torch

    from ssgwarp.services import distributed
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.trainer import Trainer

    group, device = distributed.from_env(a.device)
    try:
        data = load_dataset(a.data, images=a.images, width=a.width, seed=0)  # (the same split for every seed)
        b = a.batch_size
        steps = max(1, a.iters // b)
        t = Trainer(data, iters=steps, device=device, seed=a.seed, progress=False, batch_size=b, group=group,
                    recipe=Recipe(sh_degree=3, batch_scaling=a.batch_scaling))
        every = max(1, a.eval_every // b)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        curve, train_s = [], 0.0
        while t.step < steps:
            sync(device)
            t0 = time.perf_counter()
            t.train(until=min(steps, t.step + every))
            sync(device)
            train_s += time.perf_counter() - t0
            if group.is_main:  # (the others wait at the barrier; not counted)
                ev = t.evaluate()
                curve.append({"step": t.step, "images": t.step * b, "seconds": round(train_s, 3),
                              "psnr": ev["psnr"], "gaussians": t.num_gaussians})
            group.barrier()
        peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else 0.0
        peaks = group.gather(peak)
        if group.is_main:
            ev = t.evaluate()
            row = {"gpus": group.world_size, "batch_size": b, "batch_scaling": a.batch_scaling, "seed": a.seed, "steps": steps,
                   "images": steps * b, "train_seconds": round(train_s, 2), "psnr": ev["psnr"], "ssim": ev["ssim"],
                   "gaussians": t.num_gaussians, "peak_mb_per_gpu": [round(p, 1) for p in peaks], "device": machine(device),
                   "resolution": [data.width, data.height], "curve": curve}
            Path(a.result).write_text(json.dumps(row))
    finally:
        distributed.shutdown(group)
    return 0


# ----------------------------------------------------------------------------- the comparison
def launch(a, gpus: int, batch: int, scaling: str, result: Path) -> dict:
    args = [str(Path(__file__).resolve()), "--worker", "--data", str(a.data), "--images", a.images,
            "--iters", str(a.iters), "--eval-every", str(a.eval_every), "--batch-size", str(batch),
            "--batch-scaling", scaling, "--device", a.device, "--result", str(result), "--seed", str(a.seed)]
    if a.width:
        args += ["--width", str(a.width)]
    cmd = [sys.executable] + (["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(gpus)]
                              if gpus > 1 else []) + args
    env = dict(os.environ, SSGWARP_OFFLINE="1")
    t0 = time.time()
    r = subprocess.run(cmd, env=env)
    if r.returncode != 0 or not result.is_file():
        raise SystemExit(f"{gpus} process(es), batch {batch}: failed (exit {r.returncode})")
    row = json.loads(result.read_text())
    row["wall_seconds"] = round(time.time() - t0, 1)  # (with start-up, data loading and evaluations)
    return row


def time_to(curve: list, target: float, hold: bool = True):
    """Training seconds at which the held-out PSNR reached ``target``; with ``hold``, the first point from which it
    stays there to the end (3DGS curves dip after every opacity reset)."""
    hit = None
    for pt in curve:
        ok = pt["psnr"] is not None and pt["psnr"] >= target
        if ok and hit is None:
            hit = pt["seconds"]
            if not hold:
                return hit
        elif not ok and hold:
            hit = None
    return hit


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None, help="the LLFF fern folder (default: found)")
    ap.add_argument("--images", default="images_4")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--iters", type=int, default=7000, help="images trained on (= one-view steps; default 7000)")
    ap.add_argument("--eval-every", type=int, default=100, help="images between held-out evaluations")
    ap.add_argument("--gpus", type=int, default=2, help="processes of the data-parallel run (default 2)")
    ap.add_argument("--batch-scaling", nargs="+", default=["sqrt"], choices=("sqrt", "linear", "none"),
                    help="Adam's learning-rate scalings: the batch configurations once per scaling (default sqrt)")
    ap.add_argument("--no-single-batch", action="store_true", help="skip the 1-GPU batch-N configuration")
    ap.add_argument("--only", nargs="+", choices=("1gpu-b1", "1gpu-bN", "Ngpu-bN"), default=None,
                    help="run only these configurations (the others are read from earlier runs into the same "
                         "--out, or left out); e.g. the 1-GPU ones of two captures side by side, one per GPU")
    ap.add_argument("--device", default="cuda", help="cuda (default) or cpu (gloo; a smoke test)")
    ap.add_argument("--seed", type=int, default=0, help="training seed of every configuration (default 0)")
    ap.add_argument("--out", type=Path, default=Path("ddp.json"))
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--batch-size", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--result", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        a.batch_scaling = a.batch_scaling[0]
        return worker(a)
    a.data = a.data or data_root() / "llff_fern"
    if a.device == "cuda" and (a.only is None or "Ngpu-bN" in a.only):
        import torch

        if torch.cuda.device_count() < a.gpus:
            raise SystemExit(f"--gpus {a.gpus}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    n = a.gpus
    runs = [(1, 1, "sqrt")]  # (the scaling is irrelevant at batch 1)
    for s in a.batch_scaling:
        if not a.no_single_batch:
            runs.append((1, n, s))
        runs.append((n, n, s))
    tmp = a.out.with_suffix(".parts")
    tmp.mkdir(parents=True, exist_ok=True)
    rows = []
    for gpus, batch, scaling in runs:
        name = "1gpu-b1" if batch == 1 else ("1gpu-bN" if gpus == 1 else "Ngpu-bN")
        part = tmp / f"g{gpus}_b{batch}_{scaling}.json"
        if a.only is not None and name not in a.only:
            if part.is_file():  # measured by an earlier --only call
                rows.append(json.loads(part.read_text()))
            continue
        print(f"== {gpus} GPU(s), batch {batch}, {scaling}", flush=True)
        rows.append(launch(a, gpus, batch, scaling, part))
    if not rows or rows[0]["batch_size"] != 1:
        print(f"no reference (1gpu-b1) in {tmp} yet: table left out")
        return 0
    ref = rows[0]
    target = ref["psnr"] - 0.1
    t_ref = time_to(ref["curve"], target)
    print(f"\n{a.data.name} {a.images} {ref['resolution'][0]}x{ref['resolution'][1]}, {a.iters} images per run, "
          f"target {target:.2f} dB (1 GPU final - 0.1), {ref['device']}\n")
    shown = []
    for r in rows:
        tt, first = time_to(r["curve"], target), time_to(r["curve"], target, hold=False)
        r.update(time_to_target=tt, first_at_target=first, speedup_at_target=round(t_ref / tt, 3) if tt and t_ref else None,
                 speedup_whole_run=round(ref["train_seconds"] / r["train_seconds"], 3))
        shown.append({**r, "reached": "not reached" if tt is None else f"{tt:.1f}",
                      "first": "not reached" if first is None else f"{first:.1f}",
                      "scaling": r["batch_scaling"] if r["batch_size"] > 1 else "-",
                      "peaks": ", ".join(f"{p:.0f}" for p in r["peak_mb_per_gpu"])})
    print(table(shown, [
        ("gpus", "GPUs"), ("batch_size", "batch"), ("scaling", "Adam scaling"), ("steps", "steps"),
        ("train_seconds", "train time (s)", 1), ("first", "first at target (s)"), ("reached", "at target to the end (s)"),
        ("speedup_at_target", "speed-up at target (x)"), ("speedup_whole_run", "speed-up (whole run, x)"),
        ("psnr", "held-out PSNR (dB)"), ("gaussians", "Gaussians"), ("peaks", "peak MiB per GPU")]))
    from ssgwarp.core.fileio import write_json

    write_json(a.out, {"target_psnr": target, "iters": a.iters, "images": a.images, "rows": rows})
    print(f"\nwrote {a.out}")
    return 0


if __name__ == "__main__":
    code = main()
    from ssgwarp.services import distributed as _d

    _d.exit_after_group(code)  # (a torchrun worker: see its docstring)
    sys.exit(code)
