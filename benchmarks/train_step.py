"""A training step's cost, and whole training runs, with ssgwarp's rasterizer or gsplat's (and its strategies).

One Trainer per ``--backend`` on the same capture, seed and recipe: ``--warm`` steps, then ``--steps`` timed steps:
ms per step and, on CUDA, each synchronising call and the frames that made it; ``--ops`` names a backward op by the
line of its forward op (docs/benchmarks.md, "The training step").

    python benchmarks/train_step.py --scene fern4 --backend ssgwarp --profile
    OMP_NUM_THREADS=2 python benchmarks/train_step.py --device cpu --backend ssgwarp --warm 20 --steps 5 --ops
    python benchmarks/train_step.py --scene fern4 --backend ssgwarp --optimizer torch warp   # Adam: torch / WarpAdam

Modes, each with its own ``--help``: ``runs`` (whole training runs), ``loss`` (the photometric loss, fused or not).

    python benchmarks/train_step.py runs --scenes fern8 fern4 --backend ssgwarp gsplat
    OMP_NUM_THREADS=1 python benchmarks/train_step.py loss --device cpu --clock cpu
"""
from __future__ import annotations

import collections
import contextlib
import gc
import json
import sys
import threading
import time
import traceback
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar, Optional

import torch

from harness import (CAPTURES, ROOT, append_jsonl, capture_folder, cuda_kernel_ms, dispatch, fmt, header, interleaved,
                     knobs, parser, per_call_us, sync, table, write_text)

from ssgwarp.capture.datasets import load_dataset
from ssgwarp.cli import resolve_device
from ssgwarp.core.fileio import write_json
from ssgwarp.raster.rendering import render as render_views
from ssgwarp.reconstruction.recipe import Recipe
from ssgwarp.reconstruction.trainer import Trainer
from ssgwarp.reconstruction.step import adam_step
from ssgwarp.reconstruction.strategy import DefaultStrategy, MCMCStrategy, Strategy

RUNS_DOC = """Whole training runs: our 3DGS loop with either rasterizer and each densification strategy.

One Trainer loop per scene x ``--backend`` x ``--strategy`` (ours, or gsplat 1.5's on our tensors and schedule) x
``--iters`` x ``--max-gaussians`` x ``--recipe``; tables and raw rows go to ``--out``. Targets (issues 3, 14): within
0.2 dB of gsplat's rasterizer at <= 1.5x time.

    python benchmarks/train_step.py runs --scenes fern8 cup lego --strategy default gsplat-default --match-default
    python benchmarks/train_step.py runs --scenes PATH --iters 120 --device cpu --strategy default mcmc
"""

STRATEGIES = ("default", "mcmc", "gsplat-default", "gsplat-mcmc")


def rasterizer(backend: str):
    """``(rasterize function, extra kwargs)`` for a backend name (None: the Trainer's default, ssgwarp's)."""
    if backend == "ssgwarp":
        return None, {}
    try:
        from gsplat import rasterization
    except ImportError as e:
        raise SystemExit(f"--backend gsplat needs the gsplat package ({e}); pip install gsplat") from None
    return rasterization, {"packed": False}  # [C, N] layout, as the densification statistics read it


