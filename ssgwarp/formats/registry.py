"""The splat file formats ssgwarp writes and reads, by name: ``ply`` (the INRIA 3DGS layout,
:mod:`ssgwarp.formats.ply`), ``compressed-ply`` (PlayCanvas / SuperSplat,
:mod:`ssgwarp.formats.compressed_ply`), ``splat`` (antimatter15, :mod:`ssgwarp.formats.splat`),
``spz`` (Niantic, :mod:`ssgwarp.formats.spz`).

* :func:`write_scene` -- ``scene`` to ``path`` in a named format, atomically;
* :func:`read_scene` -- any of them back into a :class:`GaussianScene` (in our frame),
  the format found from the file's first bytes (and ``.splat``'s name) by :func:`detect_format`;
* :func:`format_for_path` -- the format a file name asks for (``.compressed.ply`` before ``.ply``).
"""
from __future__ import annotations

import difflib
from pathlib import Path
from typing import Optional

from ..errors import InputError
from ..raster.scene import GaussianScene
from .ply import read_ply, write_ply
from .compressed_ply import is_compressed_ply, read_compressed_ply, write_compressed_ply
from .splat import read_splat, write_splat
from .spz import MAGIC as SPZ_MAGIC, read_spz, write_spz

# name -> (file suffix, highest SH degree it holds)
FORMATS: dict[str, tuple[str, int]] = {
    "ply": (".ply", 3),
    "compressed-ply": (".compressed.ply", 3),
    "spz": (".spz", 3),
    "splat": (".splat", 0),
}


def check_format(name: str) -> str:
    """``name`` if it is a format of :data:`FORMATS`, else an InputError listing them."""
    if name in FORMATS:
        return name
    near = difflib.get_close_matches(str(name), list(FORMATS), n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    raise InputError(f"unknown format {name!r}{hint}; choose one of {', '.join(FORMATS)}")


def format_for_path(path: str | Path) -> Optional[str]:
    """The format a file name's suffix names, or None."""
    name = Path(path).name.lower()
    for fmt, (suffix, _) in sorted(FORMATS.items(), key=lambda kv: -len(kv[1][0])):
        if name.endswith(suffix):
            return fmt
    return None


def write_scene(path: str | Path, scene: GaussianScene, fmt: str, *, spz_sh_bits=None) -> Path:
    """Write ``scene`` to ``path`` as ``fmt``; a ``ply`` keeps the scene as it is (identities
    included), the other formats hold what they can (``splat``: SH degree 0). ``spz_sh_bits``:
    (band 1, higher bands) significant bits of SPZ's SH (default :data:`ssgwarp.formats.spz.SH_BITS`)."""
    fmt = check_format(fmt)
    if fmt == "spz":
        return write_spz(path, scene) if spz_sh_bits is None else write_spz(path, scene, sh_bits=tuple(spz_sh_bits))
    if spz_sh_bits is not None:
        raise InputError(f"SH bits are an option of the spz format, not of {fmt}")
    writer = {"ply": write_ply, "compressed-ply": write_compressed_ply, "splat": write_splat}[fmt]
    return writer(path, scene)


def detect_format(path: str | Path) -> str:
    """The format of the file at ``path``, from its content (a ``.splat`` has no header: its name)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head.startswith(b"ply"):
        return "compressed-ply" if is_compressed_ply(path) else "ply"
    if head[:2] == b"\x1f\x8b" or head == SPZ_MAGIC.to_bytes(4, "little"):
        return "spz"
    if path.suffix.lower() == ".splat":
        return "splat"
    raise InputError(f"{path}: not a splat file ssgwarp reads (PLY, compressed PLY, SPZ or .splat)")


def read_scene(path: str | Path, fmt: Optional[str] = None) -> GaussianScene:
    """Read a scene written in any of :data:`FORMATS` (``fmt``: found from the file when None)."""
    fmt = detect_format(path) if fmt is None else check_format(fmt)
    reader = {"ply": read_ply, "compressed-ply": read_compressed_ply, "spz": read_spz, "splat": read_splat}[fmt]
    return reader(path)
