"""Reconstruction benchmark: ssgwarp's rasterizer against gsplat's in the same 3DGS training loop.

For each image folder (default fern ``images_8`` and ``images_4``) and each backend, trains
``--iters`` steps (default 7,000) with :class:`ssgwarp.reconstruct.Trainer` -- same data, seed,
recipe and loop; only the ``rasterization`` function differs -- and reports held-out PSNR/SSIM
(every 8th view), the final Gaussian count, wall time of the training loop and peak GPU memory.
Prints a markdown table (and writes it with the raw numbers to ``--out``).

    python benchmarks/reconstruct.py                      # both backends, both resolutions
    python benchmarks/reconstruct.py --backend ssgwarp --images images_8 --iters 7000
    python benchmarks/reconstruct.py --backend gsplat     # needs `pip install gsplat` (imported only then)
    python benchmarks/reconstruct.py --dssim-scale 0.5    # the old halved D-SSIM term, against the default 1

Distorted captures (fern is SIMPLE_RADIAL) are undistorted into a pinhole crop (every pixel has a
source, ``ssgwarp.lens``); PSNR/SSIM are measured on that crop (``metric_frame`` in the JSON rows).

Targets (issue 3): PSNR within 0.2 dB of the gsplat run, training time within 1.5x.
"""
from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssgwarp.datasets import load_dataset  # noqa: E402
from ssgwarp.fileio import atomic_path, write_json  # noqa: E402
from ssgwarp.reconstruct import Recipe, Trainer  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "llff_fern"


def rasterizer(backend: str):
    """``(rasterize function or None, extra kwargs)`` for a backend name."""
    if backend == "ssgwarp":
        return None, {}  # the Trainer's default: ssgwarp.rasterization (Warp kernels on CUDA)
    if backend == "gsplat":
        try:
            from gsplat import rasterization
        except ImportError as e:
            raise SystemExit(f"--backend gsplat needs the gsplat package ({e}); pip install gsplat") from None
        return rasterization, {"packed": False}  # [C, N] layout, as the Trainer's densification reads it
    raise SystemExit(f"unknown backend {backend!r}")


def warm_up(trainer: Trainer) -> None:
    """Compile/JIT the rasterizer's kernels (every SH degree, forward and backward) outside the timed loop."""
    from ssgwarp.reconstruct import render_views

    scene = trainer.scene.detach()
    scene = scene.map(lambda t: t.requires_grad_(True))
    cam = trainer.data.cameras[trainer.data.train_ids[0]]
    bg = trainer.data.background_tensor(3)[None]
    for deg in range(trainer.sh_degree + 1):
        out, _, meta = render_views(scene, cam, sh_degree=deg, backgrounds=bg, rasterize=trainer.rasterize,
                                    **trainer.raster_kwargs)
        meta["means2d"].retain_grad()
        out.sum().backward()


def run_one(data_dir: Path, images: str, backend: str, iters: int, sh_degree: int, seed: int,
            max_gaussians: int, device: torch.device, progress: bool, dssim_scale: float = 1.0) -> dict:
    data = load_dataset(data_dir, images=images, device=device)
    fn, kw = rasterizer(backend)
    trainer = Trainer(data, iters=iters, sh_degree=sh_degree, max_gaussians=max_gaussians,
                      recipe=Recipe(dssim_scale=dssim_scale),
                      rasterize=fn, raster_kwargs=kw, device=device, seed=seed, progress=progress)
    warm_up(trainer)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    trainer.train()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - t0
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else float("nan")
    ev = trainer.evaluate()
    out = {"images": images, "backend": backend, "resolution": f"{data.width}x{data.height}",
           "psnr": ev["psnr"], "ssim": ev["ssim"], "gaussians": trainer.num_gaussians, "seconds": seconds,
           "peak_mib": peak, "iters": iters, "test_views": ev["views"], "dssim_scale": dssim_scale,
           **data.metric_frame}
    del trainer, data
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return out


def table(rows: list[dict]) -> str:
    lines = ["| images | resolution | backend | D-SSIM scale | held-out PSNR (dB) | SSIM | Gaussians | train time (s) "
             "| peak GPU mem (MiB) |", "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['images']} | {r['resolution']} | {r['backend']} | {r.get('dssim_scale', 1.0):g} | "
                     f"{r['psnr']:.2f} | {r['ssim']:.4f} | "
                     f"{r['gaussians']:,} | {r['seconds']:.1f} | {r['peak_mib']:.0f} |")
    by = {(r["images"], r["backend"]): r for r in rows}
    cmp = []
    for images in dict.fromkeys(r["images"] for r in rows):
        a, b = by.get((images, "ssgwarp")), by.get((images, "gsplat"))
        if a and b:
            cmp.append(f"| {images} | {a['psnr'] - b['psnr']:+.2f} dB | {a['seconds'] / b['seconds']:.2f}x | "
                       f"{a['peak_mib'] / b['peak_mib']:.2f}x |")
    if cmp:
        lines += ["", "| images | PSNR ssgwarp - gsplat (target >= -0.2 dB) | time ssgwarp / gsplat (target <= 1.5x) "
                      "| memory ssgwarp / gsplat |", "|---|---:|---:|---:|"] + cmp
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="LLFF capture (default ../shared/data/llff_fern)")
    p.add_argument("--images", nargs="+", default=["images_8", "images_4"])
    p.add_argument("--backend", choices=("ssgwarp", "gsplat", "both"), default="both")
    p.add_argument("--iters", type=int, default=7000)
    p.add_argument("--sh-degree", type=int, default=3)
    p.add_argument("--max-gaussians", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dssim-scale", type=float, default=1.0,
                   help="multiplier of the D-SSIM term: 1 (default) is the 3DGS loss, 0.5 the halved term ssgwarp "
                        "used before")
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", type=Path, default=Path("benchmark-reconstruct"), help="folder for results.json / results.md")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    device = torch.device(a.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("CUDA is not available (pass --device cpu for a (slow) CPU run)")
    backends = ["ssgwarp", "gsplat"] if a.backend == "both" else [a.backend]
    rows = []
    for images in a.images:
        for backend in backends:
            torch.manual_seed(a.seed)
            r = run_one(a.data, images, backend, a.iters, a.sh_degree, a.seed, a.max_gaussians, device,
                        not a.no_progress, dssim_scale=a.dssim_scale)
            print(json.dumps(r), flush=True)
            rows.append(r)
    md = table(rows)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    header = f"fern, {a.iters} iterations, SH degree {a.sh_degree}, seed {a.seed}, {gpu}, torch {torch.__version__}"
    print(f"\n{header}\n\n{md}")
    write_json(a.out / "results.json", {"setup": header, "rows": rows})
    with atomic_path(a.out / "results.md") as tmp:
        tmp.write_text(f"{header}\n\n{md}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