@dataclass
class GsplatStrategy(Strategy):
    """gsplat's ``DefaultStrategy`` or ``MCMCStrategy`` driving the Trainer's Gaussians under gsplat's names, with
    one-group optimizer views and our strategy's thresholds; gsplat refines once its step is past
    ``refine_start_iter``: ``refine_start - 1``."""

    kind: str = "default"
    reset_every: Optional[int] = None

    to_gsplat: ClassVar[dict] = {"log_scales": "scales", "logit_opacities": "opacities", "sh_dc": "sh0",
                                 "sh_rest": "shN"}

    def __post_init__(self):
        super().__post_init__()
        if self.kind not in ("default", "mcmc"):
            raise ValueError(self.kind)
        self.name = f"gsplat-{self.kind}"
        self.ours = DefaultStrategy() if self.kind == "default" else MCMCStrategy()   # (its thresholds)
        self.reference, self.recipe_defaults = self.ours.reference, self.ours.recipe_defaults
        self.budgeted = self.kind == "mcmc"
        self.uses_means2d_grad = self.kind == "default"
        self._meta = None

    def setup(self, gaussians, *, recipe, extent, seed) -> None:
        super().setup(gaussians, recipe=recipe, extent=extent, seed=seed)
        import gsplat.strategy as gs

        sch, ours = self.schedule, self.ours
        ours.extent = self.extent
        common = dict(refine_start_iter=sch.refine_start - 1, refine_stop_iter=sch.refine_stop,
                      refine_every=sch.refine_every)
        if self.kind == "default":
            self.impl = gs.DefaultStrategy(prune_opa=ours.prune_opacity, grow_grad2d=ours.grad_threshold,
                                           grow_scale3d=ours.percent_dense, prune_scale3d=ours.prune_world,
                                           reset_every=sch.reset_every or 10**12, **common)
            self.state = self.impl.initialize_state(scene_scale=extent)
        else:
            self.impl = gs.MCMCStrategy(cap_max=self.max_gaussians, noise_lr=ours.noise_lr,
                                        min_opacity=ours.prune_opacity, **common)
            self.state = self.impl.initialize_state()
        self.impl.check_sanity(*self._views(gaussians))

    def _views(self, g):
        params = {self.to_gsplat.get(k, k): v for k, v in g.params.items()}
        groups = g.groups
        # (one named group of the Trainer's Adam, as gsplat's strategy ops expect an optimizer)
        return params, {self.to_gsplat.get(k, k): SimpleNamespace(state=g.opt.state, param_groups=[groups[k]])
                        for k in g.params}

    def regularizer(self, g):
        return self.ours.regularizer(g)

    def observe(self, g, meta: dict) -> None:
        meta.setdefault("gaussian_ids", None)  # gsplat reads it (None in the non-packed layout)
        self._meta = meta

    def step(self, g, step: int, lr_means: float) -> dict:
        params, opts = self._views(g)
        n0 = len(g)
        extra = {"packed": False} if self.kind == "default" else {"lr": lr_means / self.extent ** 2}
        self.impl.step_post_backward(params, opts, self.state, step, self._meta, **extra)
        back = {v: k for k, v in self.to_gsplat.items()}
        for k, v in params.items():
            g.params[back.get(k, k)] = v
        self._meta = None
        return {"refine": {"gaussians": len(g) - n0}} if len(g) != n0 else {}


def make(strategy: str, max_gaussians: int) -> Strategy:
    """Our strategy ``strategy`` or gsplat's (``gsplat-default``, ``gsplat-mcmc``) with this cap / budget."""
    if strategy.startswith("gsplat-"):
        return GsplatStrategy(max_gaussians=max_gaussians, kind=strategy.split("-", 1)[1])
    return {"default": DefaultStrategy, "mcmc": MCMCStrategy}[strategy](max_gaussians=max_gaussians)


def warm_up(trainer: Trainer) -> None:
    """Compile/JIT the rasterizer's kernels (every SH degree, forward and backward) outside the timed loop."""
    scene = trainer.scene.detach().map(lambda t: t.requires_grad_(True))
    cam = trainer.data.cameras[trainer.data.train_ids[0]]
    bg = trainer.data.background_tensor(3)[None]
    for deg in range(trainer.sh_degree + 1):
        out, _, meta = render_views(scene, cam, sh_degree=deg, backgrounds=bg, rasterize=trainer.rasterize,
                                    **trainer.raster_kwargs)
        meta["means2d"].retain_grad()
        out.sum().backward()


