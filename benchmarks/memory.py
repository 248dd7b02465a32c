"""Memory of reconstruction: bytes per Gaussian (parameters, gradients, Adam) and the workspace of a
training step per (camera, Gaussian), per Gaussian-tile intersection and per pixel (docs/scaling.md).

For each configuration (Gaussians ``--gaussians``, image width ``--widths``, views per step
``--batch``): fern's COLMAP points, replicated with jitter up to N, the 3DGS initial scene from
them, two training steps (the second measured). Reported per configuration:

* ``persistent``: the bytes of the scene's tensors, their gradients and Adam moments, counted
  from the tensors themselves (exact on any device);
* ``intersections``: Gaussian-tile intersections of the step's views (the length of ``meta["isect_ids"]``);
* on CUDA, ``workspace``: the step's peak allocated memory minus what was allocated before it and
  minus the gradients (counted in ``persistent``).

On CUDA the workspace is then fitted (least squares) as ``a x (views x N) + b x intersections +
c x pixels``: ``a`` bytes per (camera, Gaussian), ``b`` per intersection, ``c`` per pixel (per
megapixel: ``c x 2^20``). On the CPU only the exact and counted columns are printed.

    python benchmarks/memory.py --out memory.json                       # GPU: 8 configurations, ~1 minute
    python benchmarks/memory.py --device cpu --gaussians 20000 --widths 64 --batch 1 --out /tmp/mem.json
"""
from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def data_root() -> Path:
    for p in (Path("/root/data"), ROOT.parent / "shared" / "data", Path("/work/shared/data")):
        if (p / "llff_fern").is_dir():
            return p
    return ROOT.parent / "shared" / "data"


def tensor_bytes(trainer) -> dict:
    """Bytes of the scene's parameters, their gradients (same size) and Adam state, and of the statistics."""
    params = sum(p.numel() * p.element_size() for p in trainer.params.values())
    adam = sum(v.numel() * v.element_size() for p in trainer.params.values()
               for v in trainer.opt.state.get(p, {}).values() if torch.is_tensor(v) and v.dim() > 0)
    stats = sum(v.numel() * v.element_size() for v in trainer.gaussians.stats.values())
    return {"params": params, "grads": params, "adam": adam, "stats": stats}


_SCENES: dict = {}


def measure(data, n: int, batch: int, device: torch.device) -> dict:
    from ssgwarp.reconstruct import Recipe, Trainer

    if n not in _SCENES:  # (the same scene at every width and batch)
        _SCENES[n] = make_scene(data, n, device)
    t = Trainer(data, scene=_SCENES[n], iters=10**6, sh_degree=3, device=device, progress=False, batch_size=batch,
                recipe=Recipe(refine_start=10**7, refine_stop=10**7, batch_scaling="none"))
    seen = {}
    observe = t.strategy.observe

    def counting(gaussians, meta):
        seen["isects"] = int(meta["isect_ids"].numel())
        observe(gaussians, meta)
    t.strategy.observe = counting
    t.train_step()  # (Adam state allocated)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        before = torch.cuda.memory_allocated(device)  # (gradients are freed between steps)
        torch.cuda.reset_peak_memory_stats(device)
    t.train_step()
    row = {"gaussians": n, "views": batch, "width": data.width, "height": data.height,
           "pixels": batch * data.width * data.height, "intersections": seen.get("isects"), **tensor_bytes(t)}
    row["persistent"] = row["params"] + row["grads"] + row["adam"] + row["stats"]
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        row["workspace"] = torch.cuda.max_memory_allocated(device) - before - row["grads"]
    del t
    return row


def make_scene(data, n: int, device: torch.device):
    """``n`` Gaussians: the capture's points replicated with jitter, 3DGS initial widths (3-NN distance)."""
    from ssgwarp.scene import GaussianScene, knn_mean_distance

    xyz, rgb = data.points
    g = torch.Generator().manual_seed(0)
    reps = -(-n // len(xyz))
    spread = (xyz.max(0).values - xyz.min(0).values) * 0.002
    pts = (xyz.repeat(reps, 1) + torch.randn(reps * len(xyz), 3, generator=g) * spread)[:n]
    cols = rgb.repeat(reps, 1)[:n]
    scale = knn_mean_distance(pts.to(device), k=3).clamp_min(1e-7).cpu()
    return GaussianScene.from_points(pts, cols, sh_degree=3, opacity=0.1, scale=scale)


def fit(rows: list) -> dict:
    A = torch.tensor([[r["views"] * r["gaussians"], r["intersections"], r["pixels"]] for r in rows],
                     dtype=torch.float64)
    y = torch.tensor([r["workspace"] for r in rows], dtype=torch.float64)
    coef = torch.linalg.lstsq(A, y[:, None]).solution[:, 0].tolist()
    resid = (A @ torch.tensor(coef, dtype=torch.float64) - y).abs().max().item()
    return {"bytes_per_camera_gaussian": coef[0], "bytes_per_intersection": coef[1], "bytes_per_pixel": coef[2],
            "max_residual_mb": resid / 2**20}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[250_000, 1_000_000])
    ap.add_argument("--widths", type=int, nargs="+", default=[504, 1008])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", type=Path, default=Path("memory.json"))
    a = ap.parse_args()
    from ssgwarp.datasets import load_dataset
    from ssgwarp.fileio import write_json

    device = torch.device(a.device)
    root = a.data or data_root() / "llff_fern"
    rows = []
    for w in a.widths:
        data = load_dataset(root, images="images_4", width=w, seed=0)
        for n, b in itertools.product(a.gaussians, a.batch):
            rows.append(measure(data, n, b, device))
            if device.type == "cuda":
                torch.cuda.empty_cache()
    mb = 2**20
    print("| Gaussians | views | image | intersections | params MB | grads MB | Adam MB | persistent B/Gaussian "
          "| workspace MB |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ws = f"{r['workspace'] / mb:.1f}" if "workspace" in r else "(CUDA only)"
        print(f"| {r['gaussians']:,} | {r['views']} | {r['width']}x{r['height']} | {r['intersections']:,} | "
              f"{r['params'] / mb:.1f} | {r['grads'] / mb:.1f} | {r['adam'] / mb:.1f} | "
              f"{r['persistent'] / r['gaussians']:.0f} | {ws} |")
    out = {"device": str(device), "rows": rows}
    if device.type == "cuda" and len(rows) >= 3:
        out["device_name"] = torch.cuda.get_device_name(device)
        out["fit"] = f = fit(rows)
        print(f"\nworkspace ~ {f['bytes_per_camera_gaussian']:.0f} B per (camera, Gaussian) + "
              f"{f['bytes_per_intersection']:.0f} B per intersection + {f['bytes_per_pixel']:.0f} B per pixel "
              f"(= MiB per 2^20 pixels); max residual "
              f"{f['max_residual_mb']:.1f} MB")
    write_json(a.out, out)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
