"""The capture quality table: every shared capture reconstructed as ``ssgwarp reconstruct`` does, held-out quality
beside the checked-in baseline; more than ``--tolerance`` dB below it is a REGRESSION (exit status 1). Finished rows
are kept in ``--out``/results.jsonl (a rerun finishes the table; ``--fresh`` starts over). How to read it and the
evidence flags: docs/reconstruction.md.

    python benchmarks/captures.py --out runs/captures                             # the whole table (GPU)
    python benchmarks/captures.py --captures lego --iters 20 --max-images 8 --device cpu --out /tmp/cap
    python benchmarks/captures.py --from runs/captures/results.jsonl --write-baseline
    python benchmarks/captures.py --backdrop-evidence --captures fern8 cup lego livingroom bird --thin 2000
    python benchmarks/captures.py --triangulation --captures fern8 --min-angle 1 2 3

Modes, each with its own ``--help``: ``appearance``, ``inside-out`` (docs/benchmarks.md).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from harness import CAPTURES, append_jsonl, capture_folder, data_root, dispatch, knobs, machine, parser  # noqa: E402
from harness import write_text  # noqa: E402
from harness import table as md_table  # noqa: E402

from ssgwarp.core.fileio import write_json  # noqa: E402

SETTINGS = {"7k": 7000, "auto": "auto"}
BASELINE = Path(__file__).resolve().parent / "captures_baseline.json"
TOLERANCE = 0.2


def setting_iters(setting: str):
    """Steps of a setting (``7k``, ``auto`` or a step count)."""
    if setting in SETTINGS:
        return SETTINGS[setting]
    if setting.isdigit() and int(setting) > 0:
        return int(setting)
    raise SystemExit(f"--settings {setting!r}: choose {', '.join(SETTINGS)} or a step count")


def key(row: dict) -> str:
    return f"{row['capture']}/{row['setting']}"


_LOADED: dict = {}


def load(spec: str, a) -> tuple:
    """``(SceneData, seconds)`` of a capture, loaded once (triangulation included) for all its settings, with the
    arguments ``reconstruct()`` loads it with."""
    from ssgwarp.capture.datasets import load_dataset

    if spec not in _LOADED:
        _LOADED.clear()
        folder, images = capture_folder(spec, a.data_root)
        t0 = time.perf_counter()
        data = load_dataset(folder, images=images, max_images=a.max_images, width=a.width,
                            num_random_points=a.random_points, seed=a.seed, progress=not a.no_progress)
        _LOADED[spec] = (data, time.perf_counter() - t0)
    return _LOADED[spec]


def run_one(spec: str, setting: str, iters, a, device) -> dict:
    """Reconstruct one capture at one setting (the command's code path: ``reconstruct()`` on the capture loaded
    as it loads it) and return its table row."""
    import torch

    from ssgwarp.reconstruction.reconstruct import ReconstructConfig, reconstruct

    folder, images = capture_folder(spec, a.data_root)
    data, load_seconds = load(spec, a)
    label = spec if spec in CAPTURES else spec.replace("/", "_").replace(":", "_").strip("_")
    run_dir = a.out / "runs" / f"{label}-{setting}"
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    cfg = ReconstructConfig(iters=iters, images=images, seed=a.seed, max_images=a.max_images, width=a.width,
                            checkpoint_every=10**9, num_random_points=a.random_points)
    m = reconstruct(folder, run_dir, cfg, force=True, device=device, progress=not a.no_progress, data=data)
    wall = time.perf_counter() - t0 + load_seconds
    data_json = json.loads((run_dir / "data.json").read_text())
    bd = m.get("backdrop") or {}
    row = {"capture": spec, "setting": setting, "folder": str(folder), "images": images,
           "resolution": "x".join(str(v) for v in m["resolution"]), "iters": m["iters"],
           "stopped": m["schedule"].get("stopped"), "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
           "test_views": m["test_views"], "gaussians": m["num_gaussians"], "train_seconds": m["train_seconds"],
           "wall_seconds": round(wall, 2), "load_seconds": round(load_seconds, 2), "points": data_json.get("points_source"),
           "points_count": data_json.get("points_count"),
           "backdrop": {k: bd.get(k) for k in ("used", "why", "layout", "coverage", "points")},
           "peak_gpu_memory_mb": m.get("peak_gpu_memory_mb"), "device": str(device),
           "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
           "date": time.strftime("%Y-%m-%d")}
    if not a.keep_runs:  # the scene and checkpoint are large; the metrics stay
        for name in ("scene.ply", "checkpoint.pt"):
            (run_dir / name).unlink(missing_ok=True)
    return row


# ----------------------------------------------------------------------------- baseline and table
def read_rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.is_file() else []


def read_baseline(path: Path) -> dict:
    """``{"capture/setting": row}`` of the baseline file (empty when there is none)."""
    return dict(json.loads(path.read_text()).get("rows", {})) if path.is_file() else {}


def write_baseline(path: Path, rows: list[dict], old: dict) -> None:
    new = dict(old)
    for r in rows:
        new[key(r)] = {k: r.get(k) for k in ("psnr", "ssim", "lpips", "gaussians", "iters", "train_seconds",
                                             "wall_seconds", "resolution", "gpu", "date")}
    write_json(path, {"note": "written by benchmarks/captures.py --write-baseline; rows by capture/setting",
                      "rows": dict(sorted(new.items()))})


def compare(rows: list[dict], baseline: dict, tolerance: float = TOLERANCE) -> list[dict]:
    """Each row with ``base_psnr``, ``delta_db`` and ``status``: ``REGRESSION`` (more than ``tolerance`` dB below
    the baseline), ``ok``, ``new`` (no baseline row, or one of another step count: a smoke run) or ``failed``
    (no PSNR)."""
    out = []
    for r in rows:
        b = baseline.get(key(r))
        if b is not None and isinstance(r.get("iters"), int) and r["setting"] not in SETTINGS \
                and b.get("iters") != r["iters"]:
            b = None
        r = dict(r, base_psnr=None if b is None else b.get("psnr"), delta_db=None)
        if r.get("psnr") is None or (isinstance(r["psnr"], float) and math.isnan(r["psnr"])):
            r["status"] = "failed"
        elif r["base_psnr"] is None:
            r["status"] = "new"
        else:
            r["delta_db"] = r["psnr"] - r["base_psnr"]
            r["status"] = "REGRESSION" if r["delta_db"] < -tolerance else "ok"
        out.append(r)
    return out


def table(rows: list[dict], tolerance: float = TOLERANCE) -> str:
    shown = []
    for r in rows:
        d, bd = r["delta_db"], r.get("backdrop") or {}
        shown.append(dict(r, change=f"**{d:+.2f} REGRESSION**" if r["status"] == "REGRESSION" else
                          f"{d:+.2f}" if r["status"] == "ok" else r["status"],
                          back="n/a" if bd.get("used") is None else
                          f"{bd.get('points', 0):,} far points" if bd["used"] else "none"))
    return md_table(shown, [("capture", "capture"), ("setting", "setting"), ("resolution", "resolution"),
                            ("iters", "steps"), ("psnr", "held-out PSNR (dB)"), ("base_psnr", "baseline"),
                            ("change", f"change (REGRESSION: < -{tolerance:g} dB)"), ("ssim", "SSIM", 4),
                            ("lpips", "LPIPS", 3), ("gaussians", "Gaussians"), ("train_seconds", "train (s)", 0),
                            ("wall_seconds", "run (s)", 0), ("points", "initial points"), ("back", "backdrop")])


# ----------------------------------------------------------------------------- main
def table_main(argv=None) -> int:
    p = parser("captures.py", __doc__)
    add = p.add_argument
    add("--captures", nargs="+", default=list(CAPTURES), help=f"{', '.join(CAPTURES)} or PATH[:IMAGES] (default: all)")
    add("--settings", nargs="+", default=list(SETTINGS), help="7k, auto (--iters auto) or a step count (default: both)")
    add("--iters", type=int, default=None, help="run every setting at this many steps (smoke runs)")
    add("--max-images", type=int, default=None, help="use at most this many images (smoke runs)")
    add("--width", type=int, default=None, help="resize the images to this width (smoke runs)")
    add("--random-points", type=int, default=100_000, help="initial points where there are none to triangulate "
        "(default 100000, as the command)")
    add("--data-root", type=Path, default=None, help=f"folder of the shared captures (default {data_root()})")
    add("--device", default=None, help="cuda when available, else cpu")
    add("--seed", type=int, default=0)
    add("--out", type=Path, default=Path("benchmark-captures"), help="folder for results.jsonl / .md and the runs")
    add("--fresh", action="store_true", help="drop the rows already in --out/results.jsonl")
    add("--keep-runs", action="store_true", help="keep each run's scene.ply")
    add("--from", dest="from_file", type=Path, default=None, help="table this results.jsonl's rows (no runs)")
    add("--baseline", type=Path, default=BASELINE, help=f"baseline file (default {BASELINE.name})")
    add("--tolerance", type=float, default=TOLERANCE, help="dB lost that counts as a regression (0.2)")
    add("--write-baseline", action="store_true", help="write the table's rows into the baseline (others kept)")
    add("--triangulation", action="store_true", help="triangulated points against COLMAP's instead (no training)")
    add("--backdrop-evidence", action="store_true", help="the backdrop decision's evidence instead (no training)")
    add("--thin", type=int, default=None, help="with --backdrop-evidence: also the points thinned to this many")
    add("--min-angle", type=float, nargs="+", default=None, help="with --triangulation: smallest triangulation "
        "angles (degrees; default: triangulate()'s)")
    add("--no-progress", action="store_true")
    a = p.parse_args(argv)
    if a.triangulation:
        return triangulation(a)
    if a.backdrop_evidence:
        return backdrop_evidence(a)
    baseline = read_baseline(a.baseline)
    if a.from_file is not None:
        rows = read_rows(a.from_file)
        if not rows:
            raise SystemExit(f"--from {a.from_file}: no rows")
    else:
        from ssgwarp.cli import resolve_device

        device = resolve_device(a.device)
        for s in a.settings:
            setting_iters(s)
        for spec in a.captures:
            capture_folder(spec, a.data_root)  # every folder checked before the first run
        results = a.out / "results.jsonl"
        if a.fresh:
            results.unlink(missing_ok=True)
        done = {key(r): r for r in read_rows(results)}
        rows = []
        settings = [str(a.iters)] if a.iters else list(dict.fromkeys(a.settings))
        for spec in dict.fromkeys(a.captures):
            for setting in settings:
                k = f"{spec}/{setting}"
                if k in done:
                    rows.append(done[k])
                    continue
                r = run_one(spec, setting, setting_iters(setting), a, device)
                print(json.dumps(r), flush=True)
                rows.append(r)
                done[k] = r
                write_text(results, "".join(json.dumps(x) + "\n" for x in done.values()))
    rows = compare(rows, baseline, a.tolerance)
    md = table(rows, a.tolerance)
    bad = [key(r) for r in rows if r["status"] == "REGRESSION"]
    print(f"\n{time.strftime('%Y-%m-%d')}, baseline {a.baseline.name}\n\n{md}")
    if a.from_file is None:
        write_text(a.out / "results.md", md + "\n")
    if a.write_baseline:
        write_baseline(a.baseline, rows, baseline)
        print(f"wrote {a.baseline} ({len(rows)} rows)")
        return 0
    if bad:
        print(f"REGRESSION (more than {a.tolerance:g} dB below the baseline): {', '.join(bad)}")
        return 1
    return 0


def backdrop_evidence(a) -> int:
    """The backdrop decision's evidence per capture (layout, points, coverage, uncovered / textured / far cells, the
    old rule and today's decision), no training; ``--thin N``: also the points thinned to N (seeded)."""
    import torch

    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.reconstruction.backdrop import MIN_COVERAGE, far_evidence, plan_backdrop

    rows = []
    for spec in dict.fromkeys(a.captures):
        folder, images = capture_folder(spec, a.data_root)
        data = load_dataset(folder, images=images, width=a.width, max_images=a.max_images, progress=False,
                            num_random_points=a.random_points)
        for thin in [None] + ([a.thin] if a.thin else []):
            xyz = data.points[0]
            if thin and thin < len(xyz):
                xyz = xyz[torch.randperm(len(xyz), generator=torch.Generator().manual_seed(0))[:thin]]
            t0 = time.perf_counter()
            plan = plan_backdrop(data, xyz)
            ev = plan.evidence or far_evidence(data.cameras, data.images, xyz, data.train_ids,
                                               background=data.background)
            sec = time.perf_counter() - t0
            row = {"capture": spec, "layout": plan.layout, "points": data.points_source, "count": len(xyz),
                   "coverage": plan.coverage, **{k: ev[k] for k in ("uncovered", "textured", "far")},
                   "before": plan.coverage < MIN_COVERAGE, "use": plan.use, "why": plan.why, "seconds": sec}
            print(json.dumps(row), flush=True)
            rows.append(dict(row, points=f"{len(xyz):,} {data.points_source}{' (thinned)' if thin else ''}",
                             before="yes" if row["before"] else "no", use=f"{'yes' if plan.use else 'no'} ({plan.why})",
                             **{k: f"{row[k]:.{0 if k != 'far' else 1}%}" for k in ("coverage", "uncovered", "textured", "far")}))
    print(md_table(rows, [("capture", "capture"), ("layout", "layout"), ("points", "initial points"),
                          ("coverage", "coverage"), ("uncovered", "uncovered cells"), ("textured", "textured of those"),
                          ("far", "far cells"), ("before", "coverage < 90% (before)"), ("use", "backdrop now"),
                          ("seconds", "seconds", 1)]))
    return 0


