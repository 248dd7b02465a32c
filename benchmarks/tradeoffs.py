"""The measured speed/accuracy trade: each knob of the renderer and of stylization, time against error.

Each rasterizer knob changed alone from the defaults (:func:`raster_cases`), timed and compared with the float64
``RasterSettings.exact()`` render of all Gaussians; ``--stylize``: Stage 2's key views and ``feature_scale``. Writes
``tradeoffs.md``, ``tradeoffs.json`` (``--append`` keeps other devices' results) and ``tradeoffs_pareto.png`` to
``--out``; docs/tradeoffs.md reads them.

    python benchmarks/tradeoffs.py --quick --out /tmp/tradeoffs          # < 1 min CPU smoke run
    python benchmarks/tradeoffs.py --devices cuda --n 500000 --size 1024 --stylize --append --out bench/tradeoffs
    python benchmarks/tradeoffs.py --scene runs/fern --size 504 --out bench/fern   # a real reconstruction

Mode ``budget RESULTS.json ... --scene fern8``: held-out PSNR against Gaussians and peak memory from
``benchmarks/train_step.py runs`` results (the MCMC budget sweep beside the other strategies).
"""
from __future__ import annotations

import datetime
import json
import math
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional

import torch

import ssgwarp
from ssgwarp import RasterSettings
from ssgwarp.core.cameras import Cameras, look_at
from ssgwarp.raster.scene import GaussianScene
from harness import ROOT, dispatch, machine, measure, parser, passes, pyplot, save_figure, sync, write_text


# ----------------------------------------------------------------------------- scene and cameras
def synthetic_scene(n: int, sh_degree: int = 3, seed: int = 0) -> GaussianScene:
    """N Gaussians in a ball of radius ~1.5 at the origin: scales log-uniform in [0.005, 0.08],
    opacities U(0.02, 1), colours U(0,1), higher SH bands N(0, 0.15) (visible view dependence)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.6
    log_s = torch.empty(n, 3).uniform_(math.log(0.005), math.log(0.08), generator=g)
    quats = torch.randn(n, 4, generator=g)
    op = torch.empty(n).uniform_(0.02, 1.0, generator=g)
    rgb = torch.rand(n, 3, generator=g)
    k = (sh_degree + 1) ** 2 - 1
    rest = torch.randn(n, k, 3, generator=g) * 0.15 if sh_degree > 0 else None
    from ssgwarp.raster.scene import rgb_to_sh_dc

    return GaussianScene(means, log_s, quats, torch.logit(op), rgb_to_sh_dc(rgb), rest, None, sh_degree)


def synthetic_cameras(views: int, width: int, height: int) -> Cameras:
    """``views`` cameras on a circle of radius 4 around the origin, 60 degree horizontal field of view."""
    ang = torch.linspace(0.0, 2.0 * math.pi, views + 1)[:-1].double()
    eyes = torch.stack([4.0 * torch.sin(ang), -0.8 * torch.ones_like(ang), -4.0 * torch.cos(ang)], -1)
    vms = look_at(eyes, torch.zeros(views, 3, dtype=torch.float64), up=(0.0, -1.0, 0.0)).float()
    f = 0.5 * width / math.tan(math.radians(30.0))
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Cameras(vms, K.expand(views, 3, 3).clone(), width, height)


def run_scene(run_dir: Path, views: int, side: int) -> tuple[GaussianScene, Cameras]:
    """A reconstruction's scene and ``views`` of its cameras (evenly spread), longer side ``side``."""
    from ssgwarp.formats.ply import read_ply

    scene = read_ply(run_dir / "scene.ply")
    cams = Cameras.load(run_dir / "cameras.json")
    ids = torch.linspace(0, len(cams) - 1, min(views, len(cams))).round().long().unique().tolist()
    cams = cams[ids]
    k = side / max(cams.width, cams.height)
    return scene, cams.rescaled(max(1, round(cams.width * k)), max(1, round(cams.height * k)))


# ----------------------------------------------------------------------------- cases
@dataclass
class Case:
    knob: str
    value: str
    dtype: torch.dtype = torch.float32
    settings: RasterSettings = field(default_factory=RasterSettings)
    tile_size: int = 16
    sh_degree: Optional[int] = None   # None: the scene's
    keep: float = 1.0
    default: bool = False


