"""Numerical extremes: the error of the Warp rasterizer against the float64 torch reference.

For each extreme case the tests cover (tests/test_rasterizer_extremes.py), render with
default and exact settings and report the max image error and the max gradient error, each
relative to the reference's largest magnitude, of (a) Warp float64 and (b) Warp float32, both against the float64
reference. Prints a markdown table (docs/numerics.md holds a run of it).

    python benchmarks/numerics.py
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from harness import header, table  # noqa: E402
from ssgwarp import RasterSettings, rasterization  # noqa: E402
from test_rasterizer_extremes import _extreme_case, _front_camera  # noqa: E402

CASES = {
    "behind_and_near": "10 behind the camera, 5 exactly at the near plane, 5 in the camera plane",
    "far": "20 at depth 1e6",
    "tiny_huge_scales": "scales 1e-8 and 1e4",
    "anisotropy": "anisotropy 1e6 (scales 1e-3 x 1e3)",
    "opacity_extremes": "opacity 1e-6 and 1 - 1e-7",
    "offscreen": "everything off-screen",
    "stack5000": "5,000 Gaussians stacked on one pixel",
}


def stacked():
    n = 5000
    g = torch.Generator().manual_seed(5)
    means = torch.zeros(n, 3, dtype=torch.float64)
    means[:, 2] = torch.linspace(2.0, 6.0, n, dtype=torch.float64)
    return (means, torch.randn(n, 4, generator=g, dtype=torch.float64), torch.full((n, 3), 0.002, dtype=torch.float64),
            torch.full((n,), 0.01, dtype=torch.float64), torch.rand(n, 3, generator=g, dtype=torch.float64))


def render(params, vm, K, w, h, backend, dtype, settings):
    leaves = [p.to(dtype).clone().requires_grad_(True) for p in params]
    img, alpha, _ = rasterization(*leaves, vm.to(dtype), K.to(dtype), w, h, backend=backend, settings=settings,
                                  render_mode="RGB+ED")
    g = torch.Generator().manual_seed(1)
    wi = torch.randn(img.shape, generator=g, dtype=torch.float64).to(dtype)
    if img.requires_grad:  # everything culled: no path to the inputs
        (img * wi).sum().backward()
    grads = [torch.zeros_like(p) if p.grad is None else p.grad for p in leaves]
    return img.detach().double(), [gr.double() for gr in grads]


def rel(a, b, floor=1e-12):
    scale = max(float(a.abs().max()) if a.numel() else 0.0, floor)
    return float((a - b).abs().max()) / scale if a.numel() else 0.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES), help="default: all")
    args = ap.parse_args(argv)
    rows = []
    for case, text in ((c, CASES[c]) for c in args.cases):
        if case == "stack5000":
            params, (vm, K), (w, h) = stacked(), _front_camera(8, 8, f=8.0), (8, 8)
        else:
            params, (vm, K), (w, h) = _extreme_case(case), _front_camera(40, 30), (40, 30)
        variants = [("default", RasterSettings()), ("exact", RasterSettings.exact())]
        if case == "anisotropy":  # the covariance form is what matters here
            variants.insert(1, ("default, covariance='factor'", RasterSettings(covariance="factor")))
        for name, st in variants:
            ref_img, ref_g = render(params, vm, K, w, h, "torch", torch.float64, st)
            row = {"case": text, "settings": name}
            for tag, dt in (("f64", torch.float64), ("f32", torch.float32)):
                img, gr = render(params, vm, K, w, h, "warp", dt, st)
                finite = bool(torch.isfinite(img).all()) and all(bool(torch.isfinite(x).all()) for x in gr)
                ierr = rel(ref_img, img)
                # a gradient that is zero in exact arithmetic (e.g. rotations of isotropic Gaussians)
                # is measured against 1e-3 of the problem's largest gradient, not its own noise
                top = max([float(x.abs().max()) for x in ref_g if x.numel()] + [1e-9])
                gerr = max(rel(a, b, 1e-3 * top) for a, b in zip(ref_g, gr))
                row.update({f"{tag} image rel err": f"{ierr:.1e}", f"{tag} grad rel err": f"{gerr:.1e}",
                            f"{tag} finite": "yes" if finite else "NO"})
            rows.append(row)
            print(row, flush=True)
    print(f"\n{header('cpu')}\n\n{table(rows, [(k, k) for k in rows[0]])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
