"""Reconstruction benchmark: our 3DGS loop with either rasterizer and each densification strategy.

One :class:`ssgwarp.reconstruction.reconstruct.Trainer` loop (same data, seed, recipe, schedule); what varies:

* ``--backend``: ``ssgwarp`` (our Warp rasterizer) or ``gsplat`` (``gsplat.rasterization``,
  non-packed; imported only when asked);
* ``--strategy``: ``default`` / ``mcmc`` (ours, :mod:`ssgwarp.reconstruction.strategy`) or ``gsplat-default`` /
  ``gsplat-mcmc`` (gsplat 1.5's ``DefaultStrategy`` / ``MCMCStrategy`` editing our loop's
  tensors and Adam state through :class:`GsplatStrategy`; MCMC needs gsplat's CUDA ops). The gsplat
  strategies get our resolved schedule and thresholds, the MCMC regulariser is ours for both
  (gsplat keeps it in its trainer), and gsplat's MCMC noise gets the position learning rate divided
  by ``extent^2`` so its noise ``lr * noise_lr * Sigma z`` is ours (the paper's formula in units of
  the scene extent, as on gsplat's own normalised scenes);
* ``--scenes``: ``fern8`` / ``fern4`` (LLFF fern ``images_8`` / ``images_4``), ``cup`` (COLMAP
  ``colmap_cup``), ``lego`` (``lego_200`` transforms, white background), or ``PATH[:IMAGES]``;
* ``--iters`` (several allowed) and ``--max-gaussians`` (several: with ``mcmc`` this is the budget
  sweep of docs/tradeoffs.md).

``--dssim-scale 0.5`` trains with the halved D-SSIM term ssgwarp used before (default 1: the 3DGS loss).
Distorted captures (fern is SIMPLE_RADIAL) are undistorted into a pinhole crop (every pixel has a
source, ``ssgwarp.capture.lens``); PSNR/SSIM are measured on that crop (``metric_frame`` in the JSON rows).

``--match-default`` also runs ``mcmc`` with the budget set to the Gaussian count the ``default`` run of
the same scene / backend / iters ended with (MCMC at an equal count). Prints markdown tables (runs;
backend pairs; strategy pairs; budget sweep) and writes them with the raw numbers to ``--out``.

    python benchmarks/reconstruct.py --scenes fern8 --backend ssgwarp gsplat --strategy default
    python benchmarks/reconstruct.py --scenes fern8 cup lego --strategy default gsplat-default --match-default
    python benchmarks/reconstruct.py --scenes fern8 --strategy mcmc --max-gaussians 50000 100000 300000 1000000
    python benchmarks/reconstruct.py --scenes PATH --iters 120 --device cpu --strategy default mcmc \
        --random-points 2000                                                        # CPU smoke test

Targets (issues 3, 14): held-out PSNR ssgwarp vs gsplat rasterizer within 0.2 dB, time within 1.5x;
fern ``images_8`` 7k >= 25.2 dB; our default within 0.2 dB of gsplat's DefaultStrategy; MCMC at an
equal count >= default.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
from shared_data import data_root  # noqa: E402

from ssgwarp.capture.datasets import load_dataset  # noqa: E402
from ssgwarp.core.fileio import atomic_path, write_json  # noqa: E402
from ssgwarp.raster.rendering import render as render_views  # noqa: E402
from ssgwarp.reconstruction.recipe import Recipe
from ssgwarp.reconstruction.trainer import Trainer
from ssgwarp.reconstruction.strategy import DefaultStrategy, MCMCStrategy, Strategy  # noqa: E402

SCENES = {"fern8": ("llff_fern", "images_8"), "fern4": ("llff_fern", "images_4"), "cup": ("colmap_cup", "images"),
          "lego": ("lego_200", "images")}
STRATEGIES = ("default", "mcmc", "gsplat-default", "gsplat-mcmc")


def rasterizer(backend: str):
    """``(rasterize function or None, extra kwargs)`` for a backend name."""
    if backend == "ssgwarp":
        return None, {}  # the Trainer's default: ssgwarp.rasterization (Warp kernels on CUDA)
    if backend == "gsplat":
        try:
            from gsplat import rasterization
        except ImportError as e:
            raise SystemExit(f"--backend gsplat needs the gsplat package ({e}); pip install gsplat") from None
        return rasterization, {"packed": False}  # [C, N] layout, as the densification statistics read it
    raise SystemExit(f"unknown backend {backend!r}")


class _OneGroup:
    """What gsplat's strategy ops expect of an optimizer (``param_groups`` of one group, ``state``),
    as a view of one named group of the Trainer's Adam."""

    def __init__(self, opt: torch.optim.Optimizer, group: dict):
        self.state = opt.state
        self.param_groups = [group]


