"""Gaussian scenes as PLY files in the INRIA 3DGS layout (common splat viewers open them).

One ``vertex`` element, float32 properties, in this order::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3K-1)  opacity  scale_0..2  rot_0..3  [obj_dc_0..E-1]

* ``f_dc_c`` = ``sh_dc[:, c]``; ``f_rest_{c*K + k}`` = ``sh_rest[:, k, c]`` (channel-major,
  as the INRIA code flattens ``[N, 3, K]``); ``K = (d+1)^2 - 1`` so the SH degree ``d``
  follows from the number of ``f_rest_*`` fields (0, 9, 24 or 45 -> degree 0..3).
* ``opacity`` is the logit, ``scale_*`` the log standard deviations, ``rot_*`` the raw
  wxyz quaternion, ``nx ny nz`` are zeros (kept for viewers that expect them).
* ``obj_dc_*`` are Gaussian Grouping identity encodings (absent before grouping).

:func:`read_points` reads any point cloud PLY (``x y z`` with ``red green blue`` or ``f_dc_*``) as
initial points (``ssgwarp reconstruct --init PATH.ply``).

Float32 scenes round-trip bit-exactly. Reading rejects, with an InputError naming the
file: unreadable/truncated files, a missing ``vertex`` element, missing or unexpected
fields, f_rest counts that match no SH degree, and NaN/inf values.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..core.fileio import atomic_path
from ..raster.scene import SH_C0, GaussianScene

_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_REST_TO_DEGREE = {3 * ((d + 1) ** 2 - 1): d for d in range(4)}


def field_names(sh_degree: int, identity_dim: int = 0) -> list[str]:
    """The property names, in file order, of a scene of ``sh_degree`` with ``identity_dim`` identity channels."""
    k = (sh_degree + 1) ** 2 - 1
    return (_BASE + [f"f_rest_{i}" for i in range(3 * k)] + _TAIL
            + [f"obj_dc_{i}" for i in range(identity_dim)])


def scene_to_array(scene: GaussianScene) -> np.ndarray:
    """The scene as a structured float32 numpy array ``[N]`` in file layout."""
    n = len(scene)
    e = 0 if scene.identities is None else int(scene.identities.shape[1])
    names = field_names(scene.sh_degree, e)
    cols = []

    def f32(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float32).numpy().reshape(n, -1)

    cols.append(f32(scene.means))
    cols.append(np.zeros((n, 3), np.float32))
    cols.append(f32(scene.sh_dc))
    if scene.sh_rest is not None:
        # [N, K, 3] -> [N, 3, K] -> [N, 3K] (channel-major)
        cols.append(f32(scene.sh_rest.transpose(1, 2).contiguous()))
    cols.append(f32(scene.logit_opacities))
    cols.append(f32(scene.log_scales))
    cols.append(f32(scene.quats))
    if scene.identities is not None:
        cols.append(f32(scene.identities))
    flat = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype=np.float32)
    assert flat.shape[1] == len(names)
    return flat.view(np.dtype([(nm, "<f4") for nm in names])).reshape(n)


def write_ply(path: str | Path, scene: GaussianScene) -> Path:
    """Write ``scene`` to ``path`` (binary little-endian PLY, atomically)."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    arr = scene_to_array(scene)
    el = PlyElement.describe(arr, "vertex")
    with atomic_path(path) as tmp:
        PlyData([el], text=False, byte_order="<").write(str(tmp))
    return path


def _read_vertices(path: Path, what: str) -> np.ndarray:
    """The ``vertex`` element of the PLY file ``path`` (structured array; InputError naming the file)."""
    from plyfile import PlyData

    if not path.is_file():
        raise InputError(f"{path}: PLY file not found")
    try:
        with open(path, "rb") as fh:
            ply = PlyData.read(fh)
        if "vertex" not in ply:
            raise InputError(f"{path}: not a {what} PLY (no 'vertex' element)")
        data = ply["vertex"].data
    except InputError:
        raise
    except Exception as e:  # plyfile raises a zoo of types on bad input (PlyParseError, ValueError, EOFError...)
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{path}: corrupt or truncated PLY ({msg})") from None
    return data


