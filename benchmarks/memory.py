"""Memory of reconstruction: bytes per Gaussian (parameters, gradients, Adam) and the workspace of a
training step per (camera, Gaussian), per Gaussian-tile intersection and per pixel (docs/scaling.md).

For each configuration (Gaussians ``--gaussians``, image width ``--widths``, views per step
``--batch``): fern's COLMAP points, replicated with jitter up to N, the 3DGS initial scene from
them, two training steps (the second measured). Reported per configuration:

* ``persistent``: the bytes of the scene's tensors, their gradients and Adam moments, counted
  from the tensors themselves (exact on any device);
* ``intersections``: Gaussian-tile intersections of the step's views (the length of ``meta["isect_ids"]``);
* on CUDA, ``workspace``: the step's peak allocated memory minus what was allocated before it and
  minus the gradients (counted in ``persistent``), and the same peak per phase: ``peak_render_backward``
  (forward, loss and backward, up to the densification statistics) and ``peak_optimizer`` (statistics,
  Adam step, strategy), both minus what was allocated before the step (gradients included).

The step's peak is the larger of the phases' peaks, not a sum of terms, and in these configurations
intersections grow with views x N; a least-squares fit of ``a x (views x N) + b x intersections +
c x pixels`` is ill-conditioned (on an H200 it gave a negative ``b``). So on CUDA the script reports
differences between pairs of configurations that differ in one factor only: per added (camera,
Gaussian) at a fixed image and views count, per added pixel at fixed N and views, per added view.

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
from shared_data import data_root  # noqa: E402


def tensor_bytes(trainer) -> dict:
    """Bytes of the scene's parameters, their gradients (same size) and Adam state, and of the statistics."""
    params = sum(p.numel() * p.element_size() for p in trainer.params.values())
    adam = sum(v.numel() * v.element_size() for p in trainer.params.values()
               for v in trainer.opt.state.get(p, {}).values() if torch.is_tensor(v) and v.dim() > 0)
    stats = sum(v.numel() * v.element_size() for v in trainer.gaussians.stats.values())
    return {"params": params, "grads": params, "adam": adam, "stats": stats}


_SCENES: dict = {}


def measure(data, n: int, batch: int, device: torch.device) -> dict:
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.trainer import Trainer

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
    phase = {}
    if device.type == "cuda":
        def counting_cuda(gaussians, meta):  # (after backward: the render + loss + backward phase ends here)
            phase["render_backward"] = torch.cuda.max_memory_allocated(device) - before
            torch.cuda.reset_peak_memory_stats(device)
            counting(gaussians, meta)
        t.strategy.observe = counting_cuda
    t.train_step()
    row = {"gaussians": n, "views": batch, "width": data.width, "height": data.height,
           "pixels": batch * data.width * data.height, "intersections": seen.get("isects"), **tensor_bytes(t)}
    row["persistent"] = row["params"] + row["grads"] + row["adam"] + row["stats"]
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        rest = torch.cuda.max_memory_allocated(device) - before
        row["peak_render_backward"] = phase["render_backward"]
        row["peak_optimizer"] = rest
        row["workspace"] = max(phase["render_backward"], rest) - row["grads"]
    del t
    return row


def make_scene(data, n: int, device: torch.device):
    """``n`` Gaussians: the capture's points replicated with jitter, 3DGS initial widths (3-NN distance)."""
    from ssgwarp.raster.scene import GaussianScene
    from ssgwarp.core.geometry import knn_mean_distance

    xyz, rgb = data.points
    g = torch.Generator().manual_seed(0)
    reps = -(-n // len(xyz))
    spread = (xyz.max(0).values - xyz.min(0).values) * 0.002
    pts = (xyz.repeat(reps, 1) + torch.randn(reps * len(xyz), 3, generator=g) * spread)[:n]
    cols = rgb.repeat(reps, 1)[:n]
    scale = knn_mean_distance(pts.to(device), k=3).clamp_min(1e-7).cpu()
    return GaussianScene.from_points(pts, cols, sh_degree=3, opacity=0.1, scale=scale)


_FACTORS = ("gaussians", "width", "views")


def pairwise(rows: list) -> list:
    """Workspace differences between configurations that differ in one factor only.

    Per pair: the factor, the two values, the other two factors, the workspace difference and what it is
    per unit of the quantity that changed: bytes per added (camera, Gaussian) when N changes, per added
    pixel when the width changes, MB per added view when the views change."""
    out = []
    for a, b in itertools.combinations(rows, 2):
        diff = [f for f in _FACTORS if a[f] != b[f]]
        if len(diff) != 1 or "workspace" not in a or "workspace" not in b:
            continue
        f = diff[0]
        lo, hi = (a, b) if a[f] < b[f] else (b, a)
        d = hi["workspace"] - lo["workspace"]
        if f == "gaussians":
            per, unit = d / (lo["views"] * (hi["gaussians"] - lo["gaussians"])), "B per camera x Gaussian"
        elif f == "width":
            per, unit = d / (hi["pixels"] - lo["pixels"]), "B per pixel"
        else:
            per, unit = d / 2**20 / (hi["views"] - lo["views"]), "MB per view"
        out.append({"factor": f, "from": lo[f], "to": hi[f],
                    "fixed": {g: lo[g] for g in _FACTORS if g != f},
                    "workspace_mb": [lo["workspace"] / 2**20, hi["workspace"] / 2**20], "per": per, "unit": unit})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[250_000, 1_000_000])
    ap.add_argument("--widths", type=int, nargs="+", default=[504, 1008])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", type=Path, default=Path("memory.json"))
    a = ap.parse_args()
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.core.fileio import write_json

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
    if device.type == "cuda":
        out["device_name"] = torch.cuda.get_device_name(device)
        print("\n| Gaussians | views | image | peak: render + backward MB | peak: optimizer MB |")
        print("|---:|---:|---|---:|---:|")
        for r in rows:
            print(f"| {r['gaussians']:,} | {r['views']} | {r['width']}x{r['height']} | "
                  f"{r['peak_render_backward'] / mb:.1f} | {r['peak_optimizer'] / mb:.1f} |")
    out["pairs"] = pairs = pairwise(rows)
    if pairs:
        print("\n| changes | from | to | at | workspace MB | difference |")
        print("|---|---:|---:|---|---|---:|")
        for p in pairs:
            at = ", ".join(f"{k} {v:,}" for k, v in p["fixed"].items())
            print(f"| {p['factor']} | {p['from']:,} | {p['to']:,} | {at} | "
                  f"{p['workspace_mb'][0]:.1f} -> {p['workspace_mb'][1]:.1f} | {p['per']:.0f} {p['unit']} |")
    write_json(a.out, out)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
