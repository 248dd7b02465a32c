"""Host-side cost of one ``rasterization`` call, split by kind of work (profiler), on CPU and CUDA.

A tiny scene (16 Gaussians, 16x16 pixels by default) makes the kernels' own time negligible, so what
is left is the per-call cost every render pays on the host: Python, input checks, Warp launch
arguments, launches, torch allocations and small ops, autograd, and the read-back of the
intersection count (on CUDA that read-back also waits for the GPU).

    python benchmarks/host_cost.py                       # CPU, and CUDA when present
    python benchmarks/host_cost.py --device cpu --calls 2000
    python benchmarks/host_cost.py --gsplat              # CUDA: gsplat's per-call wall time beside it
    python benchmarks/host_cost.py --out host.json --markdown host.md

Per device and pass (forward under ``torch.no_grad()``; forward+backward of ``img.sum() +
alpha.sum()``): the time per call (the fastest of several blocks of calls; CUDA synchronised after
each block only, so queued GPU work overlaps the host as in a training loop; plus the median of
calls synchronised one by one; on CUDA wall time, on the CPU the thread's CPU time, which leaves
out the load of other processes on a shared machine), and the split of a cProfile run into the
categories below, scaled to the wall time (the profiler slows Python down roughly uniformly; its
shares are what it measures).
"""
from __future__ import annotations

import argparse
import cProfile
import datetime
import json
import math
import pstats
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from raster import camera, make_scene, pass_closures  # noqa: E402
from timing import per_call_us  # noqa: E402

import ssgwarp  # noqa: E402

# (category, predicate on (file, function name)); first match wins
CATEGORIES = [
    ("readback (tolist/item; waits for the GPU)", lambda f, n: n in ("tolist", "item", "cpu", "_local_scalar_dense",
                                                                   "read_int64", "wp_memcpy_d2h",
                                                                   "wp_cuda_stream_synchronize")),
    ("input checks", lambda f, n: ("rasterize.py" in f and n in ("validate_inputs", "check"))
     or n in ("check_values", "__post_init__", "for_dtype")),
    ("launch arguments (array views)", lambda f, n: n in ("_wp", "from_torch", "arr", "arr2", "_arr", "array_t",
                                                          "_init_from_ptr", "data_ptr", "stride", "element_size")
     or ("warp" in f and "types.py" in f and n == "__init__")),
    ("kernel launches", lambda f, n: ("warp" in f and ("context.py" in f or "utils.py" in f))
     or "launch.py" in f or n in ("launch", "radix_sort_pairs", "sort_pairs")),
    ("allocations", lambda f, n: n in ("empty", "zeros", "zeros_like", "empty_like", "ones_like", "new_zeros",
                                       "new_empty", "full", "ones")),
    ("autograd", lambda f, n: "autograd" in f or n in ("apply", "run_backward", "save_for_backward",
                                                       "mark_non_differentiable", "backward", "_make_grads")),
    ("torch ops", lambda f, n: f == "~" or "torch" in f),
    ("ssgwarp Python", lambda f, n: "ssgwarp" in f or "kernels" in f),
]
OTHER = "other (benchmark loop)"


def categorise(stats: pstats.Stats) -> dict:
    out: dict = {}
    for (fname, _line, func), (_cc, _nc, tt, _ct, _callers) in stats.stats.items():
        name = func.split(" of ")[0].replace("<method '", "").replace("<built-in method ", "").strip("'>")
        name = name.rsplit(".", 1)[-1]  # torch.empty -> empty
        cat = next((c for c, pred in CATEGORIES if pred(fname, name)), OTHER)
        out[cat] = out.get(cat, 0.0) + tt
    return out


def scene(n: int, res: int, device: torch.device):
    params = make_scene(n, device)
    # a close camera so the Gaussians cover the small image
    params[0][:, 2] -= 4.0
    vm, K = camera(res, res, device)
    return params, vm, K


def clock(device):
    """CUDA: wall time (the host also waits for the GPU). CPU: this thread's CPU time, which
    leaves out the time other processes on a shared machine take (Warp's CPU kernels and torch,
    with one thread, run in this thread)."""
    return time.perf_counter if device.type == "cuda" else time.thread_time


