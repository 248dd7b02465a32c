"""Stylization across styles, and the probes behind docs/stylize.md's tables (no Stage 1 weights needed).

For a scene (fern ``images_8``, the demo scene, or a grouped run folder) and every style image, ``ssgwarp stylize``
and ``ssgwarp evaluate``: one row per style (the columns: docs/stylize.md). Finished styles are kept
(``OUT/<scene>/<style>/result.json``), so shards and interrupted runs add up; ``--report`` tables what is finished.
Writes ``table.md``, ``results.json`` and ``styles_sheet.jpg`` under ``OUT/<scene>``.

    python benchmarks/stylize.py --scene fern --shard 0/3      # a third of the styles (10-minute slots)
    python benchmarks/stylize.py --scene demo --demo-size small --styles-subset candy,udnie \
        --iters 10 --path-frames 6 --out /tmp/ss                       # CPU check (~2 min on 2 cores)
    python benchmarks/stylize.py --scene fern --configs FILE --timeout 420  # 'TAG: FLAGS' lines, all at once

Modes, each with its own ``--help``: ``captures``, ``stage2``, ``probe``, ``bound`` (docs/benchmarks.md).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Optional

import torch

from harness import ROOT, capture_folder, data_root, dispatch, knobs, machine, parser, pyplot, save_figure, style_paths
from harness import write_text
from harness import table as md_table

from ssgwarp.cli import resolve_device
from ssgwarp.core.fileio import read_image, read_json, write_json
from ssgwarp.core.imaging import fit_style
from ssgwarp.errors import InputError
from ssgwarp.evaluation.features import EXTRACTOR_KINDS
from ssgwarp.services.runs import Run, load_run
from ssgwarp.stylization.spread import pixel_size, probe_scene   # the probe behind --paint-strength auto

DATA = data_root()
STAGE2_DOC = """Seconds per stage of `ssgwarp stylize` on fern images_4, per Stage 2 mode (table and OUT/benchmark.json).

Stage 1 runs when its weights are configured. ``--synthetic N``: a stand-in scene of N Gaussians around fern's COLMAP
points (8 k-means groups); ``--random-stage1 sd15``: Stage 1 on random SD1.5-sized models (real compute).

    python benchmarks/stylize.py stage2 --run runs/fern4 --modes ist,global --iters 600
    python benchmarks/stylize.py stage2 --synthetic 300000 --random-stage1 sd15
"""
PROBE_DOC = """What texture costs in the consistency metric when the texture is consistent by construction.

Paints the Gaussians with a grey pattern fixed in 3-D (``spread.probe_scene``) and scores ``ssgwarp evaluate``'s path
views as it does (docs/stylize.md, "What limits texture"). ``--truth`` (an ``ssgwarp demo`` run, OUT/scene): also
the procedural scene behind it.

    python benchmarks/stylize.py probe --run RUN --style ../shared/data/styles/candy.jpg
    python benchmarks/stylize.py probe --run ssgwarp-demo/scene --truth --periods 2,8,32
"""
BOUND_DOC = """How far Stage 2's weight-free style loss takes the texture distance with nothing holding it back.

Per style: Stage 2's colour transfer, then each path view's scene pixels optimised freely with the style loss
alone, scored after each of ``--steps`` steps per view (docs/stylize.md, "How far the loss itself goes").

    python benchmarks/stylize.py bound --run RUN --styles candy,mosaic --steps 10,100
"""

CAPTURES_DOC = """The 25-style table on each shared capture, then one summary row per capture (OUT/captures<_TAG>.md).

Each capture is reconstructed with ``ssgwarp reconstruct --groups auto`` once (OUT/recon/<capture>_w<WIDTH>_i<ITERS>,
reused; its tables in OUT/<capture>_w<WIDTH>_i<ITERS>[_TAG]), then the main mode runs on it with every other flag given (``--tag``, ``--paint``, Stage 2 options, ...).

    python benchmarks/stylize.py captures --out out/s62 --recon-iters 7000
    python benchmarks/stylize.py captures --out out/s62 --tag paint --paint
    python benchmarks/stylize.py captures --width 128 --recon-iters 600 --styles-subset candy,mosaic --iters 60 \
        --path-frames 8 --out /tmp/s62                                    # CPU-sized
