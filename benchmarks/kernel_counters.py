"""Hardware counters of the rasterizer's CUDA kernels (Nsight Compute), ssgwarp next to gsplat.

Kernel time alone says which kernel is slow; the counters say why: how many warp instructions it
executes, how busy the issue slots are (compute-bound near 80-90 %), its registers and achieved
occupancy. That is how the blending loops' per-Gaussian overhead was found (docs/notes/benchmarks-history.md,
"Blending loops without per-Gaussian overhead": 1.06 G instructions against gsplat's 0.83 G at 1M
Gaussians, issue-bound both).

    python benchmarks/kernel_counters.py                          # 1M @ 1920x1080, colours
    python benchmarks/kernel_counters.py --case 200000x504x378 --sh 3 --no-gsplat

Runs ``ncu`` (Nsight Compute; ``--ncu PATH``, else from PATH or /usr/local/cuda/bin) on a child
process that renders one forward without gradients and one forward+backward between
``cudaProfilerStart`` / ``cudaProfilerStop``, and prints one row per kernel launch of more than
``--min-us`` microseconds. Nsight Compute locks the clocks to their base values and replays each
kernel, so its durations are longer than a timed run's: compare them with each other, not with
``raster.py``.
"""
from __future__ import annotations

import argparse
import csv
import io
import os
import shutil
import subprocess
import sys
from pathlib import Path

METRICS = {
    "gpu__time_duration.sum": "duration",
    "smsp__inst_executed.sum": "warp instructions",
    "sm__inst_issued.avg.pct_of_peak_sustained_active": "issue slots busy %",
    "launch__registers_per_thread": "registers",
    "sm__warps_active.avg.pct_of_peak_sustained_active": "achieved occupancy %",
}


def child(lib: str, n: int, w: int, h: int, sh: int | None) -> None:
    """Render one forward (no gradients) and one forward+backward inside the profiled range."""
    import torch

    sys.path.insert(0, str(Path(__file__).parent))
    from raster import closures

    if lib == "gsplat":
        import gsplat

        raster = gsplat.rasterization
    else:
        import ssgwarp

        raster = ssgwarp.rasterization
    fwd, fwd_bwd = closures(raster, n, w, h, torch.device("cuda"), sh_degree=sh, packed=False)
    for _ in range(2):  # (compiled, loaded and warm before the profiled range)
        fwd()
        fwd_bwd()
    torch.cuda.synchronize()
    torch.cuda.cudart().cudaProfilerStart()
    fwd()
    fwd_bwd()
    torch.cuda.synchronize()
    torch.cuda.cudart().cudaProfilerStop()


def parse(text: str) -> list[dict]:
    """Rows of ``ncu --csv`` output (one per kernel launch and metric) folded into one dict per
    launch: ``{"id", "kernel", <metric name>: value, ...}`` in launch order."""
    start = text.find('"ID"')
    if start < 0:
        return []
    launches: dict = {}
    for row in csv.DictReader(io.StringIO(text[start:])):
        key = row.get("ID")
        if key is None or row.get("Metric Name") not in METRICS:
            continue
        entry = launches.setdefault(key, {"id": int(key), "kernel": row["Kernel Name"]})
        value = row["Metric Value"].replace(",", "")
        try:
            value = float(value)
        except ValueError:
            continue
        unit = row.get("Metric Unit", "").strip().lower()
        if row["Metric Name"] == "gpu__time_duration.sum":  # to microseconds (ns, nsecond, usecond, ms, ...)
            value *= {"n": 1e-3, "u": 1.0, "µ": 1.0, "m": 1e3, "s": 1e6}.get(unit[:1], 1e-3)
        entry[row["Metric Name"]] = value
    return sorted(launches.values(), key=lambda e: e["id"])


def short(name: str) -> str:
    """A kernel's name without template arguments, argument lists, namespaces or (Warp's) factory
    prefix, module hash and suffix."""
    name = name.split("(")[0].split("<")[0].replace("void ", "").strip()
    if "__locals__" in name:  # Warp: <factory>__locals__<kernel>_<hash>_cuda_kernel_forward
        name = name.split("__locals__")[1].rsplit("_cuda_kernel_", 1)[0].rsplit("_", 1)[0]
    return name.split("::")[-1]


def find_ncu(given: str | None) -> str:
    for cand in (given, shutil.which("ncu"), "/usr/local/cuda/bin/ncu"):
        if cand and Path(cand).exists():
            return cand
    raise SystemExit("kernel_counters.py needs Nsight Compute's ncu: pass --ncu PATH (it ships with the CUDA toolkit)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="1000000x1920x1080", help="Gaussians x width x height")
    ap.add_argument("--sh", type=int, default=None, help="SH degree (default: colours)")
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--min-us", type=float, default=20.0, help="leave out launches shorter than this")
    ap.add_argument("--ncu", default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    try:
        n, w, h = (int(v) for v in args.case.lower().split("x"))
    except ValueError:
        raise SystemExit(f"--case must be NxWxH (e.g. 1000000x1920x1080), got {args.case!r}") from None
    if args.child:
        child(args.child, n, w, h, args.sh)
        return
    ncu = find_ncu(args.ncu)
    libs = ["ssgwarp"] + ([] if args.no_gsplat else ["gsplat"])
    print(f"{n:,} Gaussians at {w}x{h}, {'SH ' + str(args.sh) if args.sh is not None else 'colours'}; "
          "one forward (no grad), then one forward+backward; Nsight Compute clocks (base)\n")
    print("| library | kernel | µs | warp instructions (M) | issue slots busy % | registers | achieved occupancy % |")
    print("|---|---|---|---|---|---|---|")
    for lib in libs:
        cmd = [ncu, "--profile-from-start", "off", "--csv", "--metrics", ",".join(METRICS),
               sys.executable, str(Path(__file__).resolve()), "--case", args.case, "--child", lib]
        if args.sh is not None:
            cmd += ["--sh", str(args.sh)]
        out = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        rows = parse(out.stdout)
        if out.returncode != 0 or not rows:
            tail = (out.stderr or out.stdout).strip().splitlines()[-5:]
            print(f"| {lib} | (ncu failed, exit {out.returncode}: {' / '.join(tail)}) | | | | | |")
            continue
        for r in rows:
            us = r.get("gpu__time_duration.sum", 0.0)
            if us < args.min_us:
                continue
            print(f"| {lib} | {short(r['kernel'])} | {us:.0f} | {r.get('smsp__inst_executed.sum', 0) / 1e6:.1f} | "
                  f"{r.get('sm__inst_issued.avg.pct_of_peak_sustained_active', 0):.1f} | "
                  f"{r.get('launch__registers_per_thread', 0):.0f} | "
                  f"{r.get('sm__warps_active.avg.pct_of_peak_sustained_active', 0):.1f} |")


if __name__ == "__main__":
    main()