def measure(fn, device, calls: int, blocks: int) -> tuple[float, float]:
    """(per-call microseconds with one synchronisation per block: the fastest block; median
    per-call microseconds with one synchronisation per call)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    now = clock(device)
    fastest = per_call_us(fn, device, calls, blocks, now)
    synced = []
    for _ in range(min(calls, 200)):
        t0 = now()
        fn()
        sync()
        synced.append((now() - t0) * 1e6)
    return fastest, statistics.median(synced)


def profiled(fn, device, calls: int) -> pstats.Stats:
    """cProfile's statistics of ``calls`` calls of ``fn`` (on the device's clock)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    pr = cProfile.Profile(clock(device))
    sync()
    pr.enable()
    for _ in range(calls):
        fn()
    sync()
    pr.disable()
    return pstats.Stats(pr)


def profile(fn, device, calls: int) -> dict:
    cats = categorise(profiled(fn, device, calls))
    total = sum(cats.values())
    return {k: v / total for k, v in cats.items()}


def top_functions(fn, device, calls: int, k: int) -> list[tuple[str, float, float]]:
    """``(function, own microseconds per call, calls per call)`` of the ``k`` functions with the most
    own time under cProfile (whose times are inflated, roughly uniformly)."""
    rows = [(f"{Path(fname).name}:{func}", tt / calls * 1e6, nc / calls)
            for (fname, _line, func), (_cc, nc, tt, _ct, _callers) in profiled(fn, device, calls).stats.items()]
    return sorted(rows, key=lambda r: -r[1])[:k]


