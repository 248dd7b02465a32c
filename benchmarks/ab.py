"""Before / after of the rasterizer in one process: this checkout's ``ssgwarp`` against another tree's,
imported side by side as ``ssgwarp_base``, timed in interleaved rounds.

Timings of host-bound calls swing by up to 30 % between processes and machines (docs/notes/benchmarks-history.md), so
a change worth 5-15 % is measured here: both versions in the same process, on the same GPU, in turns
(each round times one version then the other, the order alternating), and the medians compared.

    python benchmarks/ab.py --base HEAD~1              # the tree of a git revision (git archive)
    python benchmarks/ab.py --base-dir /path/to/tree   # a tree with ssgwarp/ and kernels/ (no git needed)
    python benchmarks/ab.py --base HEAD~1 --device cpu --rounds 4

Per case (16 Gaussians at 16x16, the issue's 10k at 256x256 and 100k at 1920x1080 colour rows): forward
and forward+backward microseconds per call, as blocks of calls with one synchronisation (queued GPU work
overlaps the host, as in training) and as single synchronised calls; the minimum and median over the
rounds, and the median ratio after / before.
"""
from __future__ import annotations

import argparse
import importlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from raster import camera, make_scene, pass_closures  # noqa: E402
from timing import sync, timed  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CASES = {"16": (16, 16, 16), "10k": (10_000, 256, 256), "100k": (100_000, 1920, 1080)}


def base_package(base: str | None, base_dir: str | None, into: Path) -> None:
    """Lay out the other tree's package as ``into/ssgwarp_base`` (its ``kernels/`` and ``viewer/``
    inside, as an install puts them)."""
    if base_dir is not None:
        src = Path(base_dir)
    else:
        src = into / "tree"
        src.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", base, "ssgwarp", "kernels", "viewer"],
                                 check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    if not (src / "ssgwarp").is_dir() or not (src / "kernels").is_dir():
        raise SystemExit(f"ab.py: {src} has no ssgwarp/ and kernels/ (give a tree of this project)")
    dst = into / "ssgwarp_base"
    shutil.copytree(src / "ssgwarp", dst, ignore=shutil.ignore_patterns("__pycache__", "kernels", "viewer"))
    shutil.copytree(src / "kernels", dst / "kernels", ignore=shutil.ignore_patterns("__pycache__"))
    if (src / "viewer").is_dir():
        shutil.copytree(src / "viewer", dst / "viewer", ignore=shutil.ignore_patterns("__pycache__"))


def block_us(fn, device, calls: int) -> float:
    sync(device)
    t0 = time.perf_counter()
    for _ in range(calls):
        fn()
    sync(device)
    return (time.perf_counter() - t0) / calls * 1e6


def run_case(libs: dict, n: int, w: int, h: int, device, rounds: int, calls: int) -> list[dict]:
    params = make_scene(n, device)
    if n <= 64:  # (a close camera so that the few Gaussians cover the small image)
        params[0][:, 2] -= 4.0
    vm, K = camera(w, h, device)
    fns = {name: pass_closures(mod.rasterization, params, vm, K, w, h, tile_size=16) for name, mod in libs.items()}
    for f, fb in fns.values():
        for _ in range(10):
            f()
            fb()
    times: dict = {}
    for r in range(rounds):
        for name in (list(fns) if r % 2 == 0 else list(fns)[::-1]):
            for pname, fn in zip(("forward", "forward+backward"), fns[name]):
                times.setdefault((name, pname, "block"), []).append(block_us(fn, device, calls))
                times.setdefault((name, pname, "synced"), []).append(timed(fn, device, max(5, calls // 4)) * 1e3)
    rows = []
    for pname in ("forward", "forward+backward"):
        for mode in ("block", "synced"):
            a, b = times[("after", pname, mode)], times[("before", pname, mode)]
            rows.append({"n": n, "image": f"{w}x{h}", "pass": pname, "mode": mode, "before_min": min(b),
                         "before_median": statistics.median(b), "after_min": min(a),
                         "after_median": statistics.median(a),
                         "ratio": statistics.median(a) / statistics.median(b)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = ap.add_mutually_exclusive_group(required=True)
    which.add_argument("--base", help="git revision of the 'before' tree (needs this checkout's .git)")
    which.add_argument("--base-dir", help="a tree with ssgwarp/ and kernels/ as the 'before'")
    ap.add_argument("--cases", nargs="+", choices=sorted(CASES), default=["16", "10k", "100k"])
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--calls", type=int, default=150, help="calls per block")
    args = ap.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda":
        from raster import warm_gpu
        warm_gpu()
    with tempfile.TemporaryDirectory() as tmp:
        base_package(args.base, args.base_dir, Path(tmp))
        sys.path.insert(0, tmp)
        libs = {"after": importlib.import_module("ssgwarp"), "before": importlib.import_module("ssgwarp_base")}
        print(f"after: {Path(libs['after'].__file__).parent}; before: {args.base or args.base_dir}; {device}; "
              f"{args.rounds} interleaved rounds")
        print("| N | image | pass | timing | before µs (min / median) | after µs (min / median) | after / before |")
        print("|---|---|---|---|---|---|---|")
        for case in args.cases:
            for r in run_case(libs, *CASES[case], device, args.rounds, args.calls):
                print(f"| {r['n']:,} | {r['image']} | {r['pass']} | {r['mode']} | {r['before_min']:.0f} / "
                      f"{r['before_median']:.0f} | {r['after_min']:.0f} / {r['after_median']:.0f} | {r['ratio']:.3f} |",
                      flush=True)


if __name__ == "__main__":
    main()