def train_and_measure(data, *, backend: str = "ssgwarp", strategy="default", iters: int = 7000,
                      sh_degree: int = 3, seed: int = 0, max_gaussians: int = 1_000_000,
                      recipe: Recipe | None = None, device: torch.device, progress: bool = False,
                      dssim_scale: float = 1.0) -> dict:
    """Train one run on ``data`` (warm-up outside the timing) and return its held-out metrics and cost."""
    fn, kw = rasterizer(backend)
    torch.manual_seed(seed)
    recipe = replace(recipe or Recipe(), dssim_scale=dssim_scale, sh_degree=sh_degree)
    trainer = Trainer(data, iters=iters, recipe=recipe, rasterize=fn, raster_kwargs=kw, device=device, seed=seed,
                      progress=progress, strategy=make(strategy, max_gaussians) if isinstance(strategy, str) else
                      replace(strategy, max_gaussians=max_gaussians))
    warm_up(trainer)
    sync(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    trainer.train()
    sync(device)
    seconds = time.perf_counter() - t0
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else float("nan")
    ev = trainer.evaluate()
    r = trainer.strategy
    out = {"backend": backend, "strategy": trainer.strategy.name, "resolution": f"{data.width}x{data.height}",
           "iters": iters, "max_gaussians": max_gaussians, "psnr": ev["psnr"], "ssim": ev["ssim"],
           "gaussians": trainer.num_gaussians, "seconds": seconds, "peak_mib": peak, "test_views": ev["views"],
           "schedule": [r.refine_start, r.refine_stop, r.refine_every, getattr(r, "reset_every", 0)], "dssim_scale": dssim_scale,
           **data.metric_frame}
    del trainer
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return out


def tables(rows: list[dict]) -> str:
    lines = [table(rows, [("scene", "scene"), ("resolution", "resolution"), ("iters", "iters"), ("backend", "backend"),
                          ("strategy", "strategy"), ("recipe", "recipe"), ("max_gaussians", "budget"),
                          ("psnr", "held-out PSNR (dB)"),
                          ("ssim", "SSIM", 4), ("gaussians", "Gaussians"), ("seconds", "train time (s)", 1),
                          ("peak_mib", "peak GPU mem (MiB)", 0)])]
    key = lambda r, **kw: tuple({**r, **kw}[k] for k in ("scene", "iters", "backend", "strategy", "max_gaussians"))
    by = {key(r): r for r in rows}
    pairs = []
    for r in rows:  # rasterizers: ssgwarp vs gsplat, same everything else
        if r["backend"] == "ssgwarp" and key(r, backend="gsplat") in by:
            b = by[key(r, backend="gsplat")]
            pairs.append(f"| {r['scene']} | {r['iters']} | {r['strategy']} | {r['psnr'] - b['psnr']:+.2f} dB | "
                         f"{r['seconds'] / b['seconds']:.2f}x | {fmt(r['peak_mib'] / b['peak_mib'])}x |")
    if pairs:
        lines += ["", "| scene | iters | strategy | PSNR ssgwarp - gsplat rasterizer (target >= -0.2 dB) | "
                      "time ssgwarp / gsplat (target <= 1.5x) | memory ssgwarp / gsplat |",
                  "|---|---:|---|---:|---:|---:|"] + pairs
    strat = []
    for r in rows:  # strategies: ours vs gsplat's; MCMC at the default's count vs default
        ref = f"gsplat-{r['strategy']}"
        if key(r, strategy=ref) in by:
            b = by[key(r, strategy=ref)]
            strat.append(f"| {r['scene']} | {r['iters']} | {r['backend']} | {r['strategy']} - {ref} | "
                         f"{r['psnr'] - b['psnr']:+.2f} dB | {r['gaussians']:,} / {b['gaussians']:,} | "
                         f"{r['seconds'] / b['seconds']:.2f}x |")
        if r["strategy"] == "mcmc" and r.get("matched"):
            d = by.get(key(r, strategy="default", max_gaussians=r["matched_budget"]))
            if d:
                strat.append(f"| {r['scene']} | {r['iters']} | {r['backend']} | mcmc - default (equal count) | "
                             f"{r['psnr'] - d['psnr']:+.2f} dB | {r['gaussians']:,} / {d['gaussians']:,} | "
                             f"{r['seconds'] / d['seconds']:.2f}x |")
    if strat:
        lines += ["", "| scene | iters | backend | pair | PSNR difference (targets: ours - gsplat's >= -0.2 dB; "
                      "mcmc - default >= 0) | Gaussians | time ratio |", "|---|---:|---|---|---:|---:|---:|"] + strat
    return "\n".join(lines)


def load_scene(spec: str, root: Path | None, device: torch.device, random_points: int = 100_000, width=None):
    """A shared capture by name (harness.CAPTURES) or PATH[:IMAGES], loaded on ``device`` (``width``: resized)."""
    folder, images = capture_folder(spec, root)
    return load_dataset(folder, images=images, device=device, num_random_points=random_points, width=width)


def runs_main(argv=None) -> int:
    """`train_step.py runs`: whole training runs (see the module's docstring)."""
    p = parser("train_step.py runs", RUNS_DOC)
    p.add_argument("--scenes", nargs="+", default=["fern8", "fern4"], help=f"{', '.join(CAPTURES)} or PATH[:IMAGES]")
    p.add_argument("--data-root", type=Path, default=None, help="folder holding llff_fern, colmap_cup, lego_200")
    p.add_argument("--backend", nargs="+", choices=("ssgwarp", "gsplat", "both"), default=["ssgwarp"])
    p.add_argument("--strategy", nargs="+", choices=STRATEGIES, default=["default"])
    p.add_argument("--iters", nargs="+", type=int, default=[7000])
    p.add_argument("--max-gaussians", nargs="+", type=int, default=[1_000_000])
    p.add_argument("--recipe", nargs="+", default=[""], help="variants, each 'field=value,...' of the Recipe or the strategy (e.g. "
                   "prune_contribution=0.5,prune_budget=200000 or optimizer=warp); default: the defaults")
    p.add_argument("--match-default", action="store_true",
                   help="also run mcmc with the budget set to the default run's final count")
    p.add_argument("--sh-degree", type=int, default=3)
    p.add_argument("--width", type=int, default=None, help="resize the images to this width (default: as stored)")
    p.add_argument("--random-points", type=int, default=100_000,
                   help="initial points of captures without a point cloud (lego; default 100000, as the CLI)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dssim-scale", type=float, default=1.0,
                   help="multiplier of the D-SSIM term: 1 (default) is the 3DGS loss, 0.5 the halved term of old")
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", type=Path, default=Path("benchmark-runs"), help="folder for results.json / results.md")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    device = resolve_device(a.device)
    backends = list(dict.fromkeys(b for x in a.backend for b in (("ssgwarp", "gsplat") if x == "both" else (x,))))
    rows = []

    def record(r):
        print(json.dumps(r), flush=True)
        rows.append(r)
        write_json(a.out / "results.json", {"rows": rows})  # partial results survive an interruption

    for spec in a.scenes:
        data = load_scene(spec, a.data_root, device, a.random_points, a.width)
        for iters in a.iters:
            for backend in backends:
                common = dict(backend=backend, iters=iters, sh_degree=a.sh_degree, seed=a.seed, device=device,
                              progress=not a.no_progress, dssim_scale=a.dssim_scale)
                for strategy in a.strategy:
                    for budget, rs in ((b, rs) for b in a.max_gaussians for rs in a.recipe):
                        st = make(strategy, budget)
                        rv, sv = knobs(rs.split(","), Recipe(), st)   # (a Recipe field, else the strategy's knob)
                        recipe, st = Recipe(**rv), replace(st, **sv)
                        r = train_and_measure(data, strategy=st, max_gaussians=budget, recipe=recipe, **common)
                        record({"scene": spec, **r, **({"recipe": rs} if rs else {})})
                        if a.match_default and strategy == "default":
                            m = train_and_measure(data, strategy="mcmc", max_gaussians=r["gaussians"], **common)
                            record({"scene": spec, **m, "matched": r["gaussians"], "matched_budget": budget})
        del data
    head = header(device, f"SH degree {a.sh_degree}, seed {a.seed}, D-SSIM scale {a.dssim_scale:g}; held-out views "
                          "every 8th")
    print(f"\n{head}\n\n{tables(rows)}")
    write_json(a.out / "results.json", {"setup": head, "rows": rows})
    write_text(a.out / "results.md", f"{head}\n\n{tables(rows)}\n")
    return 0


FRAMES = ("ssgwarp", "kornia", "gsplat", "torch/optim")  # the frames a synchronisation is attributed to
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
    """While inside, every torch call runs in a profiler range ``@path:line function`` and every Warp launch of
    :mod:`ssgwarp.raster.launch` in a range ``warp::<kernel>`` too (the CPU blending's worker threads left out)."""
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
    host_us, launches}`` per step, costliest first, and the totals (``cpu``: the Warp launches are the launches)."""
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


def measure(data, backend: str, args, device: torch.device, optimizer: str = "torch") -> dict:
    fn, kw = rasterizer(backend)
    torch.manual_seed(args.seed)
    t = Trainer(data, iters=args.iters, recipe=Recipe(sh_degree=3, optimizer=optimizer), rasterize=fn,
                raster_kwargs=kw, device=device, seed=args.seed, progress=False)
    warm_up(t)
    for _ in range(args.warm):
        t.train_step()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(args.steps):
        t.train_step()
    sync(device)
    row = {"backend": backend, "optimizer": optimizer, "ms_per_step": (time.perf_counter() - t0) / args.steps * 1e3,
           "step": t.step, "gaussians": t.num_gaussians, "syncs": []}
    if device.type == "cuda":
        for (msg, where), n in sorted(sync_sites(t.train_step).items(), key=lambda kv: kv[0][1]):
            if "prototype" not in msg:
                row["syncs"].append(f"{n // 3} per step: {where or '(no ssgwarp frame)'}")
    for what in [w for w in ("profile", "ops") if getattr(args, w)]:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with ops_attributed() if what == "ops" else contextlib.nullcontext(), profile(activities=acts) as p:
            for _ in range(OPS_STEPS):
                t.train_step()
            sync(device)
        if what == "profile":
            row["profile"] = p.key_averages().table(sort_by="cpu_time_total", row_limit=60)
        else:
            row["ops"] = op_rows(p.events(), OPS_STEPS, device.type == "cpu")
    grads = {k: torch.randn_like(p) * 1e-3 for k, p in t.params.items()}

    def adam_only():   # the optimiser step alone, every group
        for k, p in t.params.items():
            p.grad = grads[k]
        adam_step(t.opt)
    clock = time.process_time if device.type == "cpu" else time.perf_counter   # (CPU: the process's CPU time)
    row["adam_us"] = per_call_us(adam_only, device, 50, 3, clock=clock)
    row["adam_gpu_us"] = 1e3 * sum(cuda_kernel_ms(adam_only).values()) if device.type == "cuda" else None
    return row


def step_main(argv=None) -> int:
    p = parser("train_step.py", __doc__)
    p.add_argument("--scene", default="fern8", help="fern8, fern4, cup, lego or PATH[:IMAGES]")
    p.add_argument("--data-root", type=Path, default=None)
    p.add_argument("--backend", nargs="+", choices=("ssgwarp", "gsplat"), default=["ssgwarp", "gsplat"])
    p.add_argument("--optimizer", nargs="+", choices=("torch", "warp"), default=["torch"],
                   help="the scene's Adam: torch's fused (one launch per tensor) or WarpAdam (one launch)")
    p.add_argument("--warm", type=int, default=700,
                   help="steps before the timing (default 700: past the 7k schedule's refinements at 117..700)")
    p.add_argument("--steps", type=int, default=90, help="timed steps (default 90: up to the next refinement)")
    p.add_argument("--iters", type=int, default=7000, help="the run's length, which sets the schedule")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's top host ops")
    p.add_argument("--ops", action="store_true", help=f"also print the step's op table (over {OPS_STEPS} steps: "
                   "every torch op and Warp launch, calls and host µs per step, the source line)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", default=None, help="append the rows as JSON lines")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    data = load_scene(args.scene, args.data_root, device)
    rows = [measure(data, b, args, device, o) for b in args.backend for o in args.optimizer]
    for r in rows:
        append_jsonl(args.out, {k: v for k, v in r.items() if k not in ("profile", "ops")})
    print(f"\n{header(device)}; {args.scene}: steps {args.warm + 1}-{args.warm + args.steps} of a {args.iters}-step run\n")
    shown = [dict(r, syncs="; ".join(r["syncs"]) or "-", adam=f"{r['adam_us']:.0f}" + (
        "" if r["adam_gpu_us"] is None else f" ({r['adam_gpu_us']:.0f})")) for r in rows]
    print(table(shown, [("backend", "backend"), ("optimizer", "Adam"), ("ms_per_step", "ms per step"),
                        ("adam", "Adam alone, µs (GPU µs)"), ("gaussians", "Gaussians"),
                        ("syncs", "synchronisations per step")]))
    if len(rows) == 2:
        print(f"\nratio {rows[0]['backend']}/{rows[0]['optimizer']} / {rows[1]['backend']}/{rows[1]['optimizer']}: "
              f"{rows[0]['ms_per_step'] / rows[1]['ms_per_step']:.2f}x")
    for r in rows:
        if "profile" in r:
            print(f"\n{r['backend']}: top host ops over 5 steps\n{r['profile']}")
        if "ops" in r:
            print(f"\n{r['backend']}: the step's ops, per step (mean of {OPS_STEPS})\n\n{op_table(*r['ops'])}")
    return 0


LOSS_SIZES = ("504x378", "1008x756", "1920x1080")


def loss_images(w: int, h: int, views: int, dtype, device):
    """A render-like pair: the target and a noisy, slightly blurred copy (the render, needing a gradient)."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(views, h, w, 3, generator=g).to(dtype)
    img = (0.9 * gt + 0.1 * torch.rand(views, h, w, 3, generator=g).to(dtype)).clamp(0, 1)
    return img.to(device).requires_grad_(True), gt.to(device)