class GsplatStrategy(Strategy):
    """gsplat's ``DefaultStrategy`` or ``MCMCStrategy`` driving the Trainer's Gaussians (a reference for ours).

    Our tensors go to gsplat under its names (``scales``, ``opacities``, ``sh0``, ``shN``; the rest as
    they are) with one-group optimizer views; what gsplat puts back (new parameters, moved Adam
    state) is written back under our names. gsplat's schedule is given as ours: it refines when its
    step (our completed-step count) is past ``refine_start_iter``, hence ``refine_start - 1``.
    """

    to_gsplat = {"log_scales": "scales", "logit_opacities": "opacities", "sh_dc": "sh0", "sh_rest": "shN"}

    def __init__(self, kind: str):
        super().__init__()
        if kind not in ("default", "mcmc"):
            raise ValueError(kind)
        self.kind = kind
        self.name = f"gsplat-{kind}"
        ours = DefaultStrategy if kind == "default" else MCMCStrategy
        self.reference, self.recipe_defaults = ours.reference, ours.recipe_defaults
        self.budgeted = kind == "mcmc"
        self.uses_means2d_grad = kind == "default"
        self._meta = None

    def setup(self, gaussians, *, recipe, extent, max_gaussians, seed) -> None:
        super().setup(gaussians, recipe=recipe, extent=extent, max_gaussians=max_gaussians, seed=seed)
        import gsplat.strategy as gs

        sch = self.schedule
        common = dict(refine_start_iter=sch.refine_start - 1, refine_stop_iter=sch.refine_stop,
                      refine_every=sch.refine_every)
        if self.kind == "default":
            self.impl = gs.DefaultStrategy(prune_opa=recipe.prune_opacity, grow_grad2d=recipe.grad_threshold,
                                           grow_scale3d=recipe.percent_dense, prune_scale3d=recipe.prune_world,
                                           reset_every=sch.reset_every or 10**12, **common)
            self.state = self.impl.initialize_state(scene_scale=extent)
        else:
            self.impl = gs.MCMCStrategy(cap_max=max_gaussians, noise_lr=recipe.noise_lr,
                                        min_opacity=recipe.prune_opacity, **common)
            self.state = self.impl.initialize_state()
        self.impl.check_sanity(*self._views(gaussians))

    def _views(self, g):
        params = {self.to_gsplat.get(k, k): v for k, v in g.params.items()}
        groups = g.groups
        return params, {self.to_gsplat.get(k, k): _OneGroup(g.opt, groups[k]) for k in g.params}

    def regularizer(self, g):
        return MCMCStrategy.regularizer(self, g) if self.kind == "mcmc" else None

    def observe(self, g, meta: dict) -> None:
        meta.setdefault("gaussian_ids", None)  # gsplat reads it (None in the non-packed layout)
        self._meta = meta

    def step(self, g, step: int, lr_means: float) -> dict:
        params, opts = self._views(g)
        n0 = len(g)
        if self.kind == "default":
            self.impl.step_post_backward(params, opts, self.state, step, self._meta, packed=False)
        else:
            self.impl.step_post_backward(params, opts, self.state, step, self._meta,
                                         lr=lr_means / self.extent ** 2)
        back = {v: k for k, v in self.to_gsplat.items()}
        for k, v in params.items():
            g.params[back.get(k, k)] = v
        self._meta = None
        return {"refine": {"gaussians": len(g) - n0}} if len(g) != n0 else {}