"""
SHEET_STYLES = ("brushstrokes", "candy", "la_muse", "mosaic", "the_resevoir_at_poitiers", "sketch", "udnie")


def prepare_scene(scene: str, out: Path, device, fern_iters: int, progress: bool, demo_size: str = "default",
                  fern: Path = DATA / "llff_fern") -> Path:
    """A grouped reconstruction run folder for ``scene`` (built once, reused)."""
    if scene not in ("fern", "demo"):
        run = Path(scene)
        if not (run / "scene.ply").is_file():
            raise SystemExit(f"--scene {scene}: not a run folder (no scene.ply); use fern, demo or a run folder")
        return run
    if scene == "demo":
        from ssgwarp.demo import run_demo

        demo = out / f"demo_build_{demo_size}"
        if not (demo / "scene" / "groups" / "classifier.pt").is_file():
            run_demo(demo, demo_size, device=device, force=True, progress=progress)
        return demo / "scene"
    from ssgwarp.grouping.stage import group_scene
    from ssgwarp.reconstruction.reconstruct import ReconstructConfig, reconstruct

    run = out / "fern_images_8"
    if not (run / "scene.ply").is_file():
        reconstruct(fern, run, ReconstructConfig(images="images_8", iters=fern_iters), device=device,
                    progress=progress, force=True)
    if not (run / "groups" / "classifier.pt").is_file():
        group_scene(run, masks=None, device=device, progress=progress, force=True)     # mask-free: no SAM weights
    return run


def stage2_config(args, **over):
    """Stage 2's configuration: the defaults, then every Stage 2 option given (the parser's "Stage 2" group names
    its fields), then ``over``."""
    import dataclasses

    from ssgwarp.stylization.stage2 import Stage2Config

    kw = {f.name: getattr(args, f.name) for f in dataclasses.fields(Stage2Config)
          if getattr(args, f.name, None) is not None}
    kw.update(over)
    return Stage2Config(**kw)


def run_style(run: Path, style: Path, out: Path, cfg, device, extractor: str, eval_opts, progress: bool) -> dict:
    """Stylize ``run`` with ``style`` into ``out`` and evaluate it; returns the result row (cached in out)."""
    from ssgwarp.evaluation.evaluate import evaluate_run
    from ssgwarp.stylization.stylize import StylizeOptions, stylize_run

    res_file = out / "result.json"
    if res_file.is_file():
        return read_json(res_file)
    t0 = time.perf_counter()
    m = stylize_run(run, style, out, stage2=cfg, opts=StylizeOptions(path_frames=0, sheet_views=2,
                                                                        extractor=extractor),
                    device=device, force=True, progress=progress)
    seconds = time.perf_counter() - t0
    ev = evaluate_run(out, eval_opts, device, write=True, progress=progress)
    sc = ev["style_content"]
    rep = ev["consistency"]["reprojection"]
    row = {"style": style.stem, "color_before": sc["style_distance_color_original"],
           "color_after": sc["style_distance_color"], "texture_before": sc["style_distance_texture_original"],
           "texture_after": sc["style_distance_texture"], "gram_before": m["gram_style_loss_original"],
           "gram_after": m["gram_style_loss"], "content": sc.get("content_loss", m["content_loss"]),
           "short": rep["short"]["rmse"], "long": rep["long"]["rmse"],
           "stylize_seconds": seconds, "stage2_seconds": m["seconds"]["stage2"], "extractor": m["extractor"],
           "config": m["config"], "views_scored": ev["views_scored"], "device": m["device"],
           "matching": m["matching"], "strength": m.get("strength"),
           "empty_spread": sc.get("empty_spread"), "empty_spread_original": sc.get("empty_spread_original")}
    write_json(res_file, row)
    return row


def add_halves(rows: list[dict], styles: list[Path], run: Path, results: Path) -> None:
    """Each row's ``color_half`` / ``texture_half``: the distances of the style image's own halves to the whole
    at the scored views' size (:meth:`StyleDistance.halves`), a reference for how close a render can get;
    computed once and kept in the style's ``result.json`` (in ``results``, ``OUT/<scene>/styles``)."""
    from ssgwarp.core.cameras import Cameras
    from ssgwarp.evaluation.style_distance import StyleDistance

    cams = Cameras.load(run / "cameras.json")
    by_name = {s.stem: s for s in styles}
    for r in rows:
        if r.get("texture_half") is None and r["style"] in by_name:
            style = torch.as_tensor(read_image(by_name[r["style"]], 3)).float()
            h = StyleDistance(style).halves(cams.height, cams.width)
            r["color_half"], r["texture_half"] = h["color"], h["texture"]
            if (results / r["style"] / "result.json").is_file():
                write_json(results / r["style"] / "result.json", r)


def source_consistency(run: Path, out: Path, device, eval_opts, progress: bool = True) -> dict:
    from ssgwarp.evaluation.evaluate import evaluate_run

    f = out / "source_consistency.json"
    if f.is_file():
        return read_json(f)
    ev = evaluate_run(run, eval_opts, device, write=False, progress=progress)
    rep = ev["consistency"]["reprojection"]
    d = {"short": rep["short"]["rmse"], "long": rep["long"]["rmse"], "views_scored": ev["views_scored"]}
    write_json(f, d)
    return d


def _pct(before: Optional[float], after: Optional[float]) -> str:
    return "-" if before is None or after is None or before == 0 else f"{100 * (after - before) / before:+.0f}%"


def table(rows: list[dict], src: dict, title: str) -> str:
    lines = [title, "",
             "| style | colour before | colour after | Δ | half of the style | texture before | texture after | Δ | "
             "half of the style | Gram before | Gram after | content loss | short RMSE (x src) | long RMSE (x src) | "
             "Stage 2 s | stylize s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['style']} | {r['color_before']:.2f} | {r['color_after']:.2f} | "
            f"{_pct(r['color_before'], r['color_after'])} | {_pct(r['color_before'], r.get('color_half'))} | "
            f"{r['texture_before']:.3f} | {r['texture_after']:.3f} | {_pct(r['texture_before'], r['texture_after'])} | "
            f"{_pct(r['texture_before'], r.get('texture_half'))} | {r['gram_before']:.3g} | {r['gram_after']:.3g} | "
            f"{r.get('content', float('nan')):.3g} | "
            f"{r['short']:.4f} ({r['short'] / src['short']:.2f}) | {r['long']:.4f} ({r['long'] / src['long']:.2f}) | "
            f"{r['stage2_seconds']:.1f} | {r['stylize_seconds']:.1f} |")
    if rows:
        n = len(rows)
        dc = sum(1 - r["color_after"] / r["color_before"] for r in rows) / n
        dt = sum(1 - r["texture_after"] / r["texture_before"] for r in rows) / n
        worse = [r["style"] for r in rows if r["color_after"] >= r["color_before"] or r["texture_after"] >= r["texture_before"]]
        ms = max(r["short"] / src["short"] for r in rows)
        ml = max(r["long"] / src["long"] for r in rows)
        lines += ["", f"Unstylized scene: short-range RMSE {src['short']:.4f}, long-range {src['long']:.4f} "
                      f"({src['views_scored']}).",
                  f"Mean reduction over {n} styles: colour {100 * dc:.1f}%, texture {100 * dt:.1f}%.",
                  f"Styles not closer on both terms: {', '.join(worse) if worse else 'none'}.",
                  f"Worst consistency ratio: short {ms:.2f}x, long {ml:.2f}x."]
        half = [r for r in rows if r.get("texture_half") is not None]
        if half:
            hc = sum(1 - r["color_half"] / r["color_before"] for r in half) / len(half)
            ht = sum(1 - r["texture_half"] / r["texture_before"] for r in half) / len(half)
            lines.append(f"Half of each style image against the whole (the same measure at the views' scale): colour "
                         f"{100 * hc:.1f}%, texture {100 * ht:.1f}% below the unstylized distance; the stylized scene "
                         f"is closer than that on {sum(r['color_after'] <= r['color_half'] for r in half)} (colour) and "
                         f"{sum(r['texture_after'] <= r['texture_half'] for r in half)} (texture) of {len(half)} styles.")
        empty = [r for r in rows if r.get("empty_spread") is not None]
        if empty:
            w = max(empty, key=lambda r: r["empty_spread"])
            lines.append(f"Floaters (RMS colour spread over the pixels the unstylized scene leaves empty): worst "
                         f"{w['empty_spread']:.4f} ({w['style']}), unstylized {w['empty_spread_original']:.4f}.")
    return "\n".join(lines) + "\n"


