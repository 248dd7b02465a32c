"""The splat file formats ssgwarp reads and writes, by name -- one detection, one reader, one writer:

=================  ====================  ==========  =================================================
name               file                  SH degree   module
=================  ====================  ==========  =================================================
``ply``            ``.ply``              3           :mod:`ssgwarp.formats.ply` (INRIA 3DGS layout)
``compressed-ply`` ``.compressed.ply``   3           :mod:`ssgwarp.formats.compressed_ply` (SuperSplat)
``spz``            ``.spz``              3 (4 read)  :mod:`ssgwarp.formats.spz` (Niantic, versions 2-4)
``splat``          ``.splat``            0           :mod:`ssgwarp.formats.splat` (antimatter15)
``ksplat``         ``.ksplat`` (read)    3           :mod:`ssgwarp.formats.ksplat` (GaussianSplats3D)
``sog``            ``.sog``, ``meta.json``  3        :mod:`ssgwarp.formats.sog` (PlayCanvas, version 2)
``glb``            ``.glb``              3           :mod:`ssgwarp.formats.gltf` (KHR_gaussian_splatting)
=================  ====================  ==========  =================================================

* :func:`detect_format` -- the format of a file (or SOG folder) from its first bytes (``.splat`` and
  ``.ksplat``, which have no magic, from their names);
* :func:`read_scene` -- any of them into a :class:`GaussianScene` in our (RDF) frame;
* :func:`write_scene` -- ``scene`` to ``path`` in a named format, atomically;
* :func:`format_for_path` -- the format a file name asks for (``.compressed.ply`` before ``.ply``).
"""
from __future__ import annotations

import difflib
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import InputError, SsgwarpError
from ..raster.scene import GaussianScene
from .compressed_ply import is_compressed_ply, read_compressed_ply, write_compressed_ply
from .gltf import read_glb, write_glb
from .ksplat import read_ksplat
from .ply import read_ply, write_ply
from .sog import read_sog, write_sog
from .splat import read_splat, write_splat
from .spz import MAGIC as SPZ_MAGIC, read_spz, write_spz

# name -> (file suffix, highest SH degree it holds, written)
FORMATS: dict[str, tuple[str, int, bool]] = {
    "ply": (".ply", 3, True),
    "compressed-ply": (".compressed.ply", 3, True),
    "spz": (".spz", 3, True),
    "splat": (".splat", 0, True),
    "ksplat": (".ksplat", 3, False),
    "sog": (".sog", 3, True),
    "glb": (".glb", 3, True),
}
WRITABLE = [name for name, (_, _, w) in FORMATS.items() if w]
_READERS = {"ply": read_ply, "compressed-ply": read_compressed_ply, "spz": read_spz, "splat": read_splat,
            "ksplat": read_ksplat, "sog": read_sog, "glb": read_glb}


