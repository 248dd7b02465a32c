"""PlayCanvas / SuperSplat compressed PLY (``.compressed.ply``), written and read with numpy.

A binary little-endian PLY with three elements --

* ``chunk`` (one per 256 Gaussians, float): ``min_x min_y min_z max_x max_y max_z``,
  ``min_scale_x .. max_scale_z`` (log scales, clamped to [-20, 20]), ``min_r min_g min_b max_r
  max_g max_b`` (the base colour ``0.5 + SH_C0 * f_dc``); readers also accept the older 12-field
  chunks without the colour range (colours then span [0, 1]);
* ``vertex`` (uint): ``packed_position`` (x 11 bits, y 10, z 11, from the top bit down, each
  the value's place between the chunk's min and max), ``packed_rotation`` (the index of the
  largest component of the unit quaternion ``rot_0..rot_3`` in the top 2 bits, then the other
  three in index order, 10 bits each, ``q * sqrt(1/2) + 0.5``, the largest made positive),
  ``packed_scale`` (11-10-11 as the position), ``packed_color`` (r, g, b within the chunk's
  colour range and ``sigmoid(opacity)``, 8 bits each, r in the top byte);
* ``sh`` (uchar, only at SH degree >= 1): ``f_rest_0..`` in the INRIA order, each
  ``trunc((v / 8 + 0.5) * 256)`` clamped to 0..255 (read back as ``(v + 0.5) / 256``, with 0
  and 255 as the ends).

The Gaussians are written in Morton (Z-curve) order so each chunk of 256 is spatially tight.
Coordinates as our PLY (no conversion).
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..raster.scene import SH_C0, GaussianScene
from .codec import OTHER_COMPONENTS, arrays_scene, logit, morton_order, scene_arrays, sigmoid, unorm, write_atomic

CHUNK = 256
CHUNK_FIELDS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
                "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
VERTEX_FIELDS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
_SQRT1_2 = math.sqrt(0.5)


def _chunk_range(v: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max of ``v [N, D]`` (the last chunk padded with its last row)."""
    c = -(-n // CHUNK)
    padded = np.concatenate([v, np.repeat(v[-1:], c * CHUNK - n, axis=0)]).reshape(c, CHUNK, -1)
    return padded.min(axis=1), padded.max(axis=1)


def _normalise(v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``v``'s place in [lo, hi] per chunk (0 where the range is under 1e-5), clamped to [0, 1]."""
    rows = np.arange(len(v)) // CHUNK
    lo, hi = lo[rows], hi[rows]
    rng = hi - lo
    t = np.where(rng < 1e-5, 0.0, (v - lo) / np.where(rng < 1e-5, 1.0, rng))
    return np.clip(t, 0.0, 1.0)


def _pack_11_10_11(t: np.ndarray) -> np.ndarray:
    return (unorm(t[:, 0], 11) << np.uint32(21)) | (unorm(t[:, 1], 10) << np.uint32(11)) | unorm(t[:, 2], 11)


def _unpack_11_10_11(p: np.ndarray) -> np.ndarray:
    p = p.astype(np.uint32)
    return np.stack([(p >> np.uint32(21)) / 2047.0, ((p >> np.uint32(11)) & np.uint32(0x3FF)) / 1023.0,
                     (p & np.uint32(0x7FF)) / 2047.0], 1)


def pack_rotation(q: np.ndarray) -> np.ndarray:
    """``[N, 4]`` unit quaternions (``rot_0..rot_3``) -> ``[N]`` uint32 in the 2-10-10-10 layout."""
    n = len(q)
    largest = np.argmax(np.abs(q), axis=1)
    q = np.where(q[np.arange(n), largest][:, None] < 0, -q, q)
    out = largest.astype(np.uint32)
    for c in range(3):
        out = (out << np.uint32(10)) | unorm(q[np.arange(n), OTHER_COMPONENTS[largest, c]] * _SQRT1_2 + 0.5, 10)
    return out


def unpack_rotation(p: np.ndarray) -> np.ndarray:
    """The inverse of :func:`pack_rotation`: ``[N, 4]`` unit quaternions."""
    p = p.astype(np.uint32)
    n = len(p)
    largest = (p >> np.uint32(30)).astype(np.int64)
    q = np.zeros((n, 4), np.float64)
    for c in range(3):
        bits = (p >> np.uint32(10 * (2 - c))) & np.uint32(0x3FF)
        q[np.arange(n), OTHER_COMPONENTS[largest, c]] = (bits / 1023.0 - 0.5) / _SQRT1_2
    q[np.arange(n), largest] = np.sqrt(np.clip(1.0 - (q ** 2).sum(axis=1), 0.0, None))
    return q


def compressed_ply_bytes(scene: GaussianScene) -> bytes:
    """The compressed PLY file of ``scene`` (see the module docs)."""
    a = scene_arrays(scene)
    n, k3 = len(scene), 3 * ((scene.sh_degree + 1) ** 2 - 1)
    order = morton_order(a["means"])
    pos = a["means"][order].astype(np.float64)
    lsc = a["log_scales"][order].astype(np.float64)
    rgb = a["sh_dc"][order].astype(np.float64) * SH_C0 + 0.5
    pmin, pmax = _chunk_range(pos, n)
    smin, smax = (np.clip(r, -20.0, 20.0) for r in _chunk_range(lsc, n))
    cmin, cmax = _chunk_range(rgb, n)
    color = unorm(_normalise(rgb, cmin, cmax), 8)
    vertex = np.stack([_pack_11_10_11(_normalise(pos, pmin, pmax)), pack_rotation(a["quats"][order]),
                       _pack_11_10_11(_normalise(lsc, smin, smax)),
                       (color[:, 0] << np.uint32(24)) | (color[:, 1] << np.uint32(16)) | (color[:, 2] << np.uint32(8))
                       | unorm(sigmoid(a["opacity"][order]), 8)], 1).astype("<u4")
    chunks = np.concatenate([pmin, pmax, smin, smax, cmin, cmax], 1).astype("<f4")
    lines = ["ply", "format binary_little_endian 1.0", "comment Generated by ssgwarp export",
             f"element chunk {len(chunks)}", *(f"property float {f}" for f in CHUNK_FIELDS),
             f"element vertex {n}", *(f"property uint {f}" for f in VERTEX_FIELDS)]
    body = [chunks.tobytes(), vertex.tobytes()]
    if k3:
        # [N, K, 3] -> the INRIA f_rest order (channel-major)
        rest = a["sh_rest"][order].transpose(0, 2, 1).reshape(n, k3).astype(np.float64)
        lines += [f"element sh {n}", *(f"property uchar f_rest_{i}" for i in range(k3))]
        body.append(np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8).tobytes())
    return ("\n".join(lines + ["end_header"]) + "\n").encode("ascii") + b"".join(body)


def write_compressed_ply(path: str | Path, scene: GaussianScene) -> Path:
    """Write ``scene`` as a PlayCanvas compressed PLY, atomically."""
    return write_atomic(path, compressed_ply_bytes(scene))


def _ply_elements(path: Path) -> dict:
    from plyfile import PlyData

    try:
        with open(path, "rb") as fh:
            ply = PlyData.read(fh)
    except Exception as e:  # plyfile raises many types on bad input
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{path}: corrupt or truncated PLY ({msg})") from None
    return {el.name: el.data for el in ply.elements}


def _fields(data, names: list[str], kind: str, what: str, path: Path) -> np.ndarray:
    have = data.dtype.names or ()
    missing = [f for f in names if f not in have]
    if missing:
        raise InputError(f"{path}: not a compressed PLY, {what} lacks {', '.join(missing[:4])}")
    bad = [f for f in names if data.dtype[f].kind != kind[0] or data.dtype[f].itemsize != int(kind[1])]
    if bad:
        raise InputError(f"{path}: compressed PLY {what} field {bad[0]} has type {data.dtype[bad[0]]}, "
                         f"expected {dict(f4='float', u4='uint', u1='uchar')[kind]}")
    return np.stack([np.asarray(data[f], np.float64) for f in names], 1)


def read_compressed_ply(path: str | Path) -> GaussianScene:
    """Read a PlayCanvas compressed PLY (18- or 12-field chunks, with or without ``sh``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: PLY file not found")
    els = _ply_elements(path)
    if "chunk" not in els or "vertex" not in els:
        raise InputError(f"{path}: not a compressed PLY (needs 'chunk' and 'vertex' elements)")
    chunk, vert = els["chunk"], els["vertex"]
    n = len(vert)
    if n == 0:
        raise InputError(f"{path}: compressed PLY holds no Gaussians")
    if len(chunk) != -(-n // CHUNK):
        raise InputError(f"{path}: {len(chunk)} chunks for {n} Gaussians (expected {-(-n // CHUNK)}, one per 256)")
    has_color = "min_r" in (chunk.dtype.names or ())
    c = _fields(chunk, CHUNK_FIELDS[: 18 if has_color else 12], "f4", "chunk", path)
    v = _fields(vert, VERTEX_FIELDS, "u4", "vertex", path).astype(np.uint32)
    rows = np.arange(n) // CHUNK
    c = c[rows]

    def lerp(lo, hi, t):
        return lo * (1.0 - t) + hi * t

    means = lerp(c[:, 0:3], c[:, 3:6], _unpack_11_10_11(v[:, 0]))
    log_scales = lerp(c[:, 6:9], c[:, 9:12], _unpack_11_10_11(v[:, 2]))
    col = np.stack([(v[:, 3] >> np.uint32(s)) & np.uint32(0xFF) for s in (24, 16, 8, 0)], 1) / 255.0
    rgb = lerp(c[:, 12:15], c[:, 15:18], col[:, :3]) if has_color else col[:, :3]
    sh_rest = None
    if "sh" in els:
        sh = els["sh"]
        k3 = len(sh.dtype.names or ())
        if k3 not in (9, 24, 45) or len(sh) != n:
            raise InputError(f"{path}: compressed PLY 'sh' element has {k3} fields and {len(sh)} rows "
                             f"(expected 9, 24 or 45 f_rest_* fields and {n} rows)")
        u = _fields(sh, [f"f_rest_{i}" for i in range(k3)], "u1", "sh", path)
        t = np.where(u == 0, 0.0, np.where(u == 255, 1.0, (u + 0.5) / 256.0))
        sh_rest = ((t - 0.5) * 8.0).reshape(n, 3, k3 // 3).transpose(0, 2, 1)
    return arrays_scene(means, log_scales, unpack_rotation(v[:, 1]), logit(col[:, 3]), (rgb - 0.5) / SH_C0, sh_rest)


def is_compressed_ply(path: str | Path) -> bool:
    """Whether ``path``'s PLY header declares a ``chunk`` element (the compressed layout)."""
    with open(path, "rb") as fh:
        head = fh.read(4096)
    end = head.find(b"end_header")
    return head.startswith(b"ply") and re.search(rb"^element chunk ", head[:end if end >= 0 else None],
                                                  re.MULTILINE) is not None