def triangulation_accuracy(xyz, ref) -> dict:
    """How far points ``xyz`` lie from reference points ``ref`` (COLMAP's): the median distance from each point to
    its nearest reference point, and that as a fraction of the reference points' median distance from their
    centre (the per-axis median)."""
    import torch

    xyz, ref = xyz.double().cpu(), ref.double().cpu()
    nearest = torch.cat([torch.cdist(c, ref).min(1).values for c in xyz.split(2048)])
    spread = float((ref - ref.median(0).values).norm(dim=1).median())
    med = float(nearest.median())
    return {"points": len(xyz), "reference_points": len(ref), "median_distance": med, "spread": spread,
            "relative": med / spread, "p90_relative": float(torch.quantile(nearest, 0.9)) / spread}


def triangulation(a) -> int:
    """Points triangulated from each capture's images and poses against its own (COLMAP) points: an LLFF
    capture (``poses_bounds.npy``) is read from a copy without ``sparse/`` (as a user's capture without points),
    any other with ``--init triangulate``."""
    import tempfile

    from ssgwarp.capture.datasets import load_dataset

    caps = a.captures if a.captures != list(CAPTURES) else \
        [c for c in a.captures if c not in ("lego", "livingroom", "bird")]   # (the shared ones with COLMAP points)
    rows = []
    from ssgwarp.capture.triangulate import triangulate

    default_angle = triangulate.__kwdefaults__["min_angle_deg"]
    for spec, angle in [(c, x) for c in caps for x in (a.min_angle or [default_angle])]:
        triangulate.__kwdefaults__["min_angle_deg"] = angle  # what load_dataset triangulates with
        folder, images = capture_folder(spec, a.data_root)
        ref = load_dataset(folder, images=images, width=a.width, progress=False)
        if ref.points_source != "colmap":
            raise SystemExit(f"--triangulation: {spec} has no COLMAP points to compare with")
        with tempfile.TemporaryDirectory() as tmp:
            if (folder / "poses_bounds.npy").is_file():
                src = Path(tmp) / folder.name
                src.mkdir()
                for f in folder.iterdir():
                    if f.name != "sparse":
                        (src / f.name).symlink_to(f.resolve())
                init = "auto"
            else:
                src, init = folder, "triangulate"
            t0 = time.perf_counter()
            try:
                tri = load_dataset(src, images=images, width=a.width, init=init, progress=not a.no_progress)
            finally:
                triangulate.__kwdefaults__["min_angle_deg"] = default_angle
            sec = time.perf_counter() - t0
        r = triangulation_accuracy(tri.points[0], ref.points[0])
        st = tri.points_stats
        row = {"capture": spec, "min_angle_deg": angle, **r, "reprojection_px": st.get("median_reprojection_error_px"),
               "track_length": st.get("mean_track_length"), "seconds": round(sec, 1)}
        print(json.dumps(row), flush=True)
        rows.append(dict(row, relative=100 * r["relative"], p90_relative=100 * r["p90_relative"]))
    print(md_table(rows, [("capture", "capture"), ("min_angle_deg", "smallest triangulation angle (deg)"),
                          ("points", "triangulated points"), ("reference_points", "COLMAP points"),
                          ("relative", "median distance to the nearest COLMAP point (% of their spread)"),
                          ("p90_relative", "90th percentile (%)", 1), ("reprojection_px", "reprojection error (px)"),
                          ("track_length", "mean track length"), ("seconds", "seconds", 0)]))
    return 0