def check_format(name: str, *, writing: bool = False) -> str:
    """``name`` if it is a format of :data:`FORMATS` (one ssgwarp writes, with ``writing``), else an
    InputError listing them."""
    names = WRITABLE if writing else list(FORMATS)
    if name in names:
        return name
    if name in FORMATS:
        raise InputError(f"format {name!r} is read, not written; write one of {', '.join(WRITABLE)}")
    near = difflib.get_close_matches(str(name), names, n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    raise InputError(f"unknown format {name!r}{hint}; choose one of {', '.join(names)}")


def format_for_path(path: str | Path) -> Optional[str]:
    """The format a file name's suffix names (a SOG folder's ``meta.json`` names ``sog``), or None."""
    name = Path(path).name.lower()
    if name == "meta.json":
        return "sog"
    for fmt, (suffix, _, _) in sorted(FORMATS.items(), key=lambda kv: -len(kv[1][0])):
        if name.endswith(suffix):
            return fmt
    return None


def write_scene(path: str | Path, scene: GaussianScene, fmt: str, *, spz_sh_bits=None,
                spz_version: Optional[int] = None) -> Path:
    """Write ``scene`` to ``path`` as ``fmt``; a ``ply`` keeps the scene as it is (identities
    included), the other formats hold what they can (``splat``: SH degree 0). ``spz_sh_bits``:
    (band 1, higher bands) significant bits of SPZ's SH (default :data:`ssgwarp.formats.spz.SH_BITS`);
    ``spz_version``: 4 (default), or 3 / 2 for older viewers. A ``sog`` whose ``path`` is a
    ``meta.json`` is written as a folder, else as a bundle."""
    fmt = check_format(fmt, writing=True)
    if fmt == "spz":
        opts = {} if spz_sh_bits is None else {"sh_bits": tuple(spz_sh_bits)}
        return write_spz(path, scene, version=4 if spz_version is None else int(spz_version), **opts)
    if spz_sh_bits is not None or spz_version is not None:
        raise InputError(f"SH bits and versions are options of the spz format, not of {fmt}")
    writer = {"ply": write_ply, "compressed-ply": write_compressed_ply, "splat": write_splat, "sog": write_sog,
              "glb": write_glb}[fmt]
    return writer(path, scene)


def detect_format(path: str | Path) -> str:
    """The format of the file (or SOG folder) at ``path``, from its content (``.splat`` and ``.ksplat``
    have no header: their names)."""
    path = Path(path)
    if path.is_dir():
        if (path / "meta.json").is_file():
            return "sog"
        raise InputError(f"{path}: a folder without meta.json (a SOG folder holds meta.json and its WebP files)")
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head.startswith(b"ply"):
        return "compressed-ply" if is_compressed_ply(path) else "ply"
    if head[:2] == b"\x1f\x8b" or head == SPZ_MAGIC.to_bytes(4, "little"):
        return "spz"
    if head == b"PK\x03\x04" or path.name.lower() == "meta.json":
        return "sog"
    if head == b"glTF":
        return "glb"
    suffix = path.suffix.lower()
    if suffix in (".splat", ".ksplat"):
        return suffix[1:]
    raise InputError(f"{path}: not a splat file ssgwarp reads (PLY, compressed PLY, SPZ, .splat, .ksplat, SOG "
                     f"or glTF with KHR_gaussian_splatting)")


def read_scene(path: str | Path, device=None, *, fmt: Optional[str] = None) -> GaussianScene:
    """Read a scene written in any of :data:`FORMATS` (``fmt``: found from the file when None), on ``device``."""
    fmt = detect_format(path) if fmt is None else check_format(fmt)
    with np.errstate(all="ignore"):   # a damaged file's overflows end in the finite check below, not in warnings
        scene = _READERS[fmt](path)
    for name, t in scene.tensors().items():
        bad = ~torch.isfinite(t.reshape(len(scene), -1)).all(dim=1)
        if bad.any():
            raise InputError(f"{path}: {int(bad.sum())} Gaussian(s) have NaN/inf {name} values (corrupt file)")
    return scene if device is None else scene.to(device)


def is_splat_file(path: str | Path) -> bool:
    """True when ``path`` is a file whose first bytes (or, for headerless formats, name) make it a splat file."""
    path = Path(path).expanduser()
    if not path.is_file():
        return False
    try:
        detect_format(path)
    except (SsgwarpError, OSError, ValueError):
        return False
    return True


def read_splat_file(path: str | Path, device=None) -> GaussianScene:
    """A splat file a user gives a command (``import``, ``render``, ``stylize``, ``view``): :func:`read_scene`
    (whose detection and readers already refuse a missing, foreign or damaged file in one line), and a file
    that holds no Gaussians refused too."""
    path = Path(path).expanduser()
    scene = read_scene(path)
    if len(scene) == 0:
        raise InputError(f"{path}: holds no Gaussians")
    return scene if device is None else scene.to(device)
