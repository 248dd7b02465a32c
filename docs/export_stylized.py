"""Export round trips of a stylized scene (docs/export.md, "Stylized scenes"): every format at every SH degree
the scene carries, with its size and the worst PSNR of the file read back against the scene.

Without ``--run`` it makes its own small stylized scene first, as a new user would: the LLFF fern capture
(images_8 at 126 px wide, shared data) reconstructed at SH degree 3 (``--iters``, default 300), then
``ssgwarp stylize`` with candy.jpg (weight-free, default options; 30 steps), on the CPU.

    python docs/export_stylized.py                      # fern, small (a few minutes on 2 CPU cores)
    python docs/export_stylized.py --run runs/fern-candy --views 3
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))   # (the benchmarks' harness: where the shared data is)

from harness import data_root  # noqa: E402


def make_run(work: Path, iters: int) -> Path:
    from ssgwarp.cli import main

    data = data_root()
    if not (data / "llff_fern").is_dir():
        sys.exit("no shared data (../shared/data): pass --run RUN")
    fern, style = data / "llff_fern", data / "styles" / "candy.jpg"
    common = ["--device", "cpu", "--seed", "0"]
    if main(["reconstruct", str(fern), "--images", "images_8", "--width", "126", "--iters", str(iters),
             "--sh-degree", "3", "--max-gaussians", "30000", "--out", str(work / "fern"), "--quiet", *common]):
        sys.exit("reconstruct failed")
    if main(["stylize", str(work / "fern"), "--style", str(style), "--out", str(work / "fern-candy"),
             "--iters", "30", "--path-frames", "0", "--quiet", *common]):
        sys.exit("stylize failed")
    return work / "fern-candy"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, default=None, help="a stylized run folder (default: make a small one)")
    ap.add_argument("--iters", type=int, default=300, help="reconstruction steps of the run it makes")
    ap.add_argument("--views", type=int, default=3, help="cameras of the round-trip check")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--keep", type=Path, default=None, help="make the run in this folder and keep it")
    args = ap.parse_args()
    from ssgwarp.formats.ply import read_ply
    from ssgwarp.evaluation.export import export

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run = args.run or make_run(args.keep or tmp, args.iters)
        scene = read_ply(run / "scene.ply")
        meta = json.loads((run / "metrics.json").read_text()) if (run / "metrics.json").is_file() else {}
        print(f"{run}: {len(scene)} Gaussians, SH degree {scene.sh_degree} ({(meta.get('sh') or {}).get('note', '')})")
        print("| format | SH degree | bytes a Gaussian | PSNR (dB, worst of views) |\n|---|---|---|---|")
        rows = []
        for fmt, ext in (("ply", "ply"), ("compressed-ply", "compressed.ply"), ("spz", "spz"), ("splat", "splat")):
            for deg in range(scene.sh_degree + 1 if fmt != "splat" else 1):
                r = export(run, tmp / f"o{deg}.{ext}", fmt, sh_degree=deg, views=args.views, force=True)
                worst = min(r["psnr"]) if r["psnr"] else None
                rows.append({"format": fmt, "sh_degree": deg, "bytes_per_gaussian": r["bytes"] / r["gaussians"],
                             "psnr_worst": worst})
                shown = "n/a" if worst is None else "identical" if worst >= 100 else f"{worst:.1f}"
                print(f"| {fmt} | {deg} | {r['bytes'] / r['gaussians']:.1f} | {shown} |")
        # what .splat loses: it clips each base colour to [0, 1] (8 bits); how far beyond that range the
        # stylized scene's base colours lie, against its source's (the reconstruction it was stylized from)
        source = Path(meta.get("source_scene", "")) if meta.get("source_scene") else None
        C0 = 0.28209479177387814
        for label, folder in (("stylized", run), ("source", source)):
            if folder is None or not (folder / "scene.ply").is_file():
                continue
            sc = read_ply(folder / "scene.ply")
            rgb = 0.5 + C0 * sc.sh_dc
            excess = (rgb - rgb.clamp(0, 1)).abs()
            line = (f"{label}: base colour beyond [0, 1] by {excess.mean().item():.4f} on average (max "
                    f"{excess.max().item():.3f}), {100 * (excess > 0).any(-1).float().mean().item():.1f} % of the Gaussians")
            if label == "source" and args.run is None:
                r = export(folder, tmp / "src.splat", "splat", sh_degree=0, views=args.views, force=True)
                line += f"; its .splat round trip {min(r['psnr']):.1f} dB"
            print(line)
            rows.append({"scene": label, "mean_excess": excess.mean().item(), "max_excess": excess.max().item()})
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