def run_device(device: torch.device, args, raster, label: str) -> list[dict]:
    params, vm, K = scene(args.gaussians, args.res, device)
    # gsplat's layout and tile size on both devices, so every library and version does the same work
    kw = {"tile_size": 16} if label != "gsplat" else {"packed": False, "tile_size": 16}
    fwd, fwd_bwd = pass_closures(raster, params, vm, K, args.res, args.res, **kw)
    rows = []
    for name, fn in (("forward", fwd), ("forward+backward", fwd_bwd)):
        per_call, synced = measure(fn, device, args.calls, args.blocks)
        shares = profile(fn, device, max(50, args.calls // 4)) if label != "gsplat" else {}
        row = {"device": device.type, "library": label, "pass": name, "us_per_call": per_call,
               "us_per_call_synced": synced, "split_us": {k: v * per_call for k, v in shares.items()}}
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.top:
            print(f"  {label} {name}, own time under cProfile (us per call, calls per call):")
            for fname, us, nc in top_functions(fn, device, max(200, args.calls), args.top):
                print(f"    {us:8.1f}  {nc:5.1f}  {fname}")
    return rows


def launch_paths(device: torch.device, launches: int) -> list[dict]:
    """Host microseconds per launch of the projection kernel (its 33 parameters, 16 Gaussians) by three
    routes: ``wp.launch`` with array descriptors (how ssgwarp launched before), Warp's recorded
    launch (``wp.launch(..., record_cmd=True)``; every parameter set again with
    ``Launch.set_param_at_index_from_ctype``, then ``Launch.launch()``), and ssgwarp's replay of the
    recorded launch (``ssgwarp.raster.launch``: the parameter block refilled by one ``struct.pack_into``)."""
    import warp as wp

    from ssgwarp import RasterSettings
    from ssgwarp.raster import launch as L, ops
    from ssgwarp.kernels import projection

    params, vm, K = scene(16, 16, device)
    C, N = 1, params[0].shape[0]
    cfg = ops._project_cfg(torch.float32, 16, 16, 0.01, 1e10, 0.0, 0.3, False, RasterSettings(), 16, 1, 1)
    outs = [torch.empty(C, N, k, device=device) for k in (2, 1, 3, 1)] + \
        [torch.empty(C, N, 2, dtype=torch.int32, device=device), torch.empty(C, N, dtype=torch.int32, device=device),
         torch.empty(C, N, dtype=torch.int64, device=device), torch.empty(C, N, 6, device=device)]
    ins = list(params[:4]) + [vm, K]

    def flat():  # the projection kernel's parameters (no input checks)
        return ops._project_args(ins, C, N) + list(cfg["params"]) + ops._NO_CHECKS + [
            *L.arr(outs[0], 2), *L.arr(outs[1]), *L.arr(outs[2], 3), *L.arr(outs[3]), *L.arr(outs[4], 2),
            *L.arr(outs[5]), *L.arr(outs[6]), *L.arr(outs[7], 6), 0]

    from ssgwarp.raster import private_api as P

    kern = projection.projection_kernel(wp.float32, *cfg["variant"])
    tg = L.target(params[0])
    stream = L._stream(tg)

    def warp_args():  # (the flat list as Warp's own arguments, the way ssgwarp's fall-back builds them)
        return P.warp_args(kern, flat(), tg.device)

    def via_wp_launch():
        wp.launch(kern, dim=(C, N), inputs=warp_args(), device=tg.device, stream=stream, record_tape=False)

    rec = wp.launch(kern, dim=(C, N), inputs=warp_args(), device=tg.device, record_tape=False, record_cmd=True)

    def via_record_cmd():
        for i, v in enumerate(warp_args()):
            if wp.types.is_struct(v):  # (a parameter block: Warp packs it)
                rec.set_param_at_index(i, v)
            else:
                rec.set_param_at_index_from_ctype(i, v)
        rec.launch(stream)

    def via_ssgwarp():
        L.launch(kern, (C, N), flat(), tg)

    rows = []
    for name, fn in (("wp.launch, array descriptors (before)", via_wp_launch),
                     ("Warp recorded launch, parameters set again, Launch.launch()", via_record_cmd),
                     ("ssgwarp.raster.launch: recorded launch replayed from one packed buffer", via_ssgwarp)):
        per_call, _ = measure(fn, device, launches, 3)
        rows.append({"device": device.type, "route": name, "us_per_launch": per_call,
                     "parameters": len(kern.adj.args)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def table(rows: list[dict]) -> str:
    cats = [c for c, _ in CATEGORIES] + [OTHER]
    cats = [c for c in cats if any(c in r["split_us"] for r in rows)]
    head = ["device", "library", "pass", "µs per call", "µs per call (synced)"] + cats
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["device"], r["library"], r["pass"], f"{r['us_per_call']:.0f}", f"{r['us_per_call_synced']:.0f}"]
        cells += [f"{r['split_us'][c]:.0f}" if c in r["split_us"] else "-" for c in cats]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["all", "cpu", "cuda"], default="all")
    ap.add_argument("--gaussians", type=int, default=16)
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--calls", type=int, default=500, help="calls per timed block")
    ap.add_argument("--blocks", type=int, default=5)
    ap.add_argument("--gsplat", action="store_true", help="also time gsplat.rasterization (CUDA)")
    ap.add_argument("--launch-paths", action="store_true",
                    help="also time one kernel launch by wp.launch, Warp's recorded launch and ssgwarp.raster.launch")
    ap.add_argument("--top", type=int, default=0, help="also list the K functions with the most own time, per library")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: host cost, not parallelism)")
    ap.add_argument("--out", default=None, help="raw rows as JSON")
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    devices = []
    if args.device in ("all", "cpu"):
        devices.append(torch.device("cpu"))
    if args.device in ("all", "cuda") and torch.cuda.is_available():
        devices.append(torch.device("cuda"))
    rows, routes = [], []
    for dev in devices:
        rows += run_device(dev, args, ssgwarp.rasterization, "ssgwarp")
        if args.launch_paths:
            routes += launch_paths(dev, args.calls)
        if args.gsplat and dev.type == "cuda":
            import gsplat

            rows += run_device(dev, args, gsplat.rasterization, "gsplat")
    meta = (f"{datetime.date.today().isoformat()}; torch {torch.__version__}; "
            f"{torch.cuda.get_device_name() if torch.cuda.is_available() else 'no GPU'}; "
            f"{args.gaussians} Gaussians, {args.res}x{args.res}; torch threads {args.threads}")
    text = meta + "\n\n" + table(rows)
    if routes:
        text += (f"\n\n| device | launch route (projection kernel, {routes[0]['parameters']} parameters) | µs per launch |"
                 "\n|---|---|---|\n")
        text += "\n".join(f"| {r['device']} | {r['route']} | {r['us_per_launch']:.1f} |" for r in routes)
    print(text)
    if args.markdown:
        Path(args.markdown).write_text(text + "\n")
    if args.out:
        Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows, "launch_routes": routes}, indent=1))
    if not math.isfinite(sum(r["us_per_call"] for r in rows)):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
