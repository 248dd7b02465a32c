"""The capture quality table: every shared capture reconstructed as ``ssgwarp reconstruct`` does, held-out
quality next to a checked-in baseline; a capture that loses more than 0.2 dB is a REGRESSION.

Each run is :func:`ssgwarp.reconstruction.reconstruct.reconstruct` (the command's code path and defaults:
``--backdrop auto``, ``--init auto``, every 8th view held out, the capture's own resolution), once per
capture and setting:

* ``--captures``: ``fern8`` / ``fern4`` (LLFF fern ``images_8`` / ``images_4``), ``cup`` (``colmap_cup``),
  ``lego`` (``lego_200``, white background), ``livingroom`` (``livingroom_360``), ``bird`` (``bird_360``), or a
  capture folder ``PATH[:IMAGES]`` (default: the six shared captures);
* ``--settings``: ``7k`` (7,000 steps) and/or ``auto`` (``--iters auto``: the 30,000-step schedule with the
  stop rule; the row gives the steps run), or a step count; ``--iters N`` runs every setting at N steps
  instead (a CPU smoke run; such rows are compared only with a baseline row of the same step count).

A row: held-out PSNR / SSIM (LPIPS where its weights are found: ``ssgwarp weights``), Gaussians, training
time and the whole run's wall time (loading and triangulation, once per capture and counted in each of its
rows; evaluation), the steps run, the initial points
and the backdrop decision. Rows are appended to ``--out``/results.jsonl as each run ends; rows already
there are kept and not run again (rerun the same command to finish an interrupted table; ``--fresh`` starts
over), so a long table can be split over several commands. ``--out``/results.md gets the markdown table.

The baseline (``--baseline``, default ``benchmarks/captures_baseline.json``) holds one row per capture and
setting; ``--write-baseline`` replaces its rows by the table's (merged: captures not run keep theirs).
Exit status 1 when any row is more than ``--tolerance`` (0.2) dB below its baseline, else 0.
``--from FILE.jsonl`` tables rows written before (no runs). ``--backdrop-evidence`` prints the backdrop
decision's evidence per capture (no training; ``--thin N``: each capture's points also thinned to N).
``--triangulation`` measures the points
triangulated from the captures with COLMAP points (default fern ``images_8`` and ``images_4`` and the cup; an LLFF
capture from a copy without its ``sparse/``) against COLMAP's instead: the median distance to the nearest COLMAP
point as a percentage of the COLMAP points' spread (their median distance from their centre); no training.

    python benchmarks/captures.py --out runs/captures                             # the whole table (GPU)
    python benchmarks/captures.py --captures fern8 cup --settings 7k --out runs/captures
    python benchmarks/captures.py --captures lego --iters 20 --max-images 8 --device cpu --out /tmp/cap
    python benchmarks/captures.py --from runs/captures/results.jsonl --write-baseline
    python benchmarks/captures.py --backdrop-evidence --captures fern8 cup lego livingroom bird --thin 2000
    python benchmarks/captures.py --triangulation --captures fern8 --min-angle 1 2 3
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from harness import CAPTURES, capture_folder, data_root  # noqa: E402

from ssgwarp.core.fileio import atomic_path, write_json  # noqa: E402

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
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def read_baseline(path: Path) -> dict:
    """``{"capture/setting": row}`` of the baseline file (empty when there is none)."""
    if not path.is_file():
        return {}
    return dict(json.loads(path.read_text()).get("rows", {}))


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


def _f(v, spec=".2f"):
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def table(rows: list[dict], tolerance: float = TOLERANCE) -> str:
    lines = [f"| capture | setting | resolution | steps | held-out PSNR (dB) | baseline | change (REGRESSION: < "
             f"-{tolerance:g} dB) | SSIM | LPIPS | Gaussians | train (s) | run (s) | initial points | backdrop |",
             "|---|---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        d = r["delta_db"]
        change = (f"**{d:+.2f} REGRESSION**" if r["status"] == "REGRESSION" else
                  f"{d:+.2f}" if r["status"] == "ok" else r["status"])
        bd = r.get("backdrop") or {}
        back = "n/a" if bd.get("used") is None else (f"{bd.get('points', 0):,} far points" if bd["used"] else "none")
        lines.append(f"| {r['capture']} | {r['setting']} | {r.get('resolution', '')} | {r.get('iters')} | "
                     f"{_f(r.get('psnr'))} | {_f(r['base_psnr'])} | {change} | {_f(r.get('ssim'), '.4f')} | "
                     f"{_f(r.get('lpips'), '.3f')} | {r.get('gaussians', 0):,} | {_f(r.get('train_seconds'), '.0f')} | "
                     f"{_f(r.get('wall_seconds'), '.0f')} | {r.get('points') or ''} | {back} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--captures", nargs="+", default=list(CAPTURES),
                   help=f"{', '.join(CAPTURES)} or PATH[:IMAGES] (default: every shared capture)")
    p.add_argument("--settings", nargs="+", default=list(SETTINGS),
                   help="7k (7,000 steps), auto (--iters auto) or a step count (default: 7k auto)")
    p.add_argument("--iters", type=int, default=None, help="run every setting at this many steps (smoke runs)")
    p.add_argument("--max-images", type=int, default=None, help="use at most this many images (smoke runs)")
    p.add_argument("--width", type=int, default=None, help="resize the images to this width (smoke runs)")
    p.add_argument("--random-points", type=int, default=100_000,
                   help="initial points of captures without points where triangulation does not apply (default "
                        "100000, as the command; fewer for smoke runs)")
    p.add_argument("--data-root", type=Path, default=None, help=f"folder of the shared captures (default {data_root()})")
    p.add_argument("--device", default=None, help="cuda when available, else cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("benchmark-captures"),
                   help="folder for results.jsonl, results.md and the run folders")
    p.add_argument("--fresh", action="store_true", help="drop the rows already in --out/results.jsonl")
    p.add_argument("--keep-runs", action="store_true", help="keep each run's scene.ply")
    p.add_argument("--from", dest="from_file", type=Path, default=None,
                   help="table the rows of this results.jsonl against the baseline (no runs)")
    p.add_argument("--baseline", type=Path, default=BASELINE, help=f"baseline file (default {BASELINE.name})")
    p.add_argument("--tolerance", type=float, default=TOLERANCE, help="dB lost that counts as a regression (0.2)")
    p.add_argument("--write-baseline", action="store_true",
                   help="write the table's rows into the baseline file (other rows kept)")
    p.add_argument("--triangulation", action="store_true",
                   help="measure the triangulated points of fern images_8 against COLMAP's instead (no training)")
    p.add_argument("--backdrop-evidence", action="store_true",
                   help="print the backdrop decision's evidence per capture instead (no training)")
    p.add_argument("--thin", type=int, default=None,
                   help="with --backdrop-evidence: also each capture with its points thinned to this many")
    p.add_argument("--min-angle", type=float, nargs="+", default=None,
                   help="with --triangulation: the smallest triangulation angles (degrees) to compare (default: "
                        "triangulate()'s)")
    p.add_argument("--no-progress", action="store_true")
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
        import torch

        device = torch.device(a.device or ("cuda" if torch.cuda.is_available() else "cpu"))
        if device.type == "cuda" and not torch.cuda.is_available():
            raise SystemExit("CUDA is not available (pass --device cpu for a (slow) CPU run)")
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
                with atomic_path(results) as tmp:
                    tmp.write_text("".join(json.dumps(x) + "\n" for x in done.values()))
    rows = compare(rows, baseline, a.tolerance)
    md = table(rows, a.tolerance)
    bad = [key(r) for r in rows if r["status"] == "REGRESSION"]
    print(f"\n{time.strftime('%Y-%m-%d')}, baseline {a.baseline.name}\n\n{md}")
    if a.from_file is None:
        with atomic_path(a.out / "results.md") as tmp:
            tmp.write_text(md + "\n")
    if a.write_baseline:
        write_baseline(a.baseline, rows, baseline)
        print(f"wrote {a.baseline} ({len(rows)} rows)")
        return 0
    if bad:
        print(f"REGRESSION (more than {a.tolerance:g} dB below the baseline): {', '.join(bad)}")
        return 1
    return 0


def backdrop_evidence(a) -> int:
    """The backdrop decision's evidence per capture (no training): camera layout, initial points, their image
    coverage, the uncovered and textured cells, the cells a plane sweep places beyond twice the points' depth,
    the old rule (coverage < 90%) and today's decision; ``--thin N``: also each capture with its points thinned to
    N (seeded: a sparse COLMAP model)."""
    import torch

    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.reconstruction.backdrop import MIN_COVERAGE, far_evidence, plan_backdrop

    lines = ["| capture | layout | initial points | coverage | uncovered cells | textured of those | far cells | "
             "coverage < 90% (before) | backdrop now | seconds |", "|---|---|---|---:|---:|---:|---:|---|---|---:|"]
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
            rows.append(row)
            print(json.dumps(row), flush=True)
            lines.append(f"| {spec} | {plan.layout} | {len(xyz):,} {data.points_source}"
                         f"{' (thinned)' if thin else ''} | {plan.coverage:.0%} | {ev['uncovered']:.0%} | "
                         f"{ev['textured']:.0%} | {ev['far']:.1%} | {'yes' if row['before'] else 'no'} | "
                         f"{'yes' if plan.use else 'no'} ({plan.why}) | {sec:.1f} |")
    print("\n".join(lines))
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

    caps = [c for c in a.captures if c != "lego" and c != "livingroom" and c != "bird"] \
        if a.captures == list(CAPTURES) else a.captures
    lines = ["| capture | smallest triangulation angle | triangulated points | COLMAP points | median distance to the nearest COLMAP point "
             "(% of their spread) | 90th percentile (%) | reprojection error (px) | mean track length | "
             "seconds |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
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
        lines.append(f"| {spec} | {angle:g} deg | {r['points']:,} | {r['reference_points']:,} | {100 * r['relative']:.2f} % | "
                     f"{100 * r['p90_relative']:.1f} % | {_f(row['reprojection_px'])} | {_f(row['track_length'])} | "
                     f"{sec:.0f} |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