def raster_cases(scene_degree: int) -> list[Case]:
    d = RasterSettings()
    cases = [Case("default", "float32, gsplat rules, tile 16", default=True),
             Case("precision", "float64", dtype=torch.float64),
             Case("alpha_min", "0", settings=replace(d, alpha_min=0.0)),
             Case("t_min", "0", settings=replace(d, t_min=0.0)),
             Case("alpha_max", "1", settings=replace(d, alpha_max=1.0)),
             Case("fast_math", "off (IEEE exp/log/division/sqrt)", settings=replace(d, fast_math=False)),
             Case("covariance", "factor (cancellation-free)", settings=replace(d, covariance="factor")),
             Case("extent", "fixed 3.33 sigma", settings=replace(d, extent="fixed")),
             *(Case("tile_size", str(t), tile_size=t) for t in (8, 32))]
    cases += [Case("sh_degree", str(k), sh_degree=k) for k in range(scene_degree)]
    cases += [Case("gaussians", f"{int(p * 100)}%", keep=p) for p in (0.25, 0.5)]
    cases.append(Case("exact", "RasterSettings.exact(), float32", settings=RasterSettings.exact()))
    return cases


def _inputs(scene: GaussianScene, cams: Cameras, device, dtype, degree: int, keep_idx: Optional[torch.Tensor]):
    s = scene if keep_idx is None else scene.subset(keep_idx)
    s = s.to(device=device, dtype=dtype)
    coeffs = s.sh_coeffs[:, : (degree + 1) ** 2].contiguous()
    return [s.means, s.quats, s.scales, s.opacities, coeffs], cams.viewmats.to(device, dtype), cams.Ks.to(device, dtype)


def render_case(scene: GaussianScene, cams: Cameras, device: torch.device, case: Case, weight: torch.Tensor,
                keep_idx: Optional[torch.Tensor], repeats: int, time_it: bool = True) -> dict:
    """Time one case and return its image, alpha and positional gradient."""
    degree = scene.sh_degree if case.sh_degree is None else case.sh_degree
    params, vm, K = _inputs(scene, cams, device, case.dtype, degree, keep_idx)
    kw = dict(sh_degree=degree, tile_size=case.tile_size, settings=case.settings)
    fwd, fwd_bwd, leaves = passes(ssgwarp.rasterization, params, (vm, K, cams.width, cams.height),
                                  weight.to(device, case.dtype), **kw)

    out: dict[str, Any] = {}
    if time_it:
        out["fwd_ms"], out["fwd_bwd_ms"] = (measure(f, device, repeats)["median"] for f in (fwd, fwd_bwd))
    else:
        fwd_bwd()
    img, alpha, _ = fwd()
    out["image"] = img.detach().double()
    out["alpha"] = alpha.detach().double()
    out["grad_means"] = leaves[0].grad.detach().double()
    return out


def raster_study(scene: GaussianScene, cams: Cameras, device: torch.device, repeats: int,
                 progress: bool = True) -> list[dict]:
    from tqdm.auto import tqdm

    g = torch.Generator().manual_seed(1)
    weight = torch.rand(len(cams), cams.height, cams.width, 3, generator=g)
    order = torch.argsort(scene.opacities.detach(), descending=True)
    ref = render_case(scene, cams, device, Case("reference", "float64 exact", torch.float64, RasterSettings.exact()),
                      weight, None, repeats, time_it=False)
    rows = []
    for case in tqdm(raster_cases(scene.sh_degree), desc=f"raster knobs ({device.type})", disable=not progress):
        keep_idx = None
        if case.keep < 1.0:
            keep_idx = torch.sort(order[: max(1, int(round(case.keep * len(scene))))]).values
        r = render_case(scene, cams, device, case, weight, keep_idx, repeats)
        d = r["image"] - ref["image"]
        gref = ref["grad_means"] if keep_idx is None else ref["grad_means"][keep_idx.to(device)]
        gerr = float((r["grad_means"] - gref).norm() / gref.norm().clamp_min(1e-300))
        rows.append({"knob": case.knob, "value": case.value, "default": case.default, "fwd_ms": r["fwd_ms"],
                     "fwd_bwd_ms": r["fwd_bwd_ms"], "rmse": float(d.pow(2).mean().sqrt()), "max_abs": float(d.abs().max()),
                     "alpha_max_abs": float((r["alpha"] - ref["alpha"]).abs().max()), "grad_rel": gerr,
                     "gaussians": len(scene) if keep_idx is None else len(keep_idx)})
    return rows