def sheet(path: Path, run: Path, results_dir: Path, styles: list[Path], device) -> Optional[Path]:
    """Rows: style image | original | stylized (one view), for the styles that finished; a small JPEG."""
    plt = pyplot()

    from ssgwarp.formats.ply import read_ply
    from ssgwarp.stylization.stage2 import render_rgb

    done = [s for s in styles if (results_dir / s.stem / "scene.ply").is_file()]
    if not done:
        return None
    src, data = load_run(run, device, load_images=False)
    cam = data.cameras[[list(data.test_ids or data.train_ids)[0]]].to(device)
    bg = torch.tensor(data.background[:3], dtype=src.dtype, device=device)
    with torch.no_grad():
        orig = render_rgb(src, cam, bg)[0].clamp(0, 1).cpu()
    h, w = orig.shape[:2]
    fig, axes = plt.subplots(len(done), 3, figsize=(3 * 2.4, len(done) * 2.4 * h / w + 0.3), dpi=90, squeeze=False)
    for i, s in enumerate(done):
        bg_s = torch.tensor(Run.open(results_dir / s.stem).background(data.background), dtype=src.dtype, device=device)
        with torch.no_grad():
            styl = render_rgb(read_ply(results_dir / s.stem / "scene.ply", device=device), cam, bg_s)[0].clamp(0, 1).cpu()
        for j, (img, label) in enumerate([(torch.from_numpy(read_image(s, 3)), s.stem), (orig, "original"),
                                          (styl, "stylized")]):
            axes[i, j].imshow(img.numpy())
            axes[i, j].set_title(label, fontsize=7)
            axes[i, j].axis("off")
    fig.tight_layout()
    save_figure(fig, path, format="jpg", pil_kwargs={"quality": 82})
    return path


def scene_name(scene: str) -> str:
    """The results' folder prefix for ``--scene``: ``fern``, ``demo`` or the run folder's name."""
    return scene if scene in ("fern", "demo") else Path(scene).name


def parse_configs(path: Path) -> list[tuple[str, list[str]]]:
    """``[(tag, flags)]`` from a file of ``TAG: FLAGS`` lines (blank lines and ``#`` comments skipped)."""
    import shlex

    out = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tag, sep, flags = line.partition(":")
        tag = tag.strip()
        if not sep or not tag or not all(c.isalnum() or c in "._-" for c in tag):
            raise SystemExit(f"{path}:{n}: expected 'TAG: FLAGS' with a TAG of letters, digits, '.', '_', '-'")
        out.append((tag, shlex.split(flags)))
    if len({t for t, _ in out}) != len(out):
        raise SystemExit(f"{path}: a TAG appears twice")
    if not out:
        raise SystemExit(f"{path}: no configuration")
    return out


def run_configs(args, styles, device, progress: bool) -> int:
    """``--configs``: build the scene once, then every configuration as its own process, all at once."""
    import subprocess

    configs = parse_configs(args.configs)
    t0, failed = time.monotonic(), 0  # --timeout counts from here: building the scene is part of it
    prepare_scene(args.scene, args.out, device, args.fern_iters, progress, args.demo_size, args.fern)
    name = scene_name(args.scene)
    shared = [sys.executable, str(Path(__file__).resolve()), "--scene", args.scene, "--out", str(args.out),
              "--device", str(device), "--styles", str(args.styles), "--fern", str(args.fern), "--fern-iters",
              str(args.fern_iters), "--demo-size", args.demo_size, "--path-frames", str(args.path_frames), "--quiet"]
    if args.styles_subset:
        shared += ["--styles-subset", args.styles_subset]
    procs = []
    for tag, flags in configs:
        log = args.out / f"{name}_{tag}.log"
        procs.append((tag, log, subprocess.Popen(shared + ["--tag", tag, *flags], stdout=log.open("w"),
                                                 stderr=subprocess.STDOUT)))
    print(f"{len(procs)} configurations running on {device} (logs {args.out}/{name}_<TAG>.log)", flush=True)
    for tag, log, proc in procs:
        try:
            left = None if args.timeout is None else max(1.0, args.timeout - (time.monotonic() - t0))
            rc = proc.wait(timeout=left)
        except subprocess.TimeoutExpired:
            proc.terminate()
            rc = proc.wait()
        done = len(list((args.out / f"{name}_{tag}" / "styles").glob("*/result.json")))
        summary = [ln for ln in log.read_text(errors="replace").splitlines()
                   if ln.startswith(("Mean reduction", "Worst consistency", "Styles not closer"))]
        failed += rc not in (0, -15)
        print(f"== {tag} (exit {rc}): {done}/{len(styles)} styles finished" +
              "".join(f"\n   {ln}" for ln in summary), flush=True)
    return 1 if failed else 0


