"""``ssgwarp export``: a run's scene (or a splat file) in another format (:func:`ssgwarp.evaluation.export.export`)."""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..evaluation.export import export
from ..formats.registry import WRITABLE


def add_arguments(parser) -> None:
    parser.add_argument("run_dir", type=Path,
                        help="a run folder holding scene.ply (reconstruct or stylize output), or a scene file "
                             "in any of the formats (PLY, compressed PLY, SPZ, .splat, .ksplat, SOG, GLB: a "
                             "conversion)")
    parser.add_argument("--out", type=Path, required=True,
                        help="the file to write (.ply, .compressed.ply, .spz, .splat, .sog, .glb; a SOG folder: "
                             "FOLDER/meta.json)")
    parser.add_argument("--format", default=None, metavar="FORMAT",
                        help=f"{', '.join(WRITABLE)} (default: from --out's name)")
    parser.add_argument("--sh-degree", type=int, default=None, metavar="N",
                        help="keep SH bands up to N (default: all the scene has, as far as the format holds: "
                             "splat 0, the others 3)")
    parser.add_argument("--check-views", type=int, default=2, metavar="N",
                        help="render N of the run's cameras from the scene and from the file read back and report "
                             "the PSNR (default 2; 0: no check)")
    parser.add_argument("--spz-sh-bits", default=None, metavar="B1,BR",
                        help="spz: significant bits of the SH coefficients of band 1 and of the higher bands, "
                             "1..8 each (default 6,5; the SPZ reference writer's 5,4 makes smaller files, 8,8 the "
                             "most faithful; readers need not know)")
    parser.add_argument("--spz-version", type=int, default=None, metavar="V",
                        help="spz: 4 (default: zstd streams, Niantic's current format), or 3 / 2 (gzip) for "
                             "viewers that predate SPZ 4")
    parser.add_argument("--force", action="store_true", help="overwrite an existing --out file")


def _bits(text: str) -> tuple[int, int]:
    try:
        b = tuple(int(v) for v in text.split(","))
    except ValueError:
        b = ()
    if len(b) != 2 or not all(1 <= v <= 8 for v in b):
        raise InputError(f"--spz-sh-bits {text}: expected two numbers 1..8, e.g. 6,5")
    return b


def run(args) -> int:
    r = export(args.run_dir, args.out, args.format, sh_degree=args.sh_degree, force=args.force,
               views=args.check_views, device=args.device,
               spz_sh_bits=None if args.spz_sh_bits is None else _bits(args.spz_sh_bits),
               spz_version=args.spz_version)
    ratio = r["source_bytes"] / max(1, r["bytes"])
    size = f"{ratio:.1f}x smaller than" if ratio >= 1 else f"{1 / ratio:.1f}x the size of"
    print(f"{r['path']}: {r['format']}, {r['gaussians']} Gaussians, SH degree {r['sh_degree']}, "
          f"{r['bytes'] / 1e6:.2f} MB ({size} the source's {r['source_bytes'] / 1e6:.2f} MB)")
    if r["psnr"]:
        worst = min(r["psnr"])
        said = "identical renders" if worst >= 100 else f"PSNR {worst:.2f} dB"
        print(f"round trip: {said} (worst of {len(r['psnr'])} view(s); the file read back against the scene, "
              f"both at SH degree {r['sh_degree']})")
    elif args.check_views:
        print("round trip: not rendered (no run cameras to render from: a bare scene file, or a run whose "
              "cameras.json cannot be read)")
    return 0
