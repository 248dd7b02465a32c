"""Tile size against speed, per device: the measurement behind ``rasterization``'s per-device default.

    python benchmarks/tile_size.py                      # CPU, and CUDA when present
    python benchmarks/tile_size.py --device cpu --tiles 4 8 16 --repeats 3
    python benchmarks/tile_size.py --out tiles.json --markdown tiles.md

Scenes: "ball" is the trade-off table's synthetic scene (benchmarks/tradeoffs.py: Gaussians in a ball,
scales log-uniform in [0.005, 0.08], SH degree 3, seen from 4 units; a few to ~15 pixels across at
256x192): 20,000 Gaussians at 256x192 and 100,000 at 200x200 (lego_200's size); "ball x2" the same
with twice the scales (large Gaussians, where larger tiles win); "small" is
benchmarks/raster.py's scene (scales under 0.02 at depth 8: about a pixel): 10,000 at 256x256; on CUDA
also 1,000,000 "small" at 1920x1080. For each tile size: forward and forward+backward milliseconds
(median of repeats; CUDA synchronised; on the CPU the process's CPU time, which leaves out other load on
a shared machine) and the speed-up against tile size 16. Images are the same at every tile size (the
tile only groups the work), which the script checks.
"""
from __future__ import annotations

import argparse
import datetime
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from raster import camera, make_scene  # noqa: E402

import ssgwarp  # noqa: E402

# (scene, N, width, height)
SCENES = {"cpu": [("ball", 20_000, 256, 192), ("ball", 100_000, 200, 200), ("small", 10_000, 256, 256),
                  ("ball x2", 20_000, 256, 192)],
          "cuda": [("ball", 20_000, 256, 192), ("ball", 100_000, 200, 200), ("small", 10_000, 256, 256),
                   ("ball x2", 20_000, 256, 192), ("ball", 300_000, 1008, 756), ("small", 1_000_000, 1920, 1080)]}


def inputs(kind: str, n: int, w: int, h: int, device):
    """``(params, viewmats, Ks, sh_degree)`` of a scene."""
    if kind == "small":
        vm, K = camera(w, h, device)
        return make_scene(n, device), vm, K, None
    from tradeoffs import synthetic_cameras, synthetic_scene

    sc = synthetic_scene(n, 3, seed=0).to(device=device, dtype=torch.float32)
    cams = synthetic_cameras(1, w, h)
    grow = 2.0 if kind.endswith("x2") else 1.0
    params = [sc.means, sc.quats, sc.scales * grow, sc.opacities, sc.sh_coeffs.contiguous()]
    return [p.detach().contiguous() for p in params], cams.viewmats.to(device), cams.Ks.to(device), 3


def timed(fn, device, repeats: int) -> float:
    cuda = device.type == "cuda"
    now = time.perf_counter if cuda else time.process_time
    fn()
    if cuda:
        torch.cuda.synchronize()
    out = []
    for _ in range(repeats):
        t0 = now()
        fn()
        if cuda:
            torch.cuda.synchronize()
        out.append((now() - t0) * 1e3)
    return statistics.median(out)


def measure(device, kind, n, w, h, tiles, repeats):
    params, vm, K, deg = inputs(kind, n, w, h, device)
    leaves = [p.clone().requires_grad_(True) for p in params]
    rows, ref = [], None
    for ts in tiles:
        def fwd():
            with torch.no_grad():
                return ssgwarp.rasterization(*params, vm, K, w, h, sh_degree=deg, tile_size=ts)[0]

        def fwd_bwd():
            for p in leaves:
                p.grad = None
            img, alpha, _ = ssgwarp.rasterization(*leaves, vm, K, w, h, sh_degree=deg, tile_size=ts)
            (img.sum() + alpha.sum()).backward()

        img = fwd()
        ref = img if ref is None else ref
        rows.append({"device": device.type, "scene": kind, "N": n, "res": f"{w}x{h}",
                     "sh": "colours" if deg is None else deg,
                     "tile_size": ts, "fwd_ms": timed(fwd, device, repeats),
                     "fwd_bwd_ms": timed(fwd_bwd, device, repeats), "max_image_diff": float((img - ref).abs().max())})
        print(json.dumps(rows[-1]), flush=True)
    base = next((r for r in rows if r["tile_size"] == 16), rows[0])
    for r in rows:
        r["speedup_fwd"] = base["fwd_ms"] / r["fwd_ms"]
        r["speedup_fwd_bwd"] = base["fwd_bwd_ms"] / r["fwd_bwd_ms"]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["all", "cpu", "cuda"], default="all")
    ap.add_argument("--tiles", type=int, nargs="*", default=[2, 4, 6, 8, 12, 16])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: torch's default)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = [torch.device(d) for d in ("cpu", "cuda") if args.device in ("all", d)
               and (d == "cpu" or torch.cuda.is_available())]
    rows = []
    for dev in devices:
        for kind, n, w, h in SCENES[dev.type]:
            rows += measure(dev, kind, n, w, h, args.tiles, args.repeats)
    lines = [f"{datetime.date.today().isoformat()}; torch {torch.__version__}; "
             f"{torch.cuda.get_device_name() if torch.cuda.is_available() else 'no GPU'}; torch threads "
             f"{torch.get_num_threads()}", "",
             "| device | scene | N | resolution | SH | tile size | fwd ms | fwd+bwd ms | fwd speed-up vs 16 | "
             "fwd+bwd speed-up vs 16 | max image diff vs first tile |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['device']} | {r['scene']} | {r['N']:,} | {r['res']} | {r['sh']} | {r['tile_size']} | "
                     f"{r['fwd_ms']:.1f} | "
                     f"{r['fwd_bwd_ms']:.1f} | {r['speedup_fwd']:.2f}x | {r['speedup_fwd_bwd']:.2f}x | "
                     f"{r['max_image_diff']:.1e} |")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        Path(args.markdown).write_text(text + "\n")
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
