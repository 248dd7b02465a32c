"""mkkellogg's GaussianSplats3D ``.ksplat`` (read only), from the layout its SplatBuffer writes.

* a 4096-byte main header (little-endian): ``uint8 major = 0``, ``uint8 minor >= 1`` at 0-1, ``uint32
  maxSections`` at 4, ``uint32 numSplats`` at 16, ``uint16 compressionMode`` (0, 1 or 2) at 20, ``float32
  minSH, maxSH`` at 36 and 40 (mode 2's SH range; 0 means -1.5 and 1.5);
* ``maxSections`` 1024-byte section headers: ``uint32 splatCount`` at 0, ``maxSplats`` at 4,
  ``bucketCapacity`` at 8, ``bucketCount`` at 12, ``float32 spatialBlockSize`` at 16, ``uint16
  bucketStorageSize`` at 20, ``uint32 quantizationRange`` at 24 (0: 1 in mode 0, 32767 otherwise),
  ``uint32 fullBuckets`` at 32, ``partialBuckets`` at 36, ``uint16 shDegree`` at 40;
* per section: ``partialBuckets`` uint32 bucket sizes, the buckets' centres (3 float32 each, in
  ``bucketStorageSize * bucketCount`` bytes), then ``maxSplats`` records of ``centre, scale, rotation,
  colour, SH``: mode 0 float32 (12 + 12 + 16 bytes), modes 1 and 2 the centre as 3 uint16 (``(u -
  range) * spatialBlockSize / 2 / range`` plus its bucket's centre), scale and rotation float16; the colour
  RGBA uint8 (``0.5 + SH_C0 * f_dc``, ``sigmoid(opacity)``); SH per band, channel-major inside a band
  (r's coefficients, then g's, then b's), float32 / float16 / uint8 over [minSH, maxSH] by mode.

Scales are linear (stored ``log``; non-positive ones read as ``exp(-10)``), the quaternion is ``w x y z``,
coordinates as the PLY the file was made from (ours: no conversion).
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..raster.scene import SH_C0, GaussianScene
from .codec import arrays_scene, logit

MAIN_HEADER = 4096
SECTION_HEADER = 1024
# mode -> (centre, scale, rotation, colour, bytes per SH value)
_MODES = {0: (12, 12, 16, 4, 4), 1: (6, 6, 8, 4, 2), 2: (6, 6, 8, 4, 1)}
_SH_COUNT = {0: 0, 1: 9, 2: 24, 3: 45}


def _sh_columns(degree: int, k: int) -> np.ndarray:
    """For each SH value a section of ``degree`` stores (band by band, channel-major in a band) its INRIA
    ``f_rest`` index in a scene of ``k`` coefficients per channel."""
    return np.array([ch * k + band * band - 1 + j for band in range(1, degree + 1)
                     for ch in range(3) for j in range(2 * band + 1)], np.int64)


def read_ksplat(path: str | Path) -> GaussianScene:
    """Read a ``.ksplat`` file into a scene (SH up to the highest degree of its sections)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: .ksplat file not found")
    data = path.read_bytes()
    size = len(data)
    if size < MAIN_HEADER:
        raise InputError(f"{path}: not a .ksplat file ({size} bytes, the header alone is {MAIN_HEADER})")
    major, minor = data[0], data[1]
    if major != 0 or minor < 1:
        raise InputError(f"{path}: .ksplat version {major}.{minor} is not supported (0.1 and later are read)")
    sections, = struct.unpack_from("<I", data, 4)
    n_total, = struct.unpack_from("<I", data, 16)
    mode, = struct.unpack_from("<H", data, 20)
    sh_lo, sh_hi = struct.unpack_from("<ff", data, 36)
    sh_lo, sh_hi = (sh_lo or -1.5), (sh_hi or 1.5)
    if mode not in _MODES:
        raise InputError(f"{path}: .ksplat compression mode {mode} is invalid (0, 1 or 2)")
    if n_total == 0:
        raise InputError(f"{path}: .ksplat file holds no Gaussians")
    if MAIN_HEADER + sections * SECTION_HEADER > size:
        raise InputError(f"{path}: .ksplat header names {sections} sections, past the file's end (truncated or corrupt)")
    cb, sb, rb, colb, shb = _MODES[mode]
    heads = [struct.unpack_from("<IIIIfHxxIxxxxIIH", data, MAIN_HEADER + i * SECTION_HEADER) for i in range(sections)]
    degree = max([h[9] for h in heads if h[0]] or [0])
    if degree > 3:
        raise InputError(f"{path}: .ksplat SH degree {degree} is invalid (0..3)")
    k3 = _SH_COUNT[degree]
    if n_total * (cb + sb + rb + colb) > size:
        raise InputError(f"{path}: .ksplat header claims {n_total} Gaussians, more than its {size} bytes hold")
    parts = []
    off = MAIN_HEADER + sections * SECTION_HEADER
    f16 = "<f2" if mode else "<f4"
    for i, (count, cap, bucket_cap, buckets, block, bucket_bytes, qrange, full, partial, deg) in enumerate(heads):
        if deg > 3:
            raise InputError(f"{path}: .ksplat section {i} has SH degree {deg} (0..3)")
        qrange = qrange or (1 if mode == 0 else 32767)
        sk3 = _SH_COUNT[deg]
        rec = cb + sb + rb + colb + sk3 * shb
        meta = partial * 4 + bucket_bytes * buckets
        end = off + meta + rec * cap
        if count > cap or end > size or (mode and (bucket_bytes < 12 and buckets or full + partial != buckets)):
            raise InputError(f"{path}: .ksplat section {i} ({count} Gaussians, {buckets} buckets) runs past the "
                             f"file's end or its own room (truncated or corrupt)")
        if count:
            raw = np.frombuffer(data, np.uint8, rec * count, off + meta).reshape(count, rec)

            def field(start, nbytes, dtype):
                return np.ascontiguousarray(raw[:, start:start + nbytes]).view(dtype).astype(np.float64)

            if mode == 0:
                means = field(0, 12, "<f4")
            else:
                sizes = np.array([bucket_cap] * full + list(np.frombuffer(data, "<u4", partial, off)), np.int64)
                if len(sizes) != buckets or sizes.sum() < count:
                    raise InputError(f"{path}: .ksplat section {i}: its buckets hold {int(sizes.sum())} Gaussians "
                                     f"in {len(sizes)} buckets, {count} in {buckets} expected (corrupt)")
                centres = np.frombuffer(data, "<f4", 3 * buckets, off + partial * 4).reshape(buckets, 3) \
                    if bucket_bytes == 12 else np.stack([np.frombuffer(data, "<f4", 3, off + partial * 4 + b * bucket_bytes)
                                                         for b in range(buckets)])
                bucket = np.searchsorted(np.cumsum(sizes), np.arange(count), side="right")
                means = (field(0, 6, "<u2") - qrange) * (block / 2.0 / qrange) + centres[bucket].astype(np.float64)
            scales = field(cb, sb, f16)
            quats = field(cb + sb, rb, f16)
            rgba = raw[:, cb + sb + rb:cb + sb + rb + 4].astype(np.float64) / 255.0
            rest = np.zeros((count, k3))
            if sk3:
                start = cb + sb + rb + colb
                vals = field(start, sk3 * 4, "<f4") if mode == 0 else field(start, sk3 * 2, "<f2") if mode == 1 \
                    else sh_lo + raw[:, start:start + sk3].astype(np.float64) / 255.0 * (sh_hi - sh_lo)
                rest[:, _sh_columns(deg, k3 // 3)] = vals
            parts.append((means, scales, quats, rgba, rest))
        off = end
    n = sum(len(p[0]) for p in parts)
    if n != n_total:
        raise InputError(f"{path}: .ksplat sections hold {n} Gaussians, the header says {n_total} (corrupt)")
    means, scales, quats, rgba, rest = (np.concatenate(c) for c in zip(*parts))
    if not (np.isfinite(means).all() and np.isfinite(scales).all() and np.isfinite(quats).all()
            and np.isfinite(rest).all()):
        raise InputError(f"{path}: .ksplat file has NaN/inf values (corrupt)")
    log_scales = np.log(np.where(scales > 0, scales, np.exp(-10.0)))
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(norm > 0, quats / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    sh_rest = rest.reshape(n, 3, k3 // 3).transpose(0, 2, 1) if k3 else None
    return arrays_scene(means, log_scales, quats, logit(rgba[:, 3]), (rgba[:, :3] - 0.5) / SH_C0, sh_rest)