def make(strategy: str):
    return GsplatStrategy(strategy.split("-", 1)[1]) if strategy.startswith("gsplat-") else strategy


def warm_up(trainer: Trainer) -> None:
    """Compile/JIT the rasterizer's kernels (every SH degree, forward and backward) outside the timed loop."""
    scene = trainer.scene.detach()
    scene = scene.map(lambda t: t.requires_grad_(True))
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
    recipe = replace(recipe or Recipe(), dssim_scale=dssim_scale)
    trainer = Trainer(data, iters=iters, sh_degree=sh_degree, max_gaussians=max_gaussians, recipe=recipe,
                      rasterize=fn, raster_kwargs=kw, device=device, seed=seed, progress=progress,
                      strategy=make(strategy) if isinstance(strategy, str) else strategy)
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
    r = trainer.recipe
    out = {"backend": backend, "strategy": trainer.strategy.name, "resolution": f"{data.width}x{data.height}",
           "iters": iters, "max_gaussians": max_gaussians, "psnr": ev["psnr"], "ssim": ev["ssim"],
           "gaussians": trainer.num_gaussians, "seconds": seconds, "peak_mib": peak, "test_views": ev["views"],
           "schedule": [r.refine_start, r.refine_stop, r.refine_every, r.reset_every], "dssim_scale": dssim_scale,
           **data.metric_frame}
    del trainer
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return out


def _f(v, spec=".2f"):
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def tables(rows: list[dict]) -> str:
    lines = ["| scene | resolution | iters | backend | strategy | budget | held-out PSNR (dB) | SSIM | Gaussians | "
             "train time (s) | peak GPU mem (MiB) |", "|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['resolution']} | {r['iters']} | {r['backend']} | {r['strategy']} | "
                     f"{r['max_gaussians']:,} | {_f(r['psnr'])} | {_f(r['ssim'], '.4f')} | {r['gaussians']:,} | "
                     f"{r['seconds']:.1f} | {_f(r['peak_mib'], '.0f')} |")
    key = lambda r, **kw: tuple({**r, **kw}[k] for k in ("scene", "iters", "backend", "strategy", "max_gaussians"))
    by = {key(r): r for r in rows}
    pairs = []
    for r in rows:  # rasterizers: ssgwarp vs gsplat, same everything else
        if r["backend"] == "ssgwarp" and key(r, backend="gsplat") in by:
            b = by[key(r, backend="gsplat")]
            pairs.append(f"| {r['scene']} | {r['iters']} | {r['strategy']} | {r['psnr'] - b['psnr']:+.2f} dB | "
                         f"{r['seconds'] / b['seconds']:.2f}x | {_f(r['peak_mib'] / b['peak_mib'], '.2f')}x |")
    if pairs:
        lines += ["", "| scene | iters | strategy | PSNR ssgwarp - gsplat rasterizer (target >= -0.2 dB) | "
                      "time ssgwarp / gsplat (target <= 1.5x) | memory ssgwarp / gsplat |",
                  "|---|---:|---|---:|---:|---:|"] + pairs
    strat = []
    for r in rows:  # strategies: ours vs gsplat's; MCMC at the default's count vs default
        for ref in (f"gsplat-{r['strategy']}",):
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
    sweep = [r for r in rows if r["strategy"] in ("mcmc", "gsplat-mcmc") and not r.get("matched")]
    groups = {}
    for r in sweep:
        groups.setdefault((r["scene"], r["iters"], r["backend"], r["strategy"]), []).append(r)
    budget = [g for g in groups.values() if len(g) > 1]
    if budget:
        lines += ["", "| scene | iters | backend | strategy | budget | Gaussians | held-out PSNR (dB) | SSIM | "
                      "train time (s) |", "|---|---:|---|---|---:|---:|---:|---:|---:|"]
        for g in budget:
            for r in sorted(g, key=lambda r: r["max_gaussians"]):
                lines.append(f"| {r['scene']} | {r['iters']} | {r['backend']} | {r['strategy']} | "
                             f"{r['max_gaussians']:,} | {r['gaussians']:,} | {_f(r['psnr'])} | "
                             f"{_f(r['ssim'], '.4f')} | {r['seconds']:.1f} |")
    return "\n".join(lines)