# ----------------------------------------------------------------------------- modes: appearance, inside-out
APPEARANCE_DOC = """Per-image appearance (``reconstruct --appearance``) on a copy of lego_200 whose photos' exposures differ.

The copy (``ssgwarp.procedural.vary_exposures``, written once into ``--work``) is trained at ``--iters`` steps; its
training views' renders are scored against the UNMODIFIED images (docs/reconstruction.md, "Per-image appearance").
``--runs``: ``CAPTURE:MODE``, CAPTURE ``orig`` (lego_200) or ``exp`` (the copy), MODE auto / on / off.

    python benchmarks/captures.py appearance --runs orig:auto exp:auto exp:off --iters 600
"""
INSIDE_OUT_DOC = """The procedural inside-out capture's held-out error region by region (known truth), with and without sky.

PSNR per region (ground, buildings, sky, railing), of the whole image and of the floaters (docs/reconstruction.md,
"Where the error of an inside-out capture sits"). ``--runs``: ``SKY:ITERS[:FAR]``: SKY ``--sky`` auto / on / off
(none: the default), FAR ``DefaultStrategy.far_split_px`` (0: off, the default).

    python benchmarks/captures.py inside-out --runs off:150 on:150 --width 48 --views 16 --density 0.25 --device cpu
"""
REGIONS = {"ground": 0, "buildings": 1, "sky": 2, "railing": 3}