# ----------------------------------------------------------------------------- stylization knobs
def _synthetic_run(folder: Path, scene: GaussianScene, cams: Cameras) -> Path:
    """A minimal reconstruction folder (scene.ply, cameras.json, data.json) for Stage 2."""
    from ssgwarp.core.fileio import write_json
    from ssgwarp.formats.ply import write_ply

    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "scene.ply", scene)
    cams.save(folder / "cameras.json")
    write_json(folder / "data.json", {"data_dir": None, "split": {"train": list(cams.names), "test": []},
                                      "background": [1.0, 1.0, 1.0], "format": "synthetic"})
    return folder


def _procedural_style(path: Path, size: int = 64) -> Path:
    """Diagonal stripes of three colours (stands in when no --style is given)."""
    from ssgwarp.core.fileio import write_image

    y, x = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    band = ((x + y) // 6) % 3
    pal = torch.tensor([[0.95, 0.75, 0.1], [0.1, 0.3, 0.8], [0.85, 0.15, 0.2]])
    write_image(path, pal[band])
    return path


def stylize_study(run_dir: Path, style: Path, out: Path, device: torch.device, iters: int,
                  keyviews=(2, 4, 8), scales=(0.25, 0.5, 1.0), max_side: int = 256) -> list[dict]:
    from ssgwarp.stylization.stage2 import Stage2Config
    from ssgwarp.stylization.stylize import StylizeOptions, stylize_run

    rows = []
    jobs = [("key views", str(k), Stage2Config(mode="ist", iters=iters), StylizeOptions(
        keyviews=k, path_frames=0, max_side=max_side)) for k in keyviews]
    jobs += [("feature resolution", f"{s:g}", Stage2Config(mode="global", iters=iters, feature_scale=s),
              StylizeOptions(path_frames=0, max_side=max_side)) for s in scales]
    # warm-up (kernel compilation, extractor set-up), not recorded: the first timed job would pay for it
    try:
        stylize_run(run_dir, style, out / "stylize_runs" / "warmup", stage2=Stage2Config(mode="global", iters=1),
                    opts=StylizeOptions(path_frames=0, max_side=max_side), device=device, force=True, progress=False)
    except Exception:
        pass
    for knob, value, s2, opts in jobs:
        dst = out / "stylize_runs" / f"{knob.replace(' ', '_')}_{value}"
        try:
            sync(device)
            t0 = time.perf_counter()
            m = stylize_run(run_dir, style, dst, stage2=s2, opts=opts, device=device, force=True, progress=False)
            total = time.perf_counter() - t0
        except Exception as e:  # report and go on: the study must finish
            rows.append({"knob": knob, "value": value, "skipped": f"{type(e).__name__}: {e}"})
            continue
        secs = m.get("seconds", {})
        rows.append({"knob": knob, "value": value, "mode": s2.mode, "iters": iters, "stage2_s": secs.get("stage2", total),
                     "total_s": total, "stage1_ran": bool((m.get("stage1") or {}).get("ran")),
                     **{k: m.get(k) for k in ("gram_style_loss", "content_loss", "gram_style_loss_original",
                                              "extractor", "matching")}})
    return rows


# ----------------------------------------------------------------------------- report


def _f(x: Any, digits: int = 3) -> str:
    if not isinstance(x, float):
        return "-" if x is None else str(x)
    return "0" if x == 0.0 else f"{x:.{digits}g}" if 1e-3 <= abs(x) < 1e5 else f"{x:.2e}"


def markdown(results: dict) -> str:
    lines = ["# Speed / accuracy trade-offs (measured)", ""]
    for key, res in results["devices"].items():
        meta = res["meta"]
        lines += [f"## {key}: {meta['device_name']}", "",
                  f"{meta['date']}; torch {meta['torch']}, warp {meta['warp']}; scene: {meta['scene']}; "
                  f"{meta['views']} view(s) {meta['width']}x{meta['height']}; median of {meta['repeats']} runs.",
                  "Reference: float64, `RasterSettings.exact()`, all Gaussians, full SH degree. "
                  "Errors on colours in [0, 1]; grad = relative L2 error of dL/dmeans.", "",
                  "| knob | value | fwd ms | fwd+bwd ms | speed-up (fwd) | image RMSE | max abs err | grad rel err |",
                  "|---|---|---|---|---|---|---|---|"]
        base = next((r for r in res["raster"] if r.get("default")), None)
        for r in res["raster"]:
            sp = base["fwd_ms"] / r["fwd_ms"] if base and r["fwd_ms"] > 0 else None
            lines.append(f"| {r['knob']} | {r['value']} | {_f(r['fwd_ms'])} | {_f(r['fwd_bwd_ms'])} | "
                         f"{_f(sp)}x | {_f(r['rmse'])} | {_f(r['max_abs'])} | {_f(r['grad_rel'])} |")
        if res.get("stylize"):
            lines += ["", "Stylization knobs (Stage 2, "
                      f"{res['stylize'][0].get('iters', '-')} iterations):", "",
                      "| knob | value | mode | Stage 2 s | total s | Gram style loss | content loss | note |",
                      "|---|---|---|---|---|---|---|---|"]
            for r in res["stylize"]:
                if "skipped" in r:
                    lines.append(f"| {r['knob']} | {r['value']} | - | - | - | - | - | skipped: {r['skipped']} |")
                    continue
                note = r.get("extractor") or ""
                if r["knob"] == "key views" and not r.get("stage1_ran"):
                    note += "; Stage 1 did not run (no diffusion weights): key views fall back to global matching"
                lines.append(f"| {r['knob']} | {r['value']} | {r['mode']} | {_f(r['stage2_s'])} | {_f(r['total_s'])} | "
                             f"{_f(r['gram_style_loss'])} | {_f(r['content_loss'])} | {note} |")
        lines.append("")
    lines += ["![time vs error](tradeoffs_pareto.png)", ""]
    return "\n".join(lines)


def _short(row: dict) -> str:
    """Plot label of a row."""
    if row["knob"] in ("default", "exact"):
        return row["knob"]
    first = row["value"].split()[0]
    return f"{row['knob']}={first}" if row["knob"] in ("alpha_min", "t_min", "alpha_max", "sh_degree", "tile_size") \
        else first


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and error (sorted by time)."""
    idx = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in idx:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def pareto_plot(results: dict, path: Path) -> Path:
    plt = pyplot()

    keys = list(results["devices"])
    fig, axes = plt.subplots(1, len(keys), figsize=(6.5 * len(keys), 5), squeeze=False)
    for ax, key in zip(axes[0], keys):
        res = results["devices"][key]
        rows = res["raster"]
        pts = [(r["fwd_bwd_ms"], max(r["rmse"], 1e-12)) for r in rows]
        knobs = sorted({r["knob"] for r in rows})
        cmap = plt.get_cmap("tab10")
        for j, k in enumerate(knobs):
            sel = [i for i, r in enumerate(rows) if r["knob"] == k]
            ax.scatter([pts[i][0] for i in sel], [pts[i][1] for i in sel], color=cmap(j % 10), label=k, s=36,
                       marker="*" if k == "default" else "o", zorder=3)
            for i in sel:
                ax.annotate(_short(rows[i]), pts[i], fontsize=7, xytext=(3, 3), textcoords="offset points")
        front = pareto_front(pts)
        ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "k--", lw=1, label="Pareto front", zorder=2)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("forward + backward time (ms)")
        ax.set_ylabel("image RMSE vs float64 exact render")
        meta = res["meta"]
        ax.set_title(f"{key}: {meta['device_name'][:48]}\n{meta['scene']}, {meta['width']}x{meta['height']}, "
                     f"{meta['date'][:10]}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    save_figure(fig, path, format="png", dpi=120)
    return path


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    p = parser("tradeoffs.py", __doc__)
    p.add_argument("--out", type=Path, default=Path("tradeoffs"), help="output folder")
    p.add_argument("--quick", action="store_true", help="tiny sizes: a CPU smoke run in under a minute")
    p.add_argument("--devices", default=None, help="cpu, cuda or cpu,cuda (default: cpu, and cuda when present)")
    p.add_argument("--n", type=int, default=20000, help="Gaussians of the synthetic scene")
    p.add_argument("--sh-degree", type=int, default=3, help="SH degree of the synthetic scene")
    p.add_argument("--size", type=int, default=256, help="longer image side")
    p.add_argument("--views", type=int, default=1, help="cameras rendered per call")
    p.add_argument("--scene", type=Path, default=None, help="a reconstruction run folder instead of the synthetic scene")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--stylize", action="store_true", help="also the stylization knobs (Stage 2 runs)")
    p.add_argument("--style", type=Path, default=None, help="style image of the stylization knobs")
    p.add_argument("--stylize-iters", type=int, default=100, help="Stage 2 iterations per stylization run")
    p.add_argument("--append", action="store_true", help="keep other devices' results already in --out")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.quick:
        args.n, args.size, args.repeats, args.views = min(args.n, 400), min(args.size, 48), min(args.repeats, 2), 1
        args.stylize, args.stylize_iters = True, min(args.stylize_iters, 2)
    devs = [d.strip() for d in (args.devices or ("cpu" if args.quick else "cpu,cuda")).split(",") if d.strip()]
    if "cuda" in devs and not torch.cuda.is_available():
        if args.devices:
            print("tradeoffs: CUDA is not available here; skipping cuda", file=sys.stderr)
        devs.remove("cuda")
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)

    if args.scene is not None:
        scene, cams = run_scene(args.scene, args.views, args.size)
        scene_desc = f"{args.scene.name} ({len(scene)} Gaussians, SH {scene.sh_degree})"
        run_dir = args.scene
    else:
        scene = synthetic_scene(args.n, args.sh_degree, args.seed)
        cams = synthetic_cameras(args.views, args.size, max(8, round(args.size * 3 / 4)))
        scene_desc = f"synthetic ({args.n} Gaussians, SH {args.sh_degree})"
        run_dir = None

    json_path = args.out / "tradeoffs.json"
    results: dict = {"devices": {}}
    if args.append and json_path.is_file():
        results = json.loads(json_path.read_text())
    import warp

    for d in devs:
        device = torch.device(d)
        t0 = time.perf_counter()
        rows = raster_study(scene, cams, device, args.repeats)
        meta = {"device_name": machine(device), "date": datetime.datetime.now().isoformat(timespec="seconds"),
                "torch": torch.__version__, "warp": warp.__version__, "scene": scene_desc, "views": len(cams),
                "width": cams.width, "height": cams.height, "repeats": args.repeats, "quick": args.quick}
        entry = {"meta": meta, "raster": rows}
        if args.stylize:
            style = args.style or _procedural_style(args.out / "style_stripes.png")
            if run_dir is None:
                scam = synthetic_cameras(8 if not args.quick else 4, cams.width, cams.height)
                base = synthetic_scene(args.n, 0, args.seed)
                run_dir = _synthetic_run(args.out / "synthetic_run", base, scam)
            entry["stylize"] = stylize_study(run_dir, style, args.out, device, args.stylize_iters,
                                             keyviews=(2, 4) if args.quick else (2, 4, 8),
                                             scales=(0.5, 1.0) if args.quick else (0.25, 0.5, 1.0),
                                             max_side=max(cams.width, cams.height))
        meta["seconds"] = round(time.perf_counter() - t0, 1)
        results["devices"][d] = entry
        write_text(json_path, json.dumps(results, indent=1))

    write_text(args.out / "tradeoffs.md", markdown(results))
    pareto_plot(results, args.out / "tradeoffs_pareto.png")
    print(markdown(results))
    print(f"wrote {args.out / 'tradeoffs.md'}, {json_path}, {args.out / 'tradeoffs_pareto.png'}")
    return 0



# ----------------------------------------------------------------------------- budget: PSNR against size
BUDGET_DOC = """Held-out PSNR against Gaussians and peak GPU memory from ``train_step.py runs`` results (a PNG).

The rows of ``--scene`` at ``--iters`` of every file: a line for the MCMC budget sweep, a marker per other run.

    python benchmarks/tradeoffs.py budget sweep/results.json f8ours/results.json f8gs/results.json \\
        dssim/results.json --scene fern8 --iters 7000 --out docs/tradeoffs_budget.png
"""


def load_rows(paths: list[Path], scene: str, iters: int) -> list[dict]:
    """The rows of ``scene`` at ``iters`` from every file, in file order."""
    rows = []
    for p in paths:
        data = json.loads(Path(p).read_text())
        rows += [r for r in data.get("rows", []) if r.get("scene") == scene and r.get("iters") == iters]
    if not rows:
        raise SystemExit(f"no rows of scene {scene!r} at {iters} steps in {', '.join(map(str, paths))}")
    return rows


def label(r: dict) -> str:
    """A legend entry for a run that is not part of the budget sweep."""
    parts = [r["strategy"]]
    if r.get("matched"):
        parts.append(f"budget = default's count ({r['max_gaussians']:,})")
    if r.get("backend", "ssgwarp") != "ssgwarp":
        parts.append(f"{r['backend']} rasterizer")
    if r.get("dssim_scale", 1.0) != 1.0:
        parts.append(f"D-SSIM x{r['dssim_scale']:g}")
    if r.get("recipe"):   # (train_step.py runs --recipe: e.g. contribution pruning)
        parts.append(r["recipe"])
    return ", ".join(parts)


def _by_point(rows: list[dict], key: str) -> dict:
    """Rows that ended alike (same Gaussian count, PSNR to 0.1 dB) grouped under their first row's point."""
    out: dict = {}
    for r in rows:
        out.setdefault((r["gaussians"], round(r["psnr"], 1)), []).append(r)
    return {(same[0][key], same[0]["psnr"]): same for same in out.values()}


def plot(rows: list[dict], out: Path, title: str) -> Path:
    plt = pyplot()

    sweep = sorted((r for r in rows if r["strategy"] == "mcmc" and not r.get("matched")),
                   key=lambda r: r["max_gaussians"])
    others = [r for r in rows if r not in sweep]
    panels = [("gaussians", "Gaussians at the end")]
    if all(math.isfinite(r.get("peak_mib") or math.nan) for r in rows):   # (CPU runs have no GPU memory)
        panels.append(("peak_mib", "peak GPU memory (MiB)"))
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 5.4), squeeze=False)
    axes = axes[0]
    cmap = plt.get_cmap("tab10")
    for ax, (key, xlabel) in zip(axes, panels):
        if sweep:
            ax.plot([r[key] for r in sweep], [r["psnr"] for r in sweep], "o-", color="k", label="mcmc, budget sweep",
                    zorder=3)
            for pt, same in _by_point(sweep, key).items():  # budgets that ended at one count share a label
                text = " / ".join(f"{r['max_gaussians'] // 1000}k" for r in same) + " budget, " + \
                    " / ".join(f"{r['seconds']:.0f}" for r in same) + " s"
                ax.annotate(text, pt, fontsize=7, xytext=(4, -10), textcoords="offset points")
        for j, r in enumerate(others):
            ax.scatter([r[key]], [r["psnr"]], color=cmap(j % 10), marker="s", s=40, label=label(r), zorder=3)
            ax.annotate(f"{r['seconds']:.0f} s", (r[key], r["psnr"]), fontsize=7, xytext=(4, 4),
                        textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("held-out PSNR (dB)")
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=4, frameon=False)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    save_figure(fig, out, format="png", dpi=110)
    return out


def budget_main(argv=None) -> int:
    ap = parser("tradeoffs.py budget", BUDGET_DOC)
    ap.add_argument("results", nargs="+", type=Path, help="results.json files of benchmarks/train_step.py runs")
    ap.add_argument("--scene", default="fern8")
    ap.add_argument("--iters", type=int, default=7000)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "tradeoffs_budget.png")
    a = ap.parse_args(argv)
    rows = load_rows(a.results, a.scene, a.iters)
    title = f"{a.scene}, {a.iters} steps: held-out PSNR against size (times in the labels)"
    print(plot(rows, a.out, title))
    return 0


if __name__ == "__main__":
    sys.exit(dispatch({"budget": budget_main}, main))