def loss_closures(img, gt, fused: bool):
    from ssgwarp.services.losses import photometric

    def forward():
        with torch.no_grad():
            photometric(img, gt, fused=fused)

    def both():
        img.grad = None
        photometric(img, gt, fused=fused).backward()
    return forward, both


def loss_main(argv=None) -> int:
    p = parser("train_step.py loss", "the photometric loss: torch reference against the fused Warp kernels, per size")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--sizes", nargs="+", default=list(LOSS_SIZES), help="WxH (default: %(default)s)")
    p.add_argument("--views", type=int, default=1, help="images per call ([V, H, W, 3])")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--repeats", type=int, default=None, help="timed calls per case (default: 5 CPU, 50 CUDA)")
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                   help="wall-clock time, or this process's CPU time (a shared machine's load does not count)")
    p.add_argument("--out", default=None, help="append the rows as JSON lines")
    args = p.parse_args(argv)
    dev = torch.device(args.device)
    repeats = args.repeats or (5 if dev.type == "cpu" else 50)
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    print(f"{header(dev)}; photometric loss, {args.views} view(s) x 3 channels, {args.dtype}; median of {repeats}, "
          f"{args.clock} clock\n\n| size | pass | reference ms | fused ms | fused / reference |\n|---|---|---|---|---|")
    for size in args.sizes:
        w, h = (int(v) for v in size.lower().split("x"))
        img, gt = loss_images(w, h, args.views, getattr(torch, args.dtype), dev)
        ref_f, ref_b = loss_closures(img, gt, False)
        fus_f, fus_b = loss_closures(img, gt, True)
        rows = []
        for name, fns in (("forward", (ref_f, fus_f)), ("forward+backward", (ref_b, fus_b))):
            t = interleaved(dict(enumerate(fns)), dev, repeats, rounds=repeats, clock=clock)
            rows.append((name, t[0]["median"], t[1]["median"]))
        if dev.type == "cuda":  # host cost per step: one synchronisation per block of 20 calls
            r, f = (per_call_us(fn, dev, 20, max(3, repeats // 10)) / 1e3 for fn in (ref_b, fus_b))
            rows.append(("fwd+bwd, 20 queued", r, f))
            kr, kf = (cuda_kernel_ms(fn) for fn in (ref_b, fus_b))
            rows.append((f"fwd+bwd GPU kernels ({len(kr)} / {len(kf)} kinds)", sum(kr.values()), sum(kf.values())))
        for name, r, f in rows:
            print(f"| {w}x{h} | {name} | {r:.3f} | {f:.3f} | {f / r:.2f} |")
            append_jsonl(args.out, {"size": f"{w}x{h}", "pass": name, "reference_ms": r, "fused_ms": f})
        del img, gt
    return 0


MODES = {"runs": runs_main, "loss": loss_main}


def main(argv=None) -> int:
    return dispatch(MODES, step_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
