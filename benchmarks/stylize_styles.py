"""Weight-free stylization over many styles: before/after by the weight-free style distances, Gram, consistency.

For a scene (fern ``images_8`` reconstruction, the demo scene, or any grouped run) and every style
image in a folder (default ``../shared/data/styles``, 25 images), runs ``ssgwarp stylize`` (no
Stage 1 weights needed: Stage 2 matches the style image) and ``ssgwarp evaluate`` (default
protocol: 30 novel views on a smooth path through the training cameras), and prints one row per
style: colour and texture distances (sliced Wasserstein in Lab / of a derivative-of-Gaussian
filter bank, ``ssgwarp.evaluation.metrics.StyleDistance``) of the original and the stylized renders, the Gram
loss of the extractor Stage 2 used, short/long-range consistency RMSE as ratios to the
unstylized scene's, and floaters over the regions the unstylized scene leaves empty (the worst
style). For reference, each row also scores half of the style image against the whole with the same
distances (about as close as a render can be expected to get; ``StyleDistance.halves``). ``--ablation`` runs the Stage 2
ablations (colour transfer, content/TV weights, SH bands, colour gain cap) on a few styles instead.

    python benchmarks/stylize_styles.py --scene demo                  # the demo scene (built first)
    python benchmarks/stylize_styles.py --scene fern                  # fern images_8 (reconstructed + grouped first)
    python benchmarks/stylize_styles.py --scene fern --shard 0/3      # a third of the styles (10-minute slots)
    python benchmarks/stylize_styles.py --scene demo --demo-size small --styles-subset candy,udnie \
        --iters 10 --path-frames 6 --out /tmp/ss                       # CPU check (~2 min on 2 cores)
    python benchmarks/stylize_styles.py --scene fern --ablation       # Stage 2 ablation table
    python benchmarks/stylize_styles.py --scene fern --ablation --styles-subset mondrian,asheville \
        --ablation-rows "default;SH rest: keep;paper objective (content 0, TV 0)"   # some rows, some styles
    python benchmarks/stylize_styles.py --scene fern --report         # table of what is finished, no new runs
    python benchmarks/stylize_styles.py --scene fern --paint --tag paint   # stylize's --paint preset
    python benchmarks/stylize_styles.py --scene fern --configs FILE --timeout 420  # several configurations at once
                                                                      # on one GPU, FILE lines 'TAG: FLAGS'

Every finished style is kept (``OUT/<scene>/<style>/result.json``) and skipped when the script
runs again, so shards and interrupted runs add up; ``--report`` prints the table of everything
finished. Writes ``OUT/<scene>/table.md``, ``OUT/<scene>/results.json`` and a contact sheet of a
few styles, ``OUT/<scene>/styles_sheet.jpg``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional

import torch

ROOT = Path(__file__).resolve().parents[1]
from shared_data import data_root, style_paths  # noqa: E402
from ssgwarp.evaluation.features import EXTRACTOR_KINDS  # noqa: E402
DATA = data_root()

SHEET_STYLES = ("brushstrokes", "candy", "la_muse", "mosaic", "the_resevoir_at_poitiers", "sketch", "udnie")
ABLATION_STYLES = ("candy", "la_muse", "sketch", "udnie")


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
    from ssgwarp.reconstruction.reconstruct import reconstruct

    run = out / "fern_images_8"
    if not (run / "scene.ply").is_file():
        reconstruct(fern, run, images="images_8", iters=fern_iters, device=device,
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
    from ssgwarp.core.fileio import read_json, write_json
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
           "empty_spread": sc.get("empty_spread"), "empty_spread_original": sc.get("empty_spread_original")}
    write_json(res_file, row)
    return row


def add_halves(rows: list[dict], styles: list[Path], run: Path, results: Path) -> None:
    """Each row's ``color_half`` / ``texture_half``: the distances of the style image's own halves to the whole
    at the scored views' size (:meth:`StyleDistance.halves`), a reference for how close a render can get;
    computed once and kept in the style's ``result.json`` (in ``results``, ``OUT/<scene>/styles``)."""
    from ssgwarp.core.cameras import Cameras
    from ssgwarp.core.fileio import read_image, write_json
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
    from ssgwarp.core.fileio import read_json, write_json

    f = out / "source_consistency.json"
    if f.is_file():
        return read_json(f)
    ev = evaluate_run(run, eval_opts, device, write=False, progress=progress)
    rep = ev["consistency"]["reprojection"]
    d = {"short": rep["short"]["rmse"], "long": rep["long"]["rmse"], "views_scored": ev["views_scored"]}
    write_json(f, d)
    return d