def styles_main(argv=None) -> int:
    p = parser("stylize.py", __doc__)
    add = p.add_argument
    add("--scene", default="demo", help="fern, demo, or a (grouped) reconstruction run folder")
    add("--styles", type=Path, default=DATA / "styles", help="folder of style images")
    add("--styles-subset", default=None, help="comma-separated style names (file stems)")
    add("--shard", default=None, help="i/n: run the i-th of n interleaved slices of the styles")
    add("--out", type=Path, default=ROOT / "out" / "stylize")
    add("--device", default="auto")
    add("--fern-iters", type=int, default=7000, help="reconstruction steps of fern images_8")
    add("--fern", type=Path, default=DATA / "llff_fern", help="the LLFF fern capture (--scene fern)")
    add("--demo-size", default="default", choices=("small", "default"), help="--scene demo's size (small: a CPU check)")
    add("--extractor", default="auto", choices=EXTRACTOR_KINDS)
    add("--path-frames", type=int, default=30, help="novel path views scored by evaluate")
    add("--report", action="store_true", help="print the table of finished styles only")
    add("--configs", type=Path, default=None, help="a file of 'TAG: FLAGS' lines (# comments): the scene is built "
        "once, then each runs as its own process (--tag TAG FLAGS), all at once; logs in OUT/<scene>_<TAG>.log")
    add("--timeout", type=float, default=None, help="with --configs: stop every configuration this many seconds "
        "after the command started (finished styles are kept)")
    add("--tag", default="", help="results in OUT/<scene>_<tag> (the scene is built once in OUT and shared)")
    add("--quiet", action="store_true")
    from ssgwarp.commands.stylize import PAINT, style_scale_arg
    g = p.add_argument_group("Stage 2 (default: the CLI defaults; docs/stylize.md)")
    for name, kind in (("iters", int), ("lr", float), ("content-weight", float), ("tv-weight", float),
                       ("blend-weight", float), ("color-transfer", str), ("color-max-gain", float),
                       ("color-detail", ("keep", "off")), ("sh-rest", str), ("background", ("transfer", "keep")),
                       ("mode", ("ist", "global")), ("densify", float), ("densify-views", int),
                       ("hold-empty", float), ("consistency-weight", float), ("consistency-neighbours", int),
                       ("consistency-budget", float), ("style-scale", style_scale_arg), ("paint-strength", style_scale_arg)):
        g.add_argument(f"--{name}", default=None, **({"choices": kind} if isinstance(kind, tuple) else {"type": kind}))
    g.add_argument("--region-check", action="store_const", const=True, default=None, help="ssgwarp stylize's --region-check")
    from ssgwarp.core.presets import add_preset
    add_preset(p, "--paint", PAINT, "ssgwarp stylize's painting preset: {values} (options given explicitly win)")
    args = p.parse_args(argv)

    from ssgwarp.evaluation.evaluate import EvalOptions

    device = resolve_device(args.device)
    torch.manual_seed(0)
    progress = not args.quiet
    styles = style_paths(args.styles_subset or "", args.styles)   # (an InputError: one line, harness.dispatch)
    if args.configs is not None:
        return run_configs(args, styles, device, progress)
    name = scene_name(args.scene)
    out = args.out / (f"{name}_{args.tag}" if args.tag else name)
    out.mkdir(parents=True, exist_ok=True)
    run = prepare_scene(args.scene, args.out, device, args.fern_iters, progress, args.demo_size, args.fern)
    eval_opts = EvalOptions(path_frames=args.path_frames, max_pairs=16, save_pairs=0)
    src = source_consistency(run, out, device, eval_opts, progress)
    dev = machine(device)

    todo = styles
    if args.shard:
        i, n = (int(x) for x in args.shard.split("/"))
        todo = styles[i::n]
    cfg = stage2_config(args)
    rows = []
    for s in styles:
        if s in todo and not args.report:
            rows.append(run_style(run, s, out / "styles" / s.stem, cfg, device, args.extractor, eval_opts, progress))
        elif (out / "styles" / s.stem / "result.json").is_file():
            rows.append(json.loads((out / "styles" / s.stem / "result.json").read_text()))
    add_halves(rows, styles, run, out / "styles")
    title = (f"`ssgwarp stylize` (weight-free: no Stage 1, {rows[0]['extractor'] if rows else '-'}) on {name}, "
             f"{dev}, {time.strftime('%Y-%m-%d')}; scored by `ssgwarp evaluate` on {src['views_scored']}. "
             f"Distances: sliced Wasserstein to the style (colour in Lab, texture of a derivative-of-Gaussian "
             f"filter bank), on the scene's pixels; lower is closer.")
    text = table(rows, src, title)
    write_text(out / "table.md", text)
    write_json(out / "results.json", {"device": dev, "source": src, "rows": rows})
    sheet(out / "styles_sheet.jpg", run, out / "styles", [s for s in styles if s.stem in SHEET_STYLES], device)
    print(text)
    print(f"{len(rows)}/{len(styles)} styles finished; table {out / 'table.md'}, sheet {out / 'styles_sheet.jpg'}")
    return 0


# ----------------------------------------------------------------------------- stage2: seconds per stage
def synthetic_run(run: Path, data_dir: Path, images: str, n: int, groups: int = 8, seed: int = 0) -> Path:
    """A grouped run folder whose scene is N Gaussians around the capture's sparse points."""
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.services.runs import data_json
    from ssgwarp.formats.ply import write_ply
    from ssgwarp.raster.scene import GaussianScene

    data = load_dataset(data_dir, images=images)
    if data.points is None:
        raise SystemExit(f"{data_dir}: no sparse points for --synthetic")
    xyz, rgb = data.points
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, len(xyz), (n,), generator=g)
    spread = torch.cdist(xyz[:2000], xyz[:2000]).topk(4, largest=False).values[:, 1:].mean() * 0.5
    pts = xyz[idx] + torch.randn(n, 3, generator=g) * spread
    # isotropic scales of about the jitter (a k-NN estimate over N points would take minutes on a CPU)
    scale = spread * (0.3 + 0.4 * torch.rand(n, generator=g))
    scene = GaussianScene.from_points(pts, (rgb[idx] + 0.03 * torch.randn(n, 3, generator=g)).clamp(0, 1),
                                      opacity=0.6, sh_degree=3, scale=scale)
    # k-means on positions -> identities (one-hot x 4) and an identity classifier with a background bias
    c = pts[torch.randperm(n, generator=g)[:groups]].clone()
    for _ in range(15):
        lab = torch.cdist(pts, c).argmin(1)
        for k in range(groups):
            if (lab == k).any():
                c[k] = pts[lab == k].mean(0)
    ident = torch.zeros(n, groups)
    ident[torch.arange(n), lab] = 4.0
    scene = scene.replace(identities=ident)
    lin = torch.nn.Linear(groups, groups)
    with torch.no_grad():
        lin.weight.copy_(torch.eye(groups))
        lin.bias.zero_()
    run.mkdir(parents=True, exist_ok=True)
    write_ply(run / "scene.ply", scene)
    data.cameras.save(run / "cameras.json")
    write_json(run / "data.json", data_json(data))
    (run / "groups").mkdir(exist_ok=True)
    torch.save({"dim": groups, "num_groups": groups, "state_dict": lin.state_dict()}, run / "groups" / "classifier.pt")
    return run


