"""Cost of one step of our training loop with each rasterizer: milliseconds per step, the device
synchronisations a step makes (and where), and the host ops that cost the most.

One :class:`ssgwarp.reconstruction.reconstruct.Trainer` per backend on the same capture, seed and recipe
(the loop of ``benchmarks/reconstruct.py``): ``--warm`` steps first (past the first refinements, so the
Gaussian count is a trained scene's), then ``--steps`` timed steps between two refinements. On CUDA the
synchronisations come from torch's sync debug mode (each synchronising call and the ssgwarp / kornia /
gsplat / torch.optim frames that made it); ``--profile`` adds torch.profiler's top host ops.

``--ops`` adds the step's op table: every torch op a step calls from Python (top-level ``aten::`` ops,
forward and backward) and every Warp launch (``warp::<kernel>``), one row per op and source line
(the innermost ssgwarp line; a backward op names the autograd node and the line of its forward op),
with calls per step, host microseconds per step (under the profiler, so inflated alike for all rows),
and the launches queued on the GPU (CUDA: kernels, memsets and copies through the CUDA runtime or
driver; CPU: the Warp launches).

    python benchmarks/train_step.py                              # fern images_8, ssgwarp and gsplat
    python benchmarks/train_step.py --scene fern4 --backend ssgwarp --profile
    OMP_NUM_THREADS=2 python benchmarks/train_step.py --device cpu --backend ssgwarp --warm 20 --steps 5 --ops
    python benchmarks/train_step.py --scene PATH:images --warm 100 --steps 20 --device cpu
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import sys
import threading
import time
import traceback
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from reconstruct import load_scene, rasterizer, warm_up  # noqa: E402
from shared_data import data_root  # noqa: E402

from ssgwarp.reconstruction.trainer import Trainer  # noqa: E402

FRAMES = ("ssgwarp", "kornia", "gsplat", "torch/optim")  # the frames a synchronisation is attributed to
ROOT = Path(__file__).resolve().parents[1]
OPS_STEPS = 5  # steps the op table averages over
# CUDA runtime / driver calls that queue work on the GPU
LAUNCH_CALLS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx", "cudaMemsetAsync",
                "cudaMemcpyAsync", "cuMemsetD8Async", "cuMemcpyDtoHAsync_v2", "cuMemcpyAsync")


def sync_sites(step, steps: int = 3) -> collections.Counter:
    """``{(message, 'file:line:function <- ...'): count}`` of the synchronising CUDA calls ``steps``
    calls of ``step()`` make (torch's sync debug mode, as warnings)."""
    sites: collections.Counter = collections.Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack()[:-2] if any(k in f.filename for k in FRAMES)]
        where = " <- ".join(f"{Path(f.filename).name}:{f.lineno}:{f.name}" for f in frames[-3:])
        sites[(str(message).split("(")[0].strip()[:50], where)] += 1

    with warnings.catch_warnings():  # (restores the filters and showwarning)
        warnings.simplefilter("always")
        warnings.showwarning = record
        torch.cuda.set_sync_debug_mode(1)
        try:
            for _ in range(steps):
                step()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    return sites


SKIP = ("benchmarks/", "ssgwarp/raster/launch.py", "ssgwarp/raster/cpu_threads.py")  # helpers, not call sites
_SITES: dict = {}  # code object, line -> its label (or None: not this repository's)


def call_site() -> str:
    """``path:line function`` of the innermost frame in this repository (outside :data:`SKIP`) that is
    running, or ''."""
    f = sys._getframe(2)
    while f is not None:
        key = (f.f_code, f.f_lineno)
        site = _SITES.get(key, 0)
        if site == 0:
            site = None
            try:
                rel = Path(f.f_code.co_filename).resolve().relative_to(ROOT).as_posix()
            except ValueError:
                rel = None
            if rel is not None and not rel.startswith(SKIP):
                site = f"{rel}:{f.f_lineno} {f.f_code.co_name}"
            _SITES[key] = site
        if site:
            return site
        f = f.f_back
    return ""


