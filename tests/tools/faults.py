"""Inject the faults of issue 20 one at a time and check that the suite fails on each (a manual check, not CI).

    python tests/tools/faults.py                 # every fault
    python tests/tools/faults.py eps2d dssim     # some of them
    python tests/tools/faults.py --list

Each fault is a textual change to one file of the repository (:data:`FAULTS`: the file, the text
replaced, its replacement, the tests that should catch it). It is applied in a copy of the repository,
``.mutation/faults/`` (git-ignored; ``kernels/`` also copied to ``ssgwarp/kernels/`` so that the copy
imports its own kernels, not the installed ones), the tests run there with ``-x`` and the copy is
restored. A fault is *caught* when pytest exits with failures (exit code 1) and the first failing test
is printed. The change must apply exactly once, so a fault whose text no longer exists is reported as
*stale* (the code moved: update :data:`FAULTS`) rather than silently passing.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
WHERE = ROOT / ".mutation" / "faults"

# name -> (description, file, old text, new text, tests run)
FAULTS = {
    "eps2d": ("default eps2d 0.3 -> 0.2", "ssgwarp/raster/rasterize.py",
              "eps2d: float = 0.3,", "eps2d: float = 0.2,",
              ["tests/test_rasterizer_analytic.py"]),
    "pixel-centre-warp": ("pixel centres at +0 instead of +0.5 (Warp forward kernel)", "kernels/blend_forward.py",
                          "px = scalar(x) + scalar(0.5)\n        py = scalar(y) + scalar(0.5)",
                          "px = scalar(x) + scalar(0.0)\n        py = scalar(y) + scalar(0.0)",
                          ["tests/test_rasterizer_analytic.py", "tests/test_rasterizer.py"]),
    "pixel-centre-warp-backward": ("pixel centres at +0 instead of +0.5 (Warp backward kernel only)",
                                   "kernels/blend_backward.py",
                                   "px = scalar(x) + scalar(0.5)\n        py = scalar(y) + scalar(0.5)",
                                   "px = scalar(x) + scalar(0.0)\n        py = scalar(y) + scalar(0.0)",
                                   ["tests/test_rasterizer.py", "tests/test_rasterizer_gradcheck.py"]),
    "pixel-centre-reference": ("pixel centres at +0 instead of +0.5 (torch reference)", "ssgwarp/raster/reference.py",
                               "dx = m2[None, :, 0] - (px.to(dt)[:, None] + 0.5)\n"
                               "            dy = m2[None, :, 1] - (py.to(dt)[:, None] + 0.5)",
                               "dx = m2[None, :, 0] - (px.to(dt)[:, None] + 0.0)\n"
                               "            dy = m2[None, :, 1] - (py.to(dt)[:, None] + 0.0)",
                               ["tests/test_rasterizer_analytic.py", "tests/test_rasterizer.py"]),
    "dssim-weight": ("D-SSIM term halved in losses.photometric", "ssgwarp/services/losses.py",
                     "w_dssim = 1.0 - lambda_dssim, lambda_dssim * dssim_scale",
                     "w_dssim = 1.0 - lambda_dssim, 0.5 * lambda_dssim * dssim_scale",
                     ["tests/test_losses.py", "tests/test_reconstruct.py"]),
    "dssim-halved": ("dssim() returns (1 - SSIM) / 2", "ssgwarp/services/losses.py",
                     "return 1.0 - ssim(a, b, fused=fused)", "return (1.0 - ssim(a, b, fused=fused)) / 2",
                     ["tests/test_losses.py", "tests/test_reconstruct.py"]),
    "fallback-fixed-key": ("group absent from the key views: no global search (every feature matches key 0)",
                           "ssgwarp/stylization/matching.py",
                           "out[sel] = nearest_neighbors(queries[sel], keys, self.chunk)[0]", "out[sel] = 0",
                           ["tests/test_stylize.py"]),
    "fallback-other-group": ("group absent from the key views: matched against the lowest group present",
                             "ssgwarp/stylization/matching.py",
                             "return self.groups.get(int(group)) if self.labels is not None else None",
                             "return self.groups.get(int(group), self.groups[min(self.groups)]) "
                             "if self.labels is not None else None",
                             ["tests/test_stylize.py"]),
    "cvsa-processor": ("CVSA processor: the whole batch (both CFG halves) shares attention", "ssgwarp/stylization/cvsa.py",
                       "K = self.num_views\n", "K = B\n", ["tests/test_cvsa.py"]),
    "cvsa-denoise": ("denoising loop: CVSA groups of 2K views (the two CFG halves together)", "ssgwarp/stylization/diffusion.py",
                     "with cvsa_enabled(models.unet, K, ", "with cvsa_enabled(models.unet, K * len(halves), ",
                     ["tests/test_cvsa.py"]),
    "undistort-zero-border": ("undistortion keeps pixels without a source, zero-filled (no pinhole crop)",
                              "ssgwarp/capture/lens.py",
                              "return (su >= 0.5) & (su <= W0 - 0.5) & (sv >= 0.5) & (sv <= H0 - 0.5)",
                              "return np.isfinite(su) & np.isfinite(sv)",
                              ["tests/test_lens.py"]),
    "undistort-zero-padding": ("grid_sample padding zeros instead of border (equivalent while the crop holds)",
                               "ssgwarp/capture/lens.py", 'padding_mode="border"', 'padding_mode="zeros"',
                               ["tests/test_lens.py"]),
}
# faults that no input can tell from the original: listed to show why, never counted as missed
EQUIVALENT = {"undistort-zero-padding": "the crop keeps every sample among the source's pixel centres, where "
                                        "bilinear sampling never reads the padding"}


def _copy() -> None:
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        src = ROOT / rel
        if not src.is_file():
            continue
        for dst in [WHERE / rel] + ([WHERE / "ssgwarp" / rel] if rel.startswith("kernels/") else []):
            if not dst.is_file() or dst.read_bytes() != src.read_bytes():
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dst)


def run(name: str) -> str:
    desc, rel, old, new, tests = FAULTS[name]
    targets = [WHERE / rel] + ([WHERE / "ssgwarp" / rel] if rel.startswith("kernels/") else [])
    text = targets[0].read_text()
    if text.count(old) != 1:
        return f"stale ({old!r} found {text.count(old)} times in {rel})"
    try:
        for t in targets:
            t.write_text(text.replace(old, new))
        env = dict(os.environ, PYTHONPATH=str(WHERE))
        r = subprocess.run(["nice", "-n", "15", sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                            *tests], cwd=WHERE, env=env, capture_output=True, text=True)
    finally:
        for t in targets:
            t.write_text(text)
    failed = re.findall(r"^FAILED (\S+)", r.stdout, re.M)
    if r.returncode == 1:
        return f"caught by {failed[0] if failed else '(see pytest output)'}"
    if r.returncode == 0:
        return f"not caught: equivalent ({EQUIVALENT[name]})" if name in EQUIVALENT else "MISSED (every test passed)"
    return f"error (pytest exit {r.returncode}):\n{r.stdout[-2000:]}{r.stderr[-2000:]}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("faults", nargs="*", help=f"among {', '.join(FAULTS)} (default: all)")
    ap.add_argument("--list", action="store_true", help="list the faults")
    args = ap.parse_args(argv)
    if args.list:
        for k, (desc, rel, *_rest) in FAULTS.items():
            print(f"{k:24s} {rel:24s} {desc}")
        return 0
    unknown = [f for f in args.faults if f not in FAULTS]
    if unknown:
        ap.error(f"unknown fault(s) {unknown}: choose among {', '.join(FAULTS)}")
    _copy()
    check = subprocess.run([sys.executable, "-c", "import ssgwarp, ssgwarp.kernels as k; print(ssgwarp.__file__, "
                            "k.__file__)"], cwd=WHERE, env=dict(os.environ, PYTHONPATH=str(WHERE)),
                           capture_output=True, text=True, check=True).stdout.split()
    if not all(Path(p).resolve().is_relative_to(WHERE.resolve()) for p in check):
        print(f"the copy does not import its own package: {check}", file=sys.stderr)
        return 2
    missed = 0
    print("| fault | file | result |\n|---|---|---|", flush=True)
    for name in args.faults or list(FAULTS):
        res = run(name)
        missed += not res.startswith(("caught", "not caught: equivalent"))
        print(f"| {name}: {FAULTS[name][0]} | `{FAULTS[name][1]}` | {res} |", flush=True)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