def stage2_main(argv=None) -> int:
    p = parser("stylize.py stage2", STAGE2_DOC)
    add = p.add_argument
    add("--run", type=Path, default=None, help="existing grouped reconstruction of the capture")
    add("--data", type=Path, default=DATA / "llff_fern")
    add("--images", default="images_4")
    add("--recon-iters", type=int, default=7000)
    add("--synthetic", type=int, default=0, metavar="N", help="stand-in scene of N Gaussians")
    add("--style", type=Path, default=DATA / "styles" / "la_muse.jpg")
    add("--modes", default="ist", help="comma-separated Stage 2 modes (ist,global,finetune)")
    add("--iters", type=int, default=None, help="Stage 2 steps (default: the CLI default)")
    add("--keyviews", type=int, default=4)
    add("--stage2", default=None, metavar="K=V,...", help="other Stage 2 options, e.g. blend_weight=0.65")
    add("--extractor", default="auto", choices=EXTRACTOR_KINDS)
    add("--path-frames", type=int, default=30)
    add("--random-stage1", choices=("tiny", "sd15"), default=None, help="Stage 1 on random models of this size")
    add("--stage1-steps", type=int, default=50)
    add("--out", type=Path, default=ROOT / "out" / "bench_stylize")
    add("--device", default="auto")
    args = p.parse_args(argv)

    from ssgwarp.cli import main as cli
    from ssgwarp.stylization.stage2 import Stage2Config
    from ssgwarp.stylization.stylize import StylizeOptions, stylize_run

    device = resolve_device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    prep = {}
    run = args.run
    if run is None:
        t0 = time.perf_counter()
        if args.synthetic:
            run = synthetic_run(args.out / f"synthetic_{args.synthetic}", args.data, args.images, args.synthetic)
            prep["synthetic_scene"] = time.perf_counter() - t0
        else:
            run = args.out / "recon"
            if not (run / "scene.ply").is_file():
                if cli(["reconstruct", str(args.data), "--images", args.images, "--out", str(run),
                        "--iters", str(args.recon_iters), "--device", str(device)]) != 0:
                    return 1
                prep["reconstruct"] = time.perf_counter() - t0
            if not (run / "groups" / "classifier.pt").is_file():
                t1 = time.perf_counter()
                if cli(["group", str(run), "--device", str(device)]) != 0:
                    return 1
                prep["group"] = time.perf_counter() - t1
    models, s1 = None, None
    if args.random_stage1:
        sys.path.insert(0, str(ROOT / "tests"))   # fakeweights: random-weight Stage 1 models
        from fakeweights import random_stage1_components
        from ssgwarp.stylization.diffusion_models import Stage1Config, assemble_stage1

        t0 = time.perf_counter()
        dtype = torch.float16 if device.type == "cuda" else torch.float32
        models = assemble_stage1(random_stage1_components(args.random_stage1, device=device), device, dtype)
        prep["random_stage1_models"] = time.perf_counter() - t0
        s1 = Stage1Config(steps=args.stage1_steps)
    results = {}
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        over = {} if args.iters is None else {"iters": args.iters}
        s2 = Stage2Config(**{"mode": mode, **over, **knobs((args.stage2 or "").split(","), Stage2Config())[0]})
        opts = StylizeOptions(keyviews=args.keyviews, extractor=args.extractor, path_frames=args.path_frames)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        m = stylize_run(run, args.style, args.out / f"styled_{mode}", stage2=s2, opts=opts, device=device,
                        force=True, stage1=s1 if mode != "global" else None,
                        stage1_models=models if mode != "global" else None)
        m["peak_gpu_memory_gib"] = (torch.cuda.max_memory_allocated(device) / 2**30) if device.type == "cuda" else None
        results[mode] = m
    dev = machine(device)
    rows = ["keyviews", "stage1", "stage2", "stage2_optimisation", "renders", "metrics", "total"]
    print(f"\n`ssgwarp stylize` on {args.data.name} {args.images}, {dev}, {time.strftime('%Y-%m-%d')}")
    if prep:
        print("preparation: " + ", ".join(f"{k} {v:.1f}s" for k, v in prep.items()))
    keys = ("gaussians", "views", "resolution", "extractor", "matching", "gram_style_loss_original", "gram_style_loss",
            "content_loss", "peak_gpu_memory_gib")
    cells = [{"what": r, **{k: f"{m['seconds'].get(r, float('nan')):.1f}" for k, m in results.items()}} for r in rows]
    cells += [{"what": key, **{k: str(m.get(key)) for k, m in results.items()}} for key in keys]
    cells += [{"what": "iters", **{k: m["config"]["iters"] for k, m in results.items()}},
              {"what": "stage 1 ran", **{k: str(m["stage1"]["ran"]) for k, m in results.items()}}]
    print("\n" + md_table(cells, [("what", "seconds"), *((k, k) for k in results)]))
    (args.out / "benchmark.json").write_text(json.dumps({"device": dev, "prep_seconds": prep, "runs": results},
                                                        indent=2, default=str))
    return 0


# ----------------------------------------------------------------------------- probe: texture fixed in 3-D
def demo_truth(run: Path):
    """The procedural scene that made the capture of the demo whose reconstruction is ``run`` (``OUT/scene``;
    size and seed from ``OUT/summary.json``)."""
    from ssgwarp import procedural as P

    summary = Path(run).resolve().parent / "summary.json"
    if not summary.is_file():
        raise InputError(f"--truth: {summary} not found; pass the scene folder of an `ssgwarp demo` output (OUT/scene)")
    info = read_json(summary)
    size = P.SIZES.get(info.get("size"))
    if size is None:
        raise InputError(f"--truth: {summary} names demo size {info.get('size')!r}; use one of {', '.join(P.SIZES)}")
    return P.build_scene(size.density, seed=int(info.get("seed", 0))).scene