@contextlib.contextmanager
def ops_attributed():
    """While inside, every torch call from Python runs in a profiler range ``@path:line function``
    (:func:`call_site`), and every Warp launch of :mod:`ssgwarp.raster.launch` (kernels, sorts, cleared
    buffers) is a range ``warp::<kernel>`` inside one too; the extra launches of the CPU blending's
    worker threads are left out (one row per launch the step asks for)."""
    from torch.overrides import TorchFunctionMode
    from torch.profiler import record_function

    from ssgwarp.raster import blend_ops, ops
    from ssgwarp.raster import launch as L

    class Sited(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            with record_function("@" + call_site()):
                return func(*args, **(kwargs or {}))

    def wrap(fn, name_of):
        def recorded(*a, **kw):
            if threading.current_thread().name.startswith("ssgwarp-blend"):
                return fn(*a, **kw)
            with record_function("@" + call_site()), record_function(f"warp::{name_of(*a)}"):
                return fn(*a, **kw)
        return recorded

    def sited(fn):  # (autograd Functions applied through ssgwarp.raster.launch.apply)
        def recorded(*a, **kw):
            with record_function("@" + call_site()):
                return fn(*a, **kw)
        return recorded

    saved = {n: getattr(L, n) for n in ("launch", "sort_pairs", "zeros")}
    applied, apply = (L, ops, blend_ops), L.apply  # (the modules that call ``apply`` by its own name)
    for m in applied:
        m.apply = sited(apply)
    L.launch = wrap(saved["launch"], lambda kernel, *_: getattr(kernel, "key", str(kernel)))
    L.sort_pairs = wrap(saved["sort_pairs"], lambda *_: "radix_sort_pairs")
    L.zeros = wrap(saved["zeros"], lambda *_: "zeros")
    try:
        with Sited():
            yield
    finally:
        for n, fn in saved.items():
            setattr(L, n, fn)
        for m in applied:
            m.apply = apply


def _site(ev) -> str:
    """The call site of ``ev`` (its innermost ``@`` range, :func:`ops_attributed`), or ''."""
    e = ev.cpu_parent
    while e is not None:
        if e.name.startswith("@"):
            return e.name[1:]
        e = e.cpu_parent
    return ""


def _bare(name: str) -> str:
    """An op's or autograd node's name reduced so that the two match (``aten::reflection_pad2d``,
    ``ReflectionPad2D``: ``reflectionpad2d``)."""
    return name.removeprefix("aten::").replace("_", "").lower()


def _is_op(name: str) -> bool:
    return name.startswith("aten::") or name.startswith("warp::")


def op_rows(events, steps: int, cpu: bool) -> tuple[list[dict], dict]:
    """The op table of a profile of ``steps`` steps (inside :func:`ops_attributed`): rows ``{op, site, calls,
    host_us, launches}`` per step, costliest first, and the totals. ``cpu``: a CPU run (the Warp
    launches are the launches)."""
    # (thread, sequence number, op) of the forward op that made an autograd node -> its line (ops
    # recorded before a node is made carry its number too: the node's name says which op made it)
    forward_site = {}
    for e in events:
        if e.sequence_nr >= 0 and not e.name.startswith("autograd::"):
            forward_site.setdefault((e.thread, e.sequence_nr, _bare(e.name)), _site(e))

    def top_and_node(e):
        """The outermost op around ``e`` (itself included) and the innermost autograd node running it."""
        top, node, below, p = (e if _is_op(e.name) else None), None, e, e.cpu_parent
        while p is not None:
            if _is_op(p.name):
                top = p
            if node is None and p.name.startswith("autograd::engine::evaluate_function: "):
                node = below if below.sequence_nr >= 0 else p  # (the node's own range has its number)
            below, p = p, p.cpu_parent
        return top, node

    rows: dict = {}
    key_of: dict = {}  # id(top-level op event) -> its row
    launches = []
    for e in events:
        top, node = top_and_node(e)
        if top is e:
            if node is not None:
                what = node.name.split(": ", 1)[-1]
                made_by = _bare(what.split("Backward")[0])
                fwd = ("(gradient accumulation)" if "AccumulateGrad" in what else
                       "bwd of " + (forward_site.get((node.fwd_thread, node.sequence_nr, made_by)) or "?"))
                key = (f"{e.name} ({what.replace('torch::autograd::', '')})", fwd)
            else:
                key = (e.name, _site(e))
            r = rows.setdefault(key, {"op": key[0], "site": key[1], "calls": 0, "host_us": 0.0, "launches": 0})
            r["calls"] += 1
            r["host_us"] += e.cpu_time_total
            key_of[id(e)] = key
        if e.name in LAUNCH_CALLS or (cpu and top is e and e.name.startswith("warp::")):
            launches.append(top)
    outside = 0
    for top in launches:
        if top is None or id(top) not in key_of:
            outside += 1
        else:
            rows[key_of[id(top)]]["launches"] += 1
    out = [{**r, "calls": r["calls"] / steps, "host_us": r["host_us"] / steps, "launches": r["launches"] / steps}
           for r in rows.values()]
    out.sort(key=lambda r: -r["host_us"])
    totals = {"ops": sum(r["calls"] for r in out), "host_us": sum(r["host_us"] for r in out),
              "launches": sum(r["launches"] for r in out), "launches_outside": outside / steps}
    return out, totals


def _area(site: str) -> str:
    """The function a row's line is in (forward and backward together): ``path function``."""
    site = site.removeprefix("bwd of ")
    if ":" not in site:
        return site or "-"
    path, rest = site.split(":", 1)
    return f"{path} {rest.split(' ', 1)[-1]}"


def op_table(rows: list[dict], totals: dict) -> str:
    """The op table (markdown), then the same rows summed per function (forward and backward)."""
    lines = ["| op | calls | host µs | launches | line |", "|---|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['op']} | {r['calls']:g} | {r['host_us']:.0f} | {r['launches']:g} | {r['site'] or '-'} |")
    lines.append(f"| **total** | {totals['ops']:g} | {totals['host_us']:.0f} | {totals['launches']:g} | "
                 f"(+{totals['launches_outside']:g} launches outside any op) |")
    areas: dict = {}
    for r in rows:
        a = areas.setdefault(_area(r["site"]), [0.0, 0.0, 0.0])
        a[0] += r["calls"]
        a[1] += r["host_us"]
        a[2] += r["launches"]
    lines += ["", "| function (forward + backward) | ops | host µs | launches |", "|---|---:|---:|---:|"]
    for name, (n, us, k) in sorted(areas.items(), key=lambda kv: -kv[1][1]):
        lines.append(f"| {name} | {n:g} | {us:.0f} | {k:g} |")
    return "\n".join(lines)


def measure(data, backend: str, args, device: torch.device) -> dict:
    fn, kw = rasterizer(backend)
    torch.manual_seed(args.seed)
    t = Trainer(data, iters=args.iters, sh_degree=3, rasterize=fn, raster_kwargs=kw, device=device, seed=args.seed,
                progress=False)
    warm_up(t)
    for _ in range(args.warm):
        t.train_step()
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        t.train_step()
    sync()
    row = {"backend": backend, "ms_per_step": (time.perf_counter() - t0) / args.steps * 1e3, "step": t.step,
           "gaussians": t.num_gaussians, "syncs": []}
    if device.type == "cuda":
        for (msg, where), n in sorted(sync_sites(t.train_step).items(), key=lambda kv: kv[0][1]):
            if "prototype" not in msg:
                row["syncs"].append(f"{n // 3} per step: {where or '(no ssgwarp frame)'}")
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=acts) as p:
            for _ in range(5):
                t.train_step()
            sync()
        row["profile"] = p.key_averages().table(sort_by="cpu_time_total", row_limit=60)
    if args.ops:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with ops_attributed(), profile(activities=acts) as p:
            for _ in range(OPS_STEPS):
                t.train_step()
            sync()
        row["ops"] = op_rows(p.events(), OPS_STEPS, device.type == "cpu")
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="fern8", help="fern8, fern4, cup, lego or PATH[:IMAGES]")
    p.add_argument("--data-root", type=Path, default=None)
    p.add_argument("--backend", nargs="+", choices=("ssgwarp", "gsplat"), default=["ssgwarp", "gsplat"])
    p.add_argument("--warm", type=int, default=700,
                   help="steps before the timing (default 700: past the 7k schedule's refinements at 117..700)")
    p.add_argument("--steps", type=int, default=90, help="timed steps (default 90: up to the next refinement)")
    p.add_argument("--iters", type=int, default=7000, help="the run's length, which sets the schedule")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's top host ops")
    p.add_argument("--ops", action="store_true", help=f"also print the step's op table (over {OPS_STEPS} steps: "
                   "every torch op and Warp launch, calls and host µs per step, the source line)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    data = load_scene(args.scene, args.data_root or data_root(), device)
    rows = [measure(data, b, args, device) for b in args.backend]
    print(f"\n{args.scene}, {device.type}: steps {args.warm + 1}-{args.warm + args.steps} of a {args.iters}-step run\n")
    print("| backend | ms per step | Gaussians | synchronisations per step |")
    print("|---|---:|---:|---|")
    for r in rows:
        print(f"| {r['backend']} | {r['ms_per_step']:.2f} | {r['gaussians']:,} | {'; '.join(r['syncs']) or '-'} |")
    if len(rows) == 2:
        print(f"\nratio {rows[0]['backend']} / {rows[1]['backend']}: {rows[0]['ms_per_step'] / rows[1]['ms_per_step']:.2f}x")
    for r in rows:
        if "profile" in r:
            print(f"\n{r['backend']}: top host ops over 5 steps\n{r['profile']}")
        if "ops" in r:
            print(f"\n{r['backend']}: the step's ops, per step (mean of {OPS_STEPS})\n\n{op_table(*r['ops'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
