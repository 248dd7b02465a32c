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
