"""Any splat file in: the one place the commands (``import``, ``render``, ``stylize``, ``view``) read a splat
file a user gives them, whatever its format (PLY, compressed PLY, SPZ, ``.splat`` and whatever
:mod:`ssgwarp.capture.splat_formats` reads).

* :func:`read_splat_file` -- the file as a :class:`~ssgwarp.raster.scene.GaussianScene` (in ssgwarp's frame);
  a file that is no splat file, or a damaged one, is one :class:`~ssgwarp.errors.InputError` line naming it;
* :func:`is_splat_file` -- whether ``path`` is a file that reader takes (by its first bytes and name).
"""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError, SsgwarpError
from ..raster.scene import GaussianScene
from . import splat_formats

__all__ = ["read_splat_file", "is_splat_file"]


def is_splat_file(path: str | Path) -> bool:
    """True when ``path`` is a file whose first bytes (or, for headerless formats, name) make it a splat file."""
    path = Path(path).expanduser()
    if not path.is_file():
        return False
    try:
        splat_formats.detect_format(path)
    except (SsgwarpError, OSError, ValueError):
        return False
    return True


def read_splat_file(path: str | Path, device=None) -> GaussianScene:
    """The Gaussians of the splat file ``path`` (any format :mod:`ssgwarp.capture.splat_formats` reads), on
    ``device`` (None: the CPU)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a splat file")
    try:
        scene = splat_formats.read_scene(path)
    except SsgwarpError:
        raise
    except (ValueError, KeyError, IndexError, TypeError, EOFError, OSError, RuntimeError) as e:
        raise InputError(f"{path}: cannot read as a splat file ({type(e).__name__}: {e})") from None
    if len(scene) == 0:
        raise InputError(f"{path}: holds no Gaussians")
    return scene if device is None else scene.to(device)
