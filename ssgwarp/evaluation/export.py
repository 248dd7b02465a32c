"""Export a run's scene for other viewers: ``ssgwarp export RUN --format F --out FILE``.

Formats (:mod:`ssgwarp.formats.registry`): ``ply`` (the INRIA 3DGS layout, float32),
``compressed-ply`` (PlayCanvas / SuperSplat, chunks of 256 quantised Gaussians), ``spz``
(Niantic, version 4 with zstd streams, or ``--spz-version 3`` / 2 in gzip, converted to SPZ's RUB axes),
``splat`` (antimatter15, 32 bytes a Gaussian, SH degree 0), ``sog`` (PlayCanvas SOG: a ``.sog`` bundle,
or a folder when ``--out`` is its ``meta.json``) and ``glb`` (glTF with KHR_gaussian_splatting, float32).
``.ksplat`` files are read (as a source), not written. ``--sh-degree N`` keeps the SH bands up to N. The file is written atomically and
an existing one is kept unless ``--force``. The export is read back and compared: the size
against the run's ``scene.ply`` and, where the run has cameras, the PSNR of renders of the file
read back against renders of the scene (``--check-views``; the quantisation error alone: both at
the exported SH degree).

Only the appearance is exported: Gaussian Grouping's identity encodings stay in ``RUN/scene.ply``.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import torch

from ..formats.registry import FORMATS, WRITABLE, check_format, format_for_path, read_scene, write_scene
from ..formats.sog import sog_names
from ..errors import InputError, SsgwarpError
from ..raster.rendering import render_views
from ..services.losses import psnr
from ..services.runs import Run, claim


def _source(run_dir: Path) -> tuple[Path, Optional[Run]]:
    """The scene file to export and the run it belongs to (None for a bare file or a run whose
    cameras cannot be read: no render check then)."""
    run_dir = Path(run_dir).expanduser()
    if run_dir.is_file():
        return run_dir, None
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: run folder not found")
    if (run_dir / "meta.json").is_file() and not (run_dir / "scene.ply").is_file():
        return run_dir, None   # a SOG folder
    if not (run_dir / "scene.ply").is_file():
        raise InputError(f"{run_dir}: no scene.ply (expected a `ssgwarp reconstruct` or `ssgwarp stylize` "
                         f"output, or give a scene file)")
    try:
        return run_dir / "scene.ply", Run.open(run_dir)
    except InputError:
        return run_dir / "scene.ply", None


def _choose_format(fmt: Optional[str], out: Path) -> str:
    if fmt is None:
        fmt = format_for_path(out)
        if fmt is None:
            raise InputError(f"--out {out.name}: cannot tell the format from its name; pass --format "
                             f"({', '.join(WRITABLE)})")
        return check_format(fmt, writing=True)
    fmt = check_format(fmt, writing=True)
    named = format_for_path(out)
    if named not in (fmt, None) and not (fmt == "compressed-ply" and named == "ply"):
        print(f"ssgwarp: note: {out.name} ends like a {named} file but is written as {fmt}; viewers choose "
              f"their reader by the extension ({FORMATS[fmt][0]})", file=sys.stderr)
    return fmt


def _degree(scene, fmt: str, sh_degree: Optional[int]) -> int:
    limit = FORMATS[fmt][1]
    if sh_degree is None:
        return min(scene.sh_degree, limit)
    if not 0 <= sh_degree <= 3:
        raise InputError(f"--sh-degree {sh_degree}: must be 0..3")
    if sh_degree > scene.sh_degree:
        raise InputError(f"--sh-degree {sh_degree}: the scene carries SH degree {scene.sh_degree}; "
                         f"choose 0..{scene.sh_degree}")
    if sh_degree > limit:
        raise InputError(f"--sh-degree {sh_degree}: the {fmt} format holds SH up to degree {limit} "
                         f"(use spz, sog, glb or compressed-ply for view-dependent colour)")
    return sh_degree


@torch.no_grad()
def check_views(scene, exported, run: Run, views: int, device="cpu") -> list[float]:
    """PSNR (dB) of renders of ``exported`` against ``scene`` on ``views`` of the run's cameras
    (held-out ones first, evenly spaced), over the run's background."""
    cams = run.cameras

    def spaced(ids: list[int], k: int) -> list[int]:
        k = min(k, len(ids))
        return [ids[round(i * (len(ids) - 1) / max(1, k - 1))] for i in range(k)]

    idx = spaced(run.test_ids, views)
    idx += spaced([i for i in run.train_ids if i not in idx], views - len(idx))
    bg = run.background(run.data.get("background") or (1.0, 1.0, 1.0))
    scene, exported, out = scene.to(device), exported.to(device), []
    for i in idx:
        cam = cams[[i]].to(device)
        a = render_views(scene, cam, bg, depth=False).rgb
        b = render_views(exported, cam, bg, depth=False).rgb
        out.append(float(psnr(b, a)))
    return out


def export(run_dir: str | Path, out: str | Path, fmt: Optional[str] = None, *, sh_degree: Optional[int] = None,
           force: bool = False, views: int = 2, device="cpu", spz_sh_bits=None,
           spz_version: Optional[int] = None) -> dict:
    """Export ``run_dir``'s scene (or a scene file in any of the formats) to ``out``; returns what was
    written and measured: ``format``, ``path``, ``bytes``, ``source_bytes``, ``gaussians``, ``sh_degree``,
    ``psnr`` (one per checked view)."""
    src, run = _source(Path(run_dir))
    out = Path(out).expanduser()
    if out.is_dir():
        raise InputError(f"--out {out}: is a folder; give a file name, e.g. {out / ('scene' + FORMATS['spz'][0])}")
    if out.resolve() == src.resolve():
        raise InputError(f"--out {out}: is the scene being exported; choose another file")
    fmt = _choose_format(fmt, out)
    if views < 0:
        raise InputError(f"--check-views {views}: must be >= 0")
    if spz_sh_bits is not None and fmt != "spz":
        raise InputError(f"--spz-sh-bits: an option of the spz format, not of {fmt}")
    if spz_version is not None and (fmt != "spz" or spz_version not in (2, 3, 4)):
        raise InputError(f"--spz-version {spz_version}: " + ("an option of the spz format, not of " + fmt
                         if fmt != "spz" else "choose 4 (the default), or 3 or 2 for viewers older than SPZ 4"))
    folder = fmt == "sog" and out.name.lower() == "meta.json"
    names = sog_names() if folder else [out.name]
    claim(out.parent, names, force=force, what="a file", resumable=False)
    scene = read_scene(src)
    degree = _degree(scene, fmt, sh_degree)
    scene = scene.with_sh_degree(degree).replace(identities=None)
    write_scene(out, scene, fmt, spz_sh_bits=spz_sh_bits, spz_version=spz_version)
    back = read_scene(out, fmt=fmt)
    if len(back) != len(scene) or back.sh_degree != degree:
        raise SsgwarpError(f"{out}: read back {len(back)} Gaussians at SH degree {back.sh_degree}, "
                         f"wrote {len(scene)} at {degree}")
    size = sum((out.parent / nm).stat().st_size for nm in names if (out.parent / nm).is_file())
    source_bytes = sum(f.stat().st_size for f in src.iterdir() if f.is_file()) if src.is_dir() else src.stat().st_size
    return {"format": fmt, "path": str(out), "bytes": size, "source_bytes": source_bytes,
            "gaussians": len(scene), "sh_degree": degree,
            "psnr": check_views(scene, back, run, views, device) if run is not None else []}


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