def load_scene(spec: str, root: Path, device: torch.device, random_points: int = 100_000):
    name, images = SCENES.get(spec, (None, None))
    if name is None:
        path, _, images = spec.partition(":")
        folder, images = Path(path), images or "images"
    else:
        folder = root / name
    if not folder.is_dir():
        raise SystemExit(f"scene {spec!r}: {folder} not found (pass --data-root)")
    return load_dataset(folder, images=images, device=device, num_random_points=random_points)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["fern8", "fern4"], help=f"{', '.join(SCENES)} or PATH[:IMAGES]")
    p.add_argument("--data-root", type=Path, default=None, help="folder holding llff_fern, colmap_cup, lego_200")
    p.add_argument("--backend", nargs="+", choices=("ssgwarp", "gsplat", "both"), default=["ssgwarp"])
    p.add_argument("--strategy", nargs="+", choices=STRATEGIES, default=["default"])
    p.add_argument("--iters", nargs="+", type=int, default=[7000])
    p.add_argument("--max-gaussians", nargs="+", type=int, default=[1_000_000])
    p.add_argument("--match-default", action="store_true",
                   help="also run mcmc with the budget set to the default run's final count")
    p.add_argument("--sh-degree", type=int, default=3)
    p.add_argument("--random-points", type=int, default=100_000,
                   help="initial points of captures without a point cloud (lego; default 100000, as the CLI)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dssim-scale", type=float, default=1.0,
                   help="multiplier of the D-SSIM term: 1 (default) is the 3DGS loss, 0.5 the halved term ssgwarp "
                        "used before")
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", type=Path, default=Path("benchmark-reconstruct"),
                   help="folder for results.json / results.md")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    device = torch.device(a.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("CUDA is not available (pass --device cpu for a (slow) CPU run)")
    root = a.data_root or data_root()
    backends = list(dict.fromkeys(b for x in a.backend for b in (("ssgwarp", "gsplat") if x == "both" else (x,))))
    rows = []

    def record(r):
        print(json.dumps(r), flush=True)
        rows.append(r)
        write_json(a.out / "results.json", {"rows": rows})  # partial results survive an interruption

    for spec in a.scenes:
        data = load_scene(spec, root, device, a.random_points)
        for iters in a.iters:
            for backend in backends:
                for strategy in a.strategy:
                    for budget in a.max_gaussians:
                        r = train_and_measure(data, backend=backend, strategy=strategy, iters=iters,
                                              sh_degree=a.sh_degree, seed=a.seed, max_gaussians=budget,
                                              device=device, progress=not a.no_progress,
                                              dssim_scale=a.dssim_scale)
                        record({"scene": spec, **r})
                        if a.match_default and strategy == "default":
                            m = train_and_measure(data, backend=backend, strategy="mcmc", iters=iters,
                                                  sh_degree=a.sh_degree, seed=a.seed, max_gaussians=r["gaussians"],
                                                  device=device, progress=not a.no_progress,
                                                  dssim_scale=a.dssim_scale)
                            record({"scene": spec, **m, "matched": r["gaussians"], "matched_budget": budget})
        del data
    report(a.out, f"SH degree {a.sh_degree}, seed {a.seed}, D-SSIM scale {a.dssim_scale:g}; held-out views every 8th",
           tables(rows), rows, device)
    return 0


def report(out: Path, setup: str, md: str, rows: list[dict], device: torch.device) -> None:
    """Print the tables under a header (date, setup, device, torch) and write results.json / results.md to ``out``."""
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    header = f"{time.strftime('%Y-%m-%d')}, {setup}, {gpu}, torch {torch.__version__}"
    print(f"\n{header}\n\n{md}")
    write_json(out / "results.json", {"setup": header, "rows": rows})
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(f"{header}\n\n{md}\n")


if __name__ == "__main__":
    sys.exit(main())