def score(scene, cams, bg, opts, style_distance, alpha0=None) -> dict:
    """Consistency, error concentration and texture per scale of ``scene``'s renders; the texture is taken over
    the pixels where ``alpha0`` (the unpainted scene's alpha; default: these renders') is at least 0.5."""
    from ssgwarp.evaluation import metrics as M
    from ssgwarp.evaluation.evaluate import consistency
    from ssgwarp.raster.rendering import render_views

    rgb, depth, alpha = render_views(scene, cams, bg)
    alpha0 = alpha if alpha0 is None else alpha0
    rep = consistency(rgb, depth, alpha, cams, opts)["reprojection"]
    sq = []
    for a, b in M.consistency_pairs(len(cams), "short", opts.gap, opts.max_pairs or None):
        res = M.reprojection_warp(M.View(rgb[a], depth[a], alpha[a], cams.viewmats[a], cams.Ks[a]),
                                  M.View(rgb[b], depth[b], alpha[b], cams.viewmats[b], cams.Ks[b]),
                                  rel_tol=opts.depth_tol, alpha_min=opts.alpha_min)
        sq.append(((res.warped - rgb[b]) ** 2).sum(-1)[res.mask])
    e = torch.cat(sq).sort(descending=True).values
    share = [float(e[: max(1, int(f * len(e)))].sum() / e.sum().clamp_min(1e-12)) for f in (0.10, 0.25)]
    levels = None
    if style_distance is not None:
        per = []
        H, W = rgb.shape[1:3]
        _, s_lab, s_resp = style_distance._style_at(H, W, rgb.device)
        n = style_distance.levels_for(H, W)
        for v in range(len(rgb)):
            _, resp = style_distance._features(rgb[v], n, alpha0[v] >= 0.5)
            per.append([float(M.sliced_wasserstein(x, None, style_distance.texture_projections, style_distance.seed, y))
                        for x, y in zip(resp, s_resp)])
        levels = torch.tensor(per).mean(0).tolist()
    return {"short": rep["short"]["rmse"], "long": rep["long"]["rmse"], "share10": share[0], "share25": share[1],
            "levels": levels, "alpha": alpha}


def probe_table(name, scene, cams, bg, opts, sd, args, described) -> dict:
    """Prints and returns the unpainted scene's error and one row per probe period and amplitude."""
    base = score(scene, cams, bg, opts, sd)
    alpha0 = base.pop("alpha")
    pixel = pixel_size(scene, cams)
    print(f"{name}: {len(scene)} Gaussians, {described}, {cams.width}x{cams.height}; unpainted short/long "
          f"RMSE {base['short']:.4f} / {base['long']:.4f}; worst 10 % / 25 % of pixels hold {100 * base['share10']:.0f} / "
          f"{100 * base['share25']:.0f} % of the squared error")
    print("| period (px) | amplitude | short (x) | long (x) | texture change per scale | worst 10 % / 25 % share |")
    print("|---|---|---|---|---|---|")
    rows = []
    for period in [float(x) for x in args.periods.split(",")]:
        for amp in [float(x) for x in args.amplitudes.split(",")]:
            r = score(probe_scene(scene, period, amp, pixel), cams, bg, opts, sd, alpha0)
            r.pop("alpha")
            lv = "-" if r["levels"] is None else " / ".join(
                f"{100 * (a / b - 1):+.0f} %" for a, b in zip(r["levels"], base["levels"]))
            print(f"| {period:g} | {amp:g} | {r['short'] / base['short']:.2f} | {r['long'] / base['long']:.2f} | {lv} | "
                  f"{100 * r['share10']:.0f} / {100 * r['share25']:.0f} % |", flush=True)
            rows.append({"period_px": period, "amplitude": amp, **r})
    return {"base": base, "rows": rows}


def probe_main(argv=None) -> int:
    p = parser("stylize.py probe", PROBE_DOC)
    p.add_argument("--run", type=Path, required=True, help="a reconstruction run folder")
    p.add_argument("--style", type=Path, default=None, help="style image: texture distance per filter scale too")
    p.add_argument("--periods", default="1,2,4,8,16", help="probe periods in pixels")
    p.add_argument("--amplitudes", default="0.15,0.3", help="probe standard deviations (colour, 0..1)")
    p.add_argument("--frames", type=int, default=30, help="path views scored (ssgwarp evaluate's default)")
    p.add_argument("--device", default="auto")
    p.add_argument("--truth", action="store_true",
                   help="a demo's run (OUT/scene): also score the procedural scene that made its capture")
    p.add_argument("--json", type=Path, default=None, help="also write the rows here")
    return probe(p.parse_args(argv))   # (an InputError: one line, exit status 2, harness.dispatch)


def probe(args) -> int:
    """Every probe on the run's scene (and on the demo's true scene with ``--truth``)."""
    from ssgwarp.evaluation.evaluate import EvalOptions, inspect_run, scored_cameras
    from ssgwarp.evaluation.style_distance import StyleDistance

    device = resolve_device(args.device)
    info = inspect_run(args.run)
    scene, data = info.load(device, load_images=False)
    opts = EvalOptions(path_frames=args.frames, max_pairs=16, save_pairs=0)
    cams, _, described = scored_cameras(data.cameras, data.train_ids, data.test_ids, opts)
    cams = cams.to(device)
    bg = list(data.background)
    sd = None if args.style is None else StyleDistance(torch.from_numpy(read_image(args.style, 3)).to(device))
    scenes = [("reconstruction", scene)] + ([("truth", demo_truth(args.run).to(device))] if args.truth else [])
    print(f"run {args.run}")
    out = {"run": str(args.run)}
    for name, sc in scenes:
        out[name] = probe_table(name, sc, cams, bg, opts, sd, args, described)
    if args.json:
        write_json(args.json, out)
    return 0


# ----------------------------------------------------------------------------- bound: the style loss on free pixels
def free_pixels(start: torch.Tensor, alphas: torch.Tensor, loss, counts: list[int], lr: float):
    """Optimise each view's scene pixels with ``loss(image [H, W, 3], view, step)``; yields ``(count, images)``
    after each step count per view in ``counts`` (ascending)."""
    keep = (alphas >= 0.5).to(start)[..., None]
    params = [torch.logit(start[v].clamp(0.01, 0.99)).clone().requires_grad_(True) for v in range(len(start))]
    opts = [torch.optim.Adam([p], lr=lr) for p in params]

    def image(v: int) -> torch.Tensor:
        return torch.sigmoid(params[v]) * keep[v] + start[v] * (1 - keep[v])

    done = 0
    for count in counts:
        for step in range(done, count):
            for v in range(len(start)):
                opts[v].zero_grad(set_to_none=True)
                loss(image(v), v, step).backward()
                opts[v].step()
        done = count
        with torch.no_grad():
            yield count, torch.stack([image(v) for v in range(len(start))])


