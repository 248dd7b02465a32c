"""Regenerate the sizes and round-trip table of docs/export.md and docs/your_splats.md ("What each
format keeps and loses") from a run folder:

    ssgwarp reconstruct ../shared/data/llff_fern --images images_8 --quick --iters 300 --out /tmp/fern
    python docs/export_table.py /tmp/fern            # prints the markdown table (CPU, about a minute)

Each row is one ``ssgwarp export`` (the library call the command makes) into a temporary folder: the
file's size, bytes a Gaussian, how much smaller than the run's ``scene.ply``, the PSNR of renders of the
file read back against renders of the scene at the same SH degree (worst of ``--views`` cameras, held-out
ones first), the time of the export without that check, and what an independent reader (gsply, where it
reads the format) says of the file."""
from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

from ssgwarp.evaluation.export import export

ROWS = [("ply", "s.ply", {}, None), ("compressed-ply", "s.compressed.ply", {}, None),
        ("spz", "s.spz", {}, None), ("spz", "s3.spz", {"spz_version": 3}, "--spz-version 3"),
        ("spz", "s54.spz", {"spz_sh_bits": (5, 4)}, "--spz-sh-bits 5,4"),
        ("sog", "s.sog", {}, None), ("glb", "s.glb", {}, None)]
DEGREES = (3, 1, 0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run folder holding scene.ply and cameras.json")
    ap.add_argument("--views", type=int, default=3, help="cameras for the round-trip PSNR (default 3)")
    args = ap.parse_args()
    print(f"<!-- {args.run}, {platform.processor() or platform.machine()}, {time.strftime('%Y-%m-%d')} -->")
    print("| format | options | SH degree | MB | bytes a Gaussian | smaller than `scene.ply` | PSNR (dB, worst view) "
          "| export time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    rows = [(d, r) for d in DEGREES for r in ROWS] + [(0, ("splat", "s.splat", {}, None))]
    with tempfile.TemporaryDirectory() as tmp:
        for degree, (fmt, name, opts, label) in rows:
            out = Path(tmp) / f"{degree}-{name}"
            t = time.perf_counter()
            export(args.run, out, fmt, sh_degree=degree, views=0, **opts)
            seconds = time.perf_counter() - t
            r = export(args.run, out, fmt, sh_degree=degree, views=args.views, force=True, **opts)
            worst = min(r["psnr"]) if r["psnr"] else float("nan")
            psnr = "identical" if worst >= 100 else f"{worst:.1f}"
            print(f"| {fmt} | {label or ''} | {degree} | {r['bytes'] / 1e6:.2f} | {r['bytes'] / r['gaussians']:.1f} "
                  f"| {r['source_bytes'] / r['bytes']:.1f}x | {psnr} | {seconds:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