def _pct(before: Optional[float], after: Optional[float]) -> str:
    if before is None or after is None or before == 0:
        return "-"
    return f"{100 * (after - before) / before:+.0f}%"


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ssgwarp.capture.datasets import load_run
    from ssgwarp.core.fileio import atomic_path, read_image
    from ssgwarp.capture.ply import read_ply
    from ssgwarp.services.runs import Run
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
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="jpg", pil_kwargs={"quality": 82})
    plt.close(fig)
    return path


ABLATIONS = {
    "default": {},
    "color transfer off": {"color_transfer": "off"},
    "color transfer pre": {"color_transfer": "pre"},
    "color transfer post": {"color_transfer": "post"},
    "colour transfer only (0 steps)": {"iters": 0},
    "paper objective (content 0, TV 0)": {"content_weight": 0.0, "tv_weight": 0.0},
    "content 0": {"content_weight": 0.0},
    "TV 0": {"tv_weight": 0.0},
    "SH rest: keep": {"sh_rest": "keep"},
    "SH rest: zero": {"sh_rest": "zero"},
    "SH rest: optimise": {"sh_rest": "optimise"},
    "TV 0.02 (previous default)": {"tv_weight": 0.02},
    "TV 0.1": {"tv_weight": 0.1},
    "TV 0.5": {"tv_weight": 0.5},
    "colour gain 1.0": {"color_max_gain": 1.0},
    "background: keep": {"background": "keep"},
    "free opacity": {"free_opacity": True},
}


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


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="demo", help="fern, demo, or a (grouped) reconstruction run folder")
    p.add_argument("--styles", type=Path, default=DATA / "styles", help="folder of style images")
    p.add_argument("--styles-subset", default=None, help="comma-separated style names (file stems)")
    p.add_argument("--shard", default=None, help="i/n: run the i-th of n interleaved slices of the styles")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "stylize_styles")
    p.add_argument("--device", default="auto")
    p.add_argument("--fern-iters", type=int, default=7000, help="reconstruction steps of fern images_8")
    p.add_argument("--fern", type=Path, default=DATA / "llff_fern", help="the LLFF fern capture (--scene fern)")
    p.add_argument("--demo-size", default="default", choices=("small", "default"),
                   help="demo scene size (--scene demo; small: the tests' scene, for a CPU check)")
    p.add_argument("--extractor", default="auto", choices=EXTRACTOR_KINDS)
    p.add_argument("--path-frames", type=int, default=30, help="novel path views scored by evaluate")
    p.add_argument("--ablation", action="store_true", help="the Stage 2 ablation table on a few styles")
    p.add_argument("--ablation-rows", default=None,
                   help="ablation row labels to run, separated by ; (default: all rows of ABLATIONS)")
    p.add_argument("--report", action="store_true", help="print the table of finished styles only")
    p.add_argument("--configs", type=Path, default=None,
                   help="a file of configurations, one per line 'TAG: FLAGS' (# comments): the scene is built once, "
                        "then each runs as its own process, all at once on the one device (--tag TAG and the line's "
                        "FLAGS; --scene, --out, --device, --styles, --styles-subset, --fern*, --demo-size and "
                        "--path-frames shared); logs in OUT/<scene>_<TAG>.log")
    p.add_argument("--timeout", type=float, default=None,
                   help="with --configs: stop every configuration this many seconds after the command started, "
                        "building the scene included (finished styles are kept; run again to continue)")
    p.add_argument("--tag", default="", help="results in OUT/<scene>_<tag> (one folder per configuration; the "
                   "scene is built once in OUT and shared)")
    p.add_argument("--quiet", action="store_true")
    g = p.add_argument_group("Stage 2 (default: the CLI defaults)")
    g.add_argument("--iters", type=int, default=None)
    g.add_argument("--lr", type=float, default=None)
    g.add_argument("--content-weight", type=float, default=None)
    g.add_argument("--tv-weight", type=float, default=None)
    g.add_argument("--blend-weight", type=float, default=None)
    g.add_argument("--color-transfer", default=None)
    g.add_argument("--color-max-gain", type=float, default=None)
    g.add_argument("--color-detail", default=None, choices=("keep", "off"))
    g.add_argument("--sh-rest", default=None)
    g.add_argument("--background", default=None, choices=("transfer", "keep"))
    g.add_argument("--mode", default=None, choices=("ist", "global"),
                   help="ist (the CLI default: per group against the style image's regions on a grouped scene) "
                        "or global (one match against the whole style image, the behaviour before issue 39)")
    g.add_argument("--densify", type=float, default=None, help="split budget (fraction of the Gaussians; 0: off)")
    g.add_argument("--densify-views", type=int, default=None)
    g.add_argument("--hold-empty", type=float, default=None, help="weight of the empty-region term (0: off)")
    g.add_argument("--consistency-weight", type=float, default=None, help="weight of the view-pair term (0: off)")
    g.add_argument("--consistency-neighbours", type=int, default=None)
    g.add_argument("--consistency-budget", type=float, default=None,
                   help="pair error (x the starting scene's, squared) left free by the view-pair term")
    g.add_argument("--style-scale", type=float, default=None, help="style image size against the views (1: fit)")
    from ssgwarp.core.presets import add_preset
    from ssgwarp.stylization.stylize_cli import PAINT
    add_preset(p, "--paint", PAINT, "ssgwarp stylize's painting preset: {values} (options given explicitly win)")
    args = p.parse_args()

    from ssgwarp.cli import resolve_device
    from ssgwarp.evaluation.evaluate import EvalOptions
    from ssgwarp.core.fileio import atomic_path, write_json
    from ssgwarp.errors import InputError

    device = resolve_device(args.device)
    torch.manual_seed(0)
    progress = not args.quiet
    try:
        styles = style_paths(args.styles_subset or "", args.styles)
    except InputError as e:
        raise SystemExit(str(e)) from None
    if args.configs is not None:
        return run_configs(args, styles, device, progress)
    name = scene_name(args.scene)
    out = args.out / (f"{name}_{args.tag}" if args.tag else name)
    out.mkdir(parents=True, exist_ok=True)
    run = prepare_scene(args.scene, args.out, device, args.fern_iters, progress, args.demo_size, args.fern)
    eval_opts = EvalOptions(path_frames=args.path_frames, max_pairs=16, save_pairs=0)
    src = source_consistency(run, out, device, eval_opts, progress)
    dev = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"

    if args.ablation:
        abl = [s for s in styles if s.stem in ABLATION_STYLES] or styles[:4]
        lines = [f"Stage 2 ablation on {name} ({dev}, {time.strftime('%Y-%m-%d')}), styles "
                 f"{', '.join(s.stem for s in abl)}; means over the styles", "",
                 "| configuration | colour Δ | texture Δ | Gram after/before | short RMSE (x src) | long RMSE (x src) | Stage 2 s |",
                 "|---|---|---|---|---|---|---|"]
        raw = {}
        rows_wanted = ABLATIONS
        if args.ablation_rows:
            want = [w.strip() for w in args.ablation_rows.split(";") if w.strip()]
            bad = [w for w in want if w not in ABLATIONS]
            if bad:
                raise SystemExit(f"--ablation-rows: unknown {', '.join(bad)}; known: {', '.join(ABLATIONS)}")
            rows_wanted = {w: ABLATIONS[w] for w in want}
        for label, over in rows_wanted.items():
            cfg = stage2_config(args, **over)
            tag = "abl_" + "".join(c if c.isalnum() else "_" for c in label)
            rows = [] if args.report else [run_style(run, s, out / tag / s.stem, cfg, device, args.extractor,
                                                      eval_opts, progress) for s in abl]
            if not rows:
                continue
            raw[label] = rows
            n = len(rows)
            mean = lambda f: sum(f(r) for r in rows) / n  # noqa: E731
            lines.append(f"| {label} | {100 * mean(lambda r: r['color_after'] / r['color_before'] - 1):+.1f}% | "
                         f"{100 * mean(lambda r: r['texture_after'] / r['texture_before'] - 1):+.1f}% | "
                         f"{mean(lambda r: r['gram_after'] / r['gram_before']):.2f} | "
                         f"{mean(lambda r: r['short'] / src['short']):.2f} | {mean(lambda r: r['long'] / src['long']):.2f} | "
                         f"{mean(lambda r: r['stage2_seconds']):.1f} |")
        text = "\n".join(lines) + "\n"
        with atomic_path(out / "ablation.md") as tmp:
            tmp.write_text(text)
        write_json(out / "ablation.json", {"device": dev, "source": src, "runs": raw})
        print(text)
        return 0

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
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(text)
    write_json(out / "results.json", {"device": dev, "source": src, "rows": rows})
    sheet(out / "styles_sheet.jpg", run, out / "styles", [s for s in styles if s.stem in SHEET_STYLES], device)
    print(text)
    print(f"{len(rows)}/{len(styles)} styles finished; table {out / 'table.md'}, sheet {out / 'styles_sheet.jpg'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