def bound_main(argv=None) -> int:
    p = parser("stylize.py bound", BOUND_DOC)
    add = p.add_argument
    add("--run", type=Path, required=True, help="a reconstruction run folder")
    add("--styles", default="", help="comma-separated style names (in --style-dir) or paths; default: all")
    add("--style-dir", type=Path, default=data_root() / "styles", help="folder of style images")
    add("--steps", default="10,100", help="steps per view at which the views are scored (ascending)")
    add("--lr", type=float, default=0.05, help="Adam learning rate on the pixels' logits")
    add("--extractor", default="patches", choices=EXTRACTOR_KINDS, help="Stage 2's features (default patches)")
    add("--tv-weight", type=float, default=0.0, help="add Stage 2's total variation term (default 0)")
    add("--frames", type=int, default=30, help="path views (ssgwarp evaluate's default 30)")
    add("--device", default="auto")
    add("--seed", type=int, default=0)
    add("--json", type=Path, default=None, help="also write the rows here (after every style)")
    args = p.parse_args(argv)
    try:
        counts = sorted({int(c) for c in args.steps.split(",")})
    except ValueError:
        counts = [-1]
    if counts[0] < 0:
        raise InputError(f"--steps takes step counts >= 0 such as 10,100, got {args.steps!r}")
    return bound(args, counts, style_paths(args.styles, args.style_dir))


def bound(args, counts: list[int], styles: list[Path]) -> int:
    """Score every style (main's table and ``--json``)."""
    from ssgwarp.evaluation.evaluate import EvalOptions, inspect_run, scored_cameras
    from ssgwarp.raster.rendering import render_views
    from ssgwarp.evaluation.style_distance import StyleDistance
    from ssgwarp.stylization.color import transfer_colors
    from ssgwarp.evaluation.features import load_extractor
    from ssgwarp.stylization.feature_defaults import resolve_for
    from ssgwarp.stylization.stage2 import Stage2Config, build_targets, extract, tv_loss
    device = resolve_device(args.device)
    torch.manual_seed(args.seed)
    scene, data = inspect_run(args.run).load(device, load_images=False)
    scene = scene.replace(sh_rest=None if scene.sh_rest is None else torch.zeros_like(scene.sh_rest))
    cams, _, described = scored_cameras(data.cameras, data.train_ids, data.test_ids,
                                        EvalOptions(path_frames=args.frames, save_pairs=0))
    cams, train = cams.to(device), data.cameras[list(data.train_ids) or list(range(len(data.cameras)))].to(device)
    bg = list(data.background)
    base = render_views(scene, cams, bg)
    H, W = base.rgb.shape[1:3]
    extractor = load_extractor(None, device, None, kind=args.extractor, seed=args.seed, config=None)
    cfg = resolve_for(Stage2Config(mode="global", seed=args.seed), extractor)
    print(f"{args.run}: {len(scene)} Gaussians, {described}, {W}x{H}; features {extractor.name}, style loss alone"
          f"{f' + TV {args.tv_weight:g}' if args.tv_weight else ''}, lr {args.lr:g}; texture / colour change "
          f"against the unstylized scene")
    head = " | ".join(f"{c} steps / view" for c in counts)
    print(f"| style | unstylized texture | colour transfer | {head} | half of the style | colour |")
    print("|---|---|---|" + "---|" * len(counts) + "---|---|")
    rows = []
    for path in styles:
        t0 = time.perf_counter()
        style = torch.from_numpy(read_image(path, 3)).to(device)
        at_views = fit_style(style.to(scene.dtype), H, W).permute(0, 2, 3, 1)
        sd = StyleDistance(style)
        d0 = {k: float(v.mean()) for k, v in sd(base.rgb, base.alpha).items()}
        recoloured, _ = transfer_colors(scene, train, at_views, max_gain=cfg.color_max_gain,
                                        keep_detail=cfg.color_detail == "keep")
        start = render_views(recoloured, cams, bg).rgb
        dct = float(sd(start, base.alpha)["texture"].mean())
        targets = build_targets(extractor, at_views, None, cfg)

        def loss(img, view, step):
            out = targets.loss(extract(extractor, img, 1.0)[0], None, step=step)
            return out + args.tv_weight * tv_loss(img) if args.tv_weight else out

        per = {}
        for count, images in free_pixels(start, base.alpha, loss, counts, args.lr):
            last = sd(images, base.alpha)
            per[count] = float(last["texture"].mean())
        raw_color = float(last["color"].mean())           # after the last step count
        row = {"style": path.stem, "texture": d0["texture"], "color": d0["color"], "color_transfer": dct,
               "free": per, "free_color": raw_color,
               "halves": sd.halves(H, W), "seconds": time.perf_counter() - t0}
        rows.append(row)
        if args.json:      # after every style: a run stopped early keeps the finished ones
            write_json(args.json, {"run": str(args.run), "features": extractor.name, "steps": counts, "lr": args.lr,
                                   "tv_weight": args.tv_weight, "views": len(cams), "rows": rows})

        def ch(x: float, ref: float) -> str:
            return f"{100 * (x / ref - 1):+.1f} %"

        cells = " | ".join(ch(per[c], d0["texture"]) for c in counts)
        print(f"| {path.stem} | {d0['texture']:.3f} | {ch(dct, d0['texture'])} | {cells} | "
              f"{ch(row['halves']['texture'], d0['texture'])} | {ch(raw_color, d0['color'])} |", flush=True)

    def mean(f) -> str:
        return f"{100 * sum(f(r) for r in rows) / len(rows):+.1f} %"

    cells = " | ".join(mean(lambda r, c=c: r["free"][c] / r["texture"] - 1) for c in counts)
    print(f"| **mean of {len(rows)}** | | {mean(lambda r: r['color_transfer'] / r['texture'] - 1)} | {cells} | "
          f"{mean(lambda r: r['halves']['texture'] / r['texture'] - 1)} | {mean(lambda r: r['free_color'] / r['color'] - 1)} |")
    return 0