def read_points(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """A point cloud PLY as ``(xyz [P, 3], rgb [P, 3] in [0, 1])`` float32, for initial points.

    Positions from ``x y z``; colours from ``red green blue`` (8/16-bit integers or floats in [0, 1]),
    else from a 3DGS scene's ``f_dc_0..2`` (degree-0 colour), else mid grey.
    """
    path = Path(path).expanduser()
    data = _read_vertices(path, "point cloud")
    names = list(data.dtype.names or ())
    missing = [c for c in "xyz" if c not in names]
    if missing or len(data) == 0:
        raise InputError(f"{path}: " + (f"no {'/'.join(missing)} vertex properties" if missing else "no points")
                         + " (expected a point cloud with x y z [red green blue])")
    xyz = np.stack([np.asarray(data[c], np.float64) for c in "xyz"], 1)
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(data[c], np.float64) for c in ("red", "green", "blue")], 1)
        kind = data.dtype["red"]
        if kind.kind in "ui":
            rgb = rgb / float(np.iinfo(kind).max)
    elif all(f"f_dc_{i}" in names for i in range(3)):
        rgb = np.stack([np.asarray(data[f"f_dc_{i}"], np.float64) for i in range(3)], 1) * SH_C0 + 0.5
    else:
        rgb = np.full_like(xyz, 0.5)
    bad = ~np.isfinite(xyz).all(1) | ~np.isfinite(rgb).all(1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} point(s) have NaN/inf positions or colours")
    return torch.from_numpy(xyz).float(), torch.from_numpy(np.clip(rgb, 0.0, 1.0)).float()


def read_ply(path: str | Path, device=None) -> GaussianScene:
    """Read a Gaussian scene written by :func:`write_ply` (or any INRIA-layout 3DGS PLY)."""
    path = Path(path)
    data = _read_vertices(path, "Gaussian")
    names = list(data.dtype.names or ())
    if not names or len(data) == 0:
        raise InputError(f"{path}: PLY has no Gaussians")
    n_rest = sum(1 for nm in names if re.fullmatch(r"f_rest_\d+", nm))
    n_obj = sum(1 for nm in names if re.fullmatch(r"obj_dc_\d+", nm))
    if n_rest not in _REST_TO_DEGREE:
        raise InputError(f"{path}: {n_rest} f_rest_* fields match no SH degree (expected 0, 9, 24 or 45)")
    degree = _REST_TO_DEGREE[n_rest]
    expected = field_names(degree, n_obj)
    required = [nm for nm in expected if nm not in ("nx", "ny", "nz")]
    missing = [nm for nm in required if nm not in names]
    if missing:
        raise InputError(f"{path}: not a 3DGS PLY, missing field(s) {', '.join(missing[:6])}"
                         f"{' ...' if len(missing) > 6 else ''}")
    unexpected = [nm for nm in names if nm not in expected]
    if unexpected:
        raise InputError(f"{path}: unexpected PLY field(s) {', '.join(unexpected[:6])}"
                         f"{' ...' if len(unexpected) > 6 else ''} (expected the INRIA 3DGS layout"
                         f"{' plus obj_dc_*' if n_obj else ''})")
    for nm in required:
        if data.dtype[nm].kind != "f":
            raise InputError(f"{path}: PLY field {nm} has type {data.dtype[nm]}, expected float")

    n = len(data)

    def cols(fields: list[str]) -> torch.Tensor:
        a = np.empty((n, len(fields)), np.float32)
        for j, nm in enumerate(fields):
            a[:, j] = data[nm]
        return torch.from_numpy(a)

    means = cols(["x", "y", "z"])
    sh_dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    k = (degree + 1) ** 2 - 1
    sh_rest = cols([f"f_rest_{i}" for i in range(3 * k)]).reshape(n, 3, k).transpose(1, 2).contiguous() if k else None
    opac = cols(["opacity"])[:, 0].contiguous()
    scales = cols(["scale_0", "scale_1", "scale_2"])
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])
    ident = cols([f"obj_dc_{i}" for i in range(n_obj)]) if n_obj else None

    for name, t in (("position", means), ("f_dc", sh_dc), ("f_rest", sh_rest), ("opacity", opac),
                    ("scale", scales), ("rot", quats), ("obj_dc", ident)):
        if t is not None and not torch.isfinite(t).all():
            bad = int((~torch.isfinite(t.reshape(n, -1))).any(dim=1).sum())
            raise InputError(f"{path}: {bad} Gaussian(s) have NaN/inf {name} values")
    zero_q = (quats == 0).all(dim=1)
    if zero_q.any():
        raise InputError(f"{path}: {int(zero_q.sum())} Gaussian(s) have a zero rotation quaternion")

    scene = GaussianScene(means, scales, quats, opac, sh_dc, sh_rest, ident, degree)
    return scene.to(device) if device is not None else scene