def mode_parser(mode: str, doc: str, work: str, runs: list[str]) -> argparse.ArgumentParser:
    """The options both modes share: ``--runs``, ``--width``, ``--device``, ``--work``, ``--out``."""
    import tempfile

    import torch

    p = parser(f"captures.py {mode}", doc)
    p.add_argument("--runs", nargs="+", default=runs, help="default: %(default)s")
    p.add_argument("--width", type=int, default=None, help="image width (default: as stored; inside-out 96)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / work, help="the captures written once")
    p.add_argument("--out", type=Path, default=None, help="append the rows as JSON lines here")
    return p


def trained(spec: str, form: str, data, a, **kw):
    """``(the two halves of spec, the trained Trainer)``."""
    from ssgwarp.reconstruction.trainer import Trainer

    x, sep, y = spec.partition(":")
    if not sep:
        raise SystemExit(f"--runs {spec!r}: expected {form}")
    tr = Trainer(data(x), iters=int(kw.pop("iters", 0) or y), device=a.device, progress=False, **kw)
    tr.train()
    return (x, y), tr


def finish(row: dict, tr, a, rows: list[dict]) -> None:
    """Complete a mode's row (Gaussians, time, machine, date), print it as JSON and keep it."""
    row.update(gaussians=tr.num_gaussians, train_seconds=round(tr.elapsed, 1), machine=machine(a.device),
               date=time.strftime("%Y-%m-%d"))
    print(json.dumps(row, default=str), flush=True)
    append_jsonl(a.out, row)
    rows.append(row)


def appearance_main(argv=None) -> int:
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.procedural import vary_exposures
    from ssgwarp.services.losses import psnr

    p = mode_parser("appearance", APPEARANCE_DOC, "ssgwarp_appearance", ["orig:auto", "exp:auto", "exp:off"])
    p.add_argument("--iters", type=int, default=600)
    p.add_argument("--seed", type=int, default=0, help="the exposures' seed (default 0)")
    a = p.parse_args(argv)
    src = data_root() / "lego_200"
    varied = a.work / f"lego_200_exposures_{a.seed}"
    if not varied.is_dir():
        a.work.mkdir(parents=True, exist_ok=True)
        vary_exposures(src, varied, seed=a.seed)
    cache, rows = {}, []

    def data(name):
        if name not in ("orig", "exp"):
            raise SystemExit(f"--runs: capture {name!r}: choose orig or exp")
        if name not in cache:
            cache[name] = load_dataset(src if name == "orig" else varied, width=a.width, progress=False,
                                       device=a.device)
        return cache[name]

    for spec in a.runs:
        (name, mode), tr = trained(spec, "CAPTURE:MODE", data, a, iters=a.iters, appearance=spec.partition(":")[2])
        truth, ids = data("orig"), list(tr.data.train_ids)
        rec = tr.appearance_record or {"use": False, "why": "run ended before the probe"}
        finish({"capture": name, "mode": mode, "iters": a.iters, "width": tr.data.width,
                "decision": f"{'on' if rec['use'] else 'off'} ({rec.get('exposure_spread', '-')})",
                "train_psnr_vs_unmodified": sum(float(psnr(tr.render([i]), truth.images[i][None])) for i in ids)
                / len(ids), "heldout_psnr": tr.evaluate()["psnr"], "eval_protocol": tr.eval_protocol,
                "appearance": rec, "fitted": None if tr.appearance is None else tr.appearance.summary()}, tr, a, rows)
    print(md_table(rows, [("capture", "capture (exp: varied exposures)"), ("width", "px"), ("mode", "--appearance"),
                          ("decision", "decision (spread)"), ("train_psnr_vs_unmodified", "train views vs unmodified (dB)"),
                          ("heldout_psnr", "held-out (dB)"), ("eval_protocol", "protocol"), ("gaussians", "Gaussians"),
                          ("train_seconds", "train (s)"), ("machine", "machine")]))
    return 0


def region_errors(tr, ids, depth) -> dict:
    """PSNR per region and of the floaters over the held-out views (``ids``, ``depth``: every view's truth)."""
    import torch

    from ssgwarp.raster.rendering import render_views

    se, n = {}, {}
    for i in tr.data.test_ids:
        err = ((tr.render([i])[0].cpu() - tr.data.images[i].cpu()) ** 2).sum(-1)
        v = render_views(tr.scene.detach(), tr.data.cameras[i], depth=True)
        masks = {k: ids[i] == r for k, r in REGIONS.items()}
        masks["all"] = torch.ones_like(err, dtype=torch.bool)
        masks["floaters"] = (v.alpha[0].cpu() > 0.5) & (v.depth[0].cpu() < 0.5 * depth[i].cpu())
        for k, m in masks.items():
            se[k] = se.get(k, 0.0) + float(err[m].sum())
            n[k] = n.get(k, 0) + int(m.sum())
    out = {f"psnr_{k}": round(-10 * math.log10(max(se[k] / (3 * n[k]), 1e-10)), 2) if n[k] else float("nan")
           for k in se}
    out["floater_share"] = round(n["floaters"] / n["all"], 4)
    out["region_share"] = {k: round(n[k] / n["all"], 3) for k in REGIONS}
    out["error_share"] = {k: round(se[k] / se["all"], 3) for k in [*REGIONS, "floaters"]}
    return out


def inside_out_main(argv=None) -> int:
    import torch

    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.core.fileio import write_image
    from ssgwarp.procedural import build_inside_out, render_views, rig_cameras, surface_points, write_transforms_dataset
    from ssgwarp.raster.rendering import render_views as render_depth
    from ssgwarp.reconstruction.far_field import FAR_EXTENTS
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.strategy import DefaultStrategy

    p = mode_parser("inside-out", INSIDE_OUT_DOC, "ssgwarp_inside_out", ["off:600", "on:600"])
    p.add_argument("--views", type=int, default=36, help="views of the rig (every 8th held out)")
    p.add_argument("--density", type=float, default=1.0, help="ground-truth Gaussians (x about 30,000)")
    p.add_argument("--renders", type=Path, default=None, help="one PNG per run: held-out truth above, render below")
    p.add_argument("--points", type=int, default=0, help="N points of the truth (procedural.surface_points)")
    p.add_argument("--recipe", nargs="+", default=[], metavar="KEY=NUMBER", help="Recipe fields or DefaultStrategy knobs for every run")
    a = p.parse_args(argv)
    width = a.width or 96
    gt = build_inside_out(a.density, railing=True)
    cams = rig_cameras(a.views, width, width * 3 // 4)
    images, ids = render_views(gt, cams)
    depth = render_depth(gt.scene, cams, depth=True).depth
    folder = a.work / f"insideout_railing_{width}_{a.views}"
    if not (folder / "transforms.json").is_file():
        write_transforms_dataset(folder, images, cams)
    data = load_dataset(folder, progress=False, device=a.device)
    if a.points:  # a stand-in for SfM points (default: the loader's)
        data.points, data.points_source = surface_points(gt, a.points), "colmap"
    (rv, sv), rows = knobs(a.recipe, Recipe(), DefaultStrategy()), []   # (a Recipe field, else the strategy's knob)
    for spec in a.runs:
        sky, iters, far = (spec.split(":") + ["", ""])[:3]
        st, recipe = DefaultStrategy(**{**sv, **({"far_split_px": float(far)} if far else {})}), Recipe(**rv)
        _, tr = trained(f"{sky}:{iters}", "SKY:ITERS[:FAR]", lambda _: data, a, recipe=recipe, strategy=st,
                        **({} if sky == "none" else {"sky": sky}))
        finish({"sky": sky + ("" if (rec := tr.sky_record) is None else f" ({'on' if rec['use'] else 'off'})"),
                "sky_record": rec, "points": a.points or data.points_source, "recipe": {**rv, **sv}, "far_split_px": st.far_split_px
                if tr.strategy.far else 0, "far_gaussians": None if tr.strategy.center is None else int(((  # 5 extents out
                    tr.scene.means.detach() - tr.strategy.center).norm(dim=1) >= FAR_EXTENTS * tr.extent).sum()),
                "iters": tr.iters, "width": width, "views": a.views, "psnr": tr.evaluate()["psnr"],
                **region_errors(tr, ids, depth),
                "backdrop": None if tr.backdrop is None else tr.backdrop.record()}, tr, a, rows)
        if a.renders:
            t = list(data.test_ids)[:4]
            pred = torch.cat([tr.render([i])[0].cpu() for i in t], 1)
            truth = torch.cat([data.images[i].cpu() for i in t], 1)
            a.renders.mkdir(parents=True, exist_ok=True)
            write_image(a.renders / f"{spec.replace(':', '_')}.png", torch.cat([truth, pred], 0))
    for r in rows:
        r["floaters"] = f"{100 * r['floater_share']:.1f} %, {r['psnr_floaters']:.2f} dB"
    print(md_table(rows, [("sky", "sky"), ("far_split_px", "far split (px)"), ("iters", "steps"), ("psnr", "PSNR all"),
                          ("psnr_ground", "ground"), ("psnr_buildings", "buildings"), ("psnr_sky", "sky"),
                          ("psnr_railing", "railing"), ("floaters", "floaters (share, PSNR)"), ("gaussians", "Gaussians"),
                          ("far_gaussians", "far Gaussians"), ("train_seconds", "train (s)"), ("machine", "machine")]))
    return 0


MODES = {"appearance": appearance_main, "inside-out": inside_out_main}


def main(argv=None) -> int:
    return dispatch(MODES, table_main, argv)


if __name__ == "__main__":
    sys.exit(main())