# ----------------------------------------------------------------------------- captures: the table on each capture
def captures_main(argv=None) -> int:
    p = parser("stylize.py captures", CAPTURES_DOC)
    p.add_argument("--captures", default="fern4,cup,livingroom,bird", help="shared capture names or PATH[:IMAGES]")
    p.add_argument("--recon-iters", type=int, default=7000, help="reconstruction steps")
    p.add_argument("--width", type=int, default=0, help="reconstruct at this image width (0: as loaded)")
    p.add_argument("--recon", default="", help="more reconstruct flags, e.g. '--max-images 24 --max-gaussians 20000'")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "stylize")
    p.add_argument("--tag", default="")
    p.add_argument("--device", default="auto")
    p.add_argument("--regions", action="store_true", help="only the region check of every style (no Stage 2): the "
                   "groups' shares, their regions, which fall back to the whole style and the predicted distances")
    args, rest = p.parse_known_args(argv)
    from ssgwarp.cli import main as cli
    from ssgwarp.stylization.spread import consistency_probe, strength_for

    rows = []
    for spec in (c.strip() for c in args.captures.split(",") if c.strip()):
        folder, images = capture_folder(spec)
        run = args.out / "recon" / f"{Path(spec).name}_w{args.width}_i{args.recon_iters}"   # results: OUT/<its name>
        if not (run / "groups" / "classifier.pt").is_file() and cli(
                ["reconstruct", str(folder), "--images", images, "--out", str(run), "--iters", str(args.recon_iters),
                 "--groups", "auto", "--force", "--device", args.device, *__import__("shlex").split(args.recon)]
                + (["--width", str(args.width)] * (args.width > 0))):
            return 1
        scene, data = load_run(run, resolve_device(args.device), load_images=False)   # --paint-strength auto's probe
        probe = consistency_probe(scene, data.cameras[list(data.train_ids)].to(scene.device))
        print(f"{run.name}: {len(scene)} Gaussians; 3-D probe {probe:.2f}x, --paint-strength auto {strength_for(probe):.2f}")
        if args.regions:
            region_check(run, resolve_device(args.device))
            continue
        styles_main(["--scene", str(run), "--out", str(args.out), "--device", args.device, "--tag", args.tag, *rest])
        res = json.loads((args.out / (f"{run.name}_{args.tag}" if args.tag else run.name) / "results.json").read_text())
        rows.append({**capture_row(Path(spec).name, res["rows"], res["source"]), "probe": probe,
                     "strength": strength_for(probe)})
    if args.regions:
        return 0
    text = f"`benchmarks/stylize.py captures {__import__('shlex').join(argv or sys.argv[2:])}`\n\n" + md_table(rows, [
        ("capture", "capture"), ("styles", "styles"), ("colour", "colour Δ (mean)"), ("texture", "texture Δ (mean)"),
        ("farther", "styles not closer on both (texture after/before)"), ("consistency", "worst short / long (x)"),
        ("probe", "3-D probe (x)"), ("strength", "--paint-strength auto")])
    write_text(args.out / f"captures{'_' + args.tag if args.tag else ''}.md", text)
    print(text)
    return 0


def region_check(run: Path, device) -> None:
    """Per style: each group's region (-1: the whole style) as ``ssgwarp stylize --region-check`` takes it without Stage 1,
    and the predicted distances of the view it gives, before / after the fallback, against the style's halves."""
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.stylization.regions import style_regions
    from ssgwarp.stylization.stage2 import render_alphas, render_rgb
    from ssgwarp.stylization.targets import group_maps

    scene, data = load_run(run, device, load_images=False)
    cams, gm = data.cameras[list(data.train_ids)].to(device), load_groups(run, device)
    with torch.no_grad():
        views = render_rgb(scene, cams, torch.tensor(data.background[:3]).to(scene.sh_dc)).clamp(0, 1).float()
    labels, alphas = group_maps(scene, cams, gm.classifier, False), render_alphas(scene, cams)
    print(f"{run.name}: | style | groups' shares | regions | predicted colour / texture, before -> after | halves |")
    for style in style_paths("", DATA / "styles"):
        at = fit_style(torch.from_numpy(read_image(style, 3)).float().to(device), cams.height, cams.width)[0]
        r = style_regions(at.permute(1, 2, 0), views, labels, int(gm.num_groups), alphas=alphas, check=True)
        f, pct = r["fallback"], " ".join(f"{100 * float(m):.0f}%" for m in r["group_mass"])
        print(f"| {style.stem} | {pct} | {r['region'].tolist()} | {f['predicted_before'][0]:.2f} / "
              f"{f['predicted_before'][1]:.2f} -> {f['predicted_after'][0]:.2f} / {f['predicted_after'][1]:.2f} | "
              f"{f['halves'][0]:.2f} / {f['halves'][1]:.2f} |", flush=True)


def capture_row(name: str, rows: list[dict], src: dict) -> dict:
    """One capture's summary: mean colour / texture change, the styles not closer on both, worst consistency."""
    n = max(len(rows), 1)
    far = [f"{r['style']} ({r['texture_after'] / r['texture_before']:.2f})" for r in rows
           if r["color_after"] >= r["color_before"] or r["texture_after"] >= r["texture_before"]]
    return {"capture": name, "styles": len(rows),
            "colour": f"{100 * sum(r['color_after'] / r['color_before'] - 1 for r in rows) / n:+.1f} %",
            "texture": f"{100 * sum(r['texture_after'] / r['texture_before'] - 1 for r in rows) / n:+.1f} %",
            "farther": ", ".join(far) or "none", "consistency": f"{max(r['short'] / src['short'] for r in rows):.2f} / "
            f"{max(r['long'] / src['long'] for r in rows):.2f}" if rows else "-"}


MODES = {"captures": captures_main, "stage2": stage2_main, "probe": probe_main, "bound": bound_main}


def main(argv=None) -> int:
    return dispatch(MODES, styles_main, argv)


if __name__ == "__main__":
    sys.exit(main())
