"""Niantic's SPZ format (``.spz``): a gzip stream of a 16-byte header and the Gaussians'
attributes, quantised, one attribute after the other.

Header (little-endian): ``uint32 magic = 0x5053474e`` ("NGSP"), ``uint32 version``,
``uint32 numPoints``, ``uint8 shDegree``, ``uint8 fractionalBits``, ``uint8 flags``
(``0x1``: trained with antialiasing; ``0x2``: extension records follow), ``uint8 reserved = 0``.
Then, for all N Gaussians one attribute at a time:

* positions ``N x 3 x 3`` bytes: 24-bit signed fixed point, ``fractionalBits`` fractional bits;
* alphas ``N`` bytes: ``sigmoid(opacity) * 255``;
* colours ``N x 3`` bytes: ``sh_dc * 0.15 * 255 + 127.5`` (0.15 rather than SH's 0.282 leaves
  room for base colours outside [0, 1]);
* scales ``N x 3`` bytes: ``(log_scale + 10) * 16``;
* rotations: version 3, ``N x 4`` bytes, the "smallest three" of the unit xyzw quaternion: a
  little-endian uint32 holding the largest component's index in its top 2 bits, then the other
  three in index order, 10 bits each (a sign bit, then ``511 * |q_i| / sqrt(1/2)``), the largest
  made positive; version 2, ``N x 3`` bytes: xyz as ``q * 127.5 + 127.5`` with w >= 0 implied;
* SH ``N x K x 3`` bytes (coefficient-major, colour inside): ``x * 128 + 128``, rounded to fewer
  significant bits to help gzip (readers need not know how many): here 6 for band 1 and 5 for the
  higher bands by default, one more than the reference writer's 5 and 4 (:data:`SH_BITS`).

Coordinates: SPZ is RUB (x right, y up, z back, as OpenGL / three.js) where 3DGS PLY scenes are
RDF (x right, y down, z forward, as OpenCV / COLMAP). Writing and reading convert by flipping
y and z: positions ``(x, -y, -z)``, quaternions ``(w, x, -y, -z)``, and each SH coefficient
times the parity of its basis function under that flip (:func:`sh_flip_signs`).

:func:`write_spz` writes version 3 (version 2 on request); :func:`read_spz` reads versions 2 and 3
(degree 4 files keep their first three bands); files with extension records, the float16
positions of version 1 and the zstd container of version 4 are refused with a one-line error.
"""
from __future__ import annotations

import gzip
import math
import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..raster.scene import GaussianScene
from .codec import OTHER_COMPONENTS, arrays_scene, logit, scene_arrays, sigmoid, to_u8, write_atomic

MAGIC = 0x5053474E
HEADER = struct.Struct("<IIIBBBB")
COLOR_SCALE = 0.15
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
# significant bits of the SH coefficients (band 1, higher bands): one more than the reference writer's
# default (5, 4), which costs 0.5 dB under the 40 dB round trip on a degree-3 fern (docs/export.md);
# readers need not know them (the dropped bits are zeros)
SH_BITS = (6, 5)
_SQRT1_2 = math.sqrt(0.5)
# the axes each SH basis function (bands 1-3, 3DGS order) is odd in: its sign under an axis flip
_SH_ODD_AXES = ("y", "z", "x",                                   # band 1: y, z, x
                "xy", "yz", "", "xz", "",                         # band 2: xy, yz, 3z^2-1, xz, x^2-y^2
                "y", "xyz", "y", "z", "x", "z", "x")              # band 3
RDF_TO_RUB = (1.0, -1.0, -1.0)   # the axis flips between PLY's frame and SPZ's (its own inverse)


def sh_flip_signs(flips=RDF_TO_RUB, k: int = 15) -> np.ndarray:
    """``[k]`` the sign each SH coefficient (bands 1.., DC excluded) takes when the axes are
    multiplied by ``flips`` (x, y, z), from the parity of its basis function."""
    f = dict(zip("xyz", flips))
    return np.array([np.prod([f[a] for a in axes]) if axes else 1.0 for axes in _SH_ODD_AXES[:k]], np.float32)


# ----------------------------------------------------------------------------- quaternions
def pack_smallest_three(q_xyzw: np.ndarray) -> np.ndarray:
    """``[N, 4]`` unit xyzw quaternions -> ``[N]`` uint32 (SPZ version 3's packing)."""
    n = q_xyzw.shape[0]
    largest = np.argmax(np.abs(q_xyzw), axis=1)
    negate = q_xyzw[np.arange(n), largest] < 0
    comp = largest.astype(np.uint32)
    others = OTHER_COMPONENTS[largest]   # [N, 3]: the components other than the largest, in index order
    for c in range(3):
        v = q_xyzw[np.arange(n), others[:, c]]
        neg = ((v < 0) ^ negate).astype(np.uint32)
        mag = np.clip(np.floor(511.0 * np.abs(v) / _SQRT1_2 + 0.5), 0, 511).astype(np.uint32)
        comp = (comp << np.uint32(10)) | (neg << np.uint32(9)) | mag
    return comp


def unpack_smallest_three(comp: np.ndarray) -> np.ndarray:
    """``[N]`` uint32 -> ``[N, 4]`` unit xyzw quaternions (the inverse of :func:`pack_smallest_three`)."""
    comp = comp.astype(np.uint32)
    n = comp.shape[0]
    largest = (comp >> np.uint32(30)).astype(np.int64)
    others = OTHER_COMPONENTS[largest]
    q = np.zeros((n, 4), np.float64)
    for c in range(3):   # the last component sits in the lowest bits
        bits = (comp >> np.uint32(10 * (2 - c))) & np.uint32(0x3FF)
        v = _SQRT1_2 * (bits & np.uint32(0x1FF)).astype(np.float64) / 511.0
        q[np.arange(n), others[:, c]] = np.where(bits >> np.uint32(9) == 1, -v, v)
    q[np.arange(n), largest] = np.sqrt(np.clip(1.0 - (q ** 2).sum(axis=1), 0.0, None))
    return q


# ----------------------------------------------------------------------------- writing
def encode_spz(scene: GaussianScene, *, version: int = 3, antialiased: bool = False,
               sh_bits: tuple[int, int] = SH_BITS) -> bytes:
    """The uncompressed SPZ stream (header + attributes) of ``scene`` (RDF), in SPZ's RUB frame;
    ``sh_bits``: the significant bits of the SH coefficients of band 1 and of the higher bands."""
    if version not in (2, 3):
        raise InputError(f"SPZ version {version}: only versions 2 and 3 are written")
    if not all(isinstance(b, int) and 1 <= b <= 8 for b in sh_bits) or len(sh_bits) != 2:
        raise InputError(f"SPZ SH bits {sh_bits}: expected two numbers 1..8 (band 1, higher bands)")
    a = scene_arrays(scene)
    n, deg = len(scene), scene.sh_degree
    flip = np.array(RDF_TO_RUB, np.float64)
    pos = a["means"].astype(np.float64) * flip
    extent = float(np.abs(pos).max()) if n else 0.0
    # 12 fractional bits (about 0.25 mm) as the reference writer; fewer when the scene is too large for
    # 24 bits at 12 (|x| >= 2048), so every position fits (readers take the count from the header)
    frac = 12 if extent < 2047.0 else max(0, 22 - math.ceil(math.log2(extent + 1.0)))
    if extent * 2 ** frac >= 2 ** 23 - 1:
        raise InputError(f"SPZ: positions up to {extent:.3g} do not fit 24-bit fixed point")
    fixed = np.floor(pos * 2 ** frac + 0.5).astype(np.int64).reshape(-1) & 0xFFFFFF
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)
    alphas = to_u8(sigmoid(a["opacity"]) * 255.0)
    colors = to_u8(a["sh_dc"].astype(np.float64) * (COLOR_SCALE * 255.0) + 127.5)
    scales = to_u8((a["log_scales"].astype(np.float64) + 10.0) * 16.0)
    q = a["quats"].astype(np.float64)                       # wxyz -> xyzw, then the frame's flips
    q_xyzw = np.stack([q[:, 1] * flip[0], q[:, 2] * flip[1], q[:, 3] * flip[2], q[:, 0]], 1)
    if version == 3:
        rotations = pack_smallest_three(q_xyzw).astype("<u4").view(np.uint8)
    else:
        q_xyzw = np.where(q_xyzw[:, 3:4] < 0, -q_xyzw, q_xyzw)
        rotations = to_u8(q_xyzw[:, :3] * 127.5 + 127.5)
    parts = [HEADER.pack(MAGIC, version, n, deg, frac, FLAG_ANTIALIASED if antialiased else 0, 0),
             positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), rotations.tobytes()]
    if deg:
        k = (deg + 1) ** 2 - 1
        sh = a["sh_rest"].astype(np.float64) * sh_flip_signs(RDF_TO_RUB, k)[None, :, None]
        q8 = np.sign(sh) * np.floor(np.abs(sh) * 128.0 + 0.5) + 128.0
        bucket = np.where(np.arange(k) < 3, 1 << (8 - sh_bits[0]), 1 << (8 - sh_bits[1]))[None, :, None]
        q8 = np.floor((q8 + bucket // 2) / bucket) * bucket
        parts.append(np.clip(q8, 0, 255).astype(np.uint8).tobytes())
    return b"".join(parts)


def write_spz(path: str | Path, scene: GaussianScene, *, version: int = 3, antialiased: bool = False,
              sh_bits: tuple[int, int] = SH_BITS) -> Path:
    """Write ``scene`` (RDF, as our PLY) to ``path`` as SPZ (gzip, RUB), atomically."""
    raw = encode_spz(scene, version=version, antialiased=antialiased, sh_bits=tuple(sh_bits))
    return write_atomic(path, gzip.compress(raw, compresslevel=6, mtime=0))


# ----------------------------------------------------------------------------- reading
def decode_spz(raw: bytes, name: str = "SPZ") -> tuple[GaussianScene, dict]:
    """Decode an uncompressed SPZ stream: ``(scene in RDF, header dict)``."""
    if len(raw) < HEADER.size:
        raise InputError(f"{name}: truncated SPZ (no header)")
    magic, version, n, deg, frac, flags, _ = HEADER.unpack_from(raw)
    if magic != MAGIC:
        raise InputError(f"{name}: not an SPZ file (magic {magic:#010x}, expected {MAGIC:#010x})")
    if version not in (2, 3):
        raise InputError(f"{name}: SPZ version {version} is not supported (versions 2 and 3 are read)")
    if flags & FLAG_EXTENSIONS:
        raise InputError(f"{name}: SPZ file carries extension records (flag 0x2), which are not read; "
                         f"re-save it without extensions")
    if deg > 4:
        raise InputError(f"{name}: SPZ SH degree {deg} is invalid (0..4)")
    k_file = (deg + 1) ** 2 - 1
    rot_bytes = 4 if version >= 3 else 3
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * k_file * n]
    if len(raw) != HEADER.size + sum(sizes):
        raise InputError(f"{name}: SPZ payload is {len(raw) - HEADER.size} bytes, {sum(sizes)} expected for "
                         f"{n} Gaussians at SH degree {deg} (truncated or corrupt)")
    if n == 0:
        raise InputError(f"{name}: SPZ file holds no Gaussians")
    off, chunks = HEADER.size, []
    for s in sizes:
        chunks.append(np.frombuffer(raw, np.uint8, s, off))
        off += s
    pos_b, alpha_b, color_b, scale_b, rot_b, sh_b = chunks
    flip = np.array(RDF_TO_RUB, np.float64)
    p = pos_b.reshape(-1, 3).astype(np.int64)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.reshape(n, 3).astype(np.float64) / 2 ** frac * flip
    opacity = logit(alpha_b.astype(np.float64) / 255.0)
    sh_dc = (color_b.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE
    log_scales = scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 10.0
    if version >= 3:
        q = unpack_smallest_three(rot_b.view("<u4"))
    else:
        xyz = rot_b.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        q = np.concatenate([xyz, np.sqrt(np.clip(1.0 - (xyz ** 2).sum(1, keepdims=True), 0.0, None))], 1)
    quats = np.stack([q[:, 3], q[:, 0] * flip[0], q[:, 1] * flip[1], q[:, 2] * flip[2]], 1)   # xyzw -> wxyz
    sh_rest = None
    if deg:
        k = min(k_file, 15)   # a degree-4 file keeps bands 1-3
        sh = (sh_b.reshape(n, k_file, 3)[:, :k].astype(np.float64) - 128.0) / 128.0
        sh_rest = sh * sh_flip_signs(RDF_TO_RUB, k)[None, :, None]
    header = {"version": version, "num_points": n, "sh_degree": deg, "fractional_bits": frac,
              "antialiased": bool(flags & FLAG_ANTIALIASED)}
    return arrays_scene(means, log_scales, quats, opacity, sh_dc, sh_rest), header


def read_spz(path: str | Path) -> GaussianScene:
    """Read an SPZ file (versions 2 and 3) into a scene in our (RDF) frame."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: SPZ file not found")
    data = path.read_bytes()
    if data[:4] == struct.pack("<I", MAGIC):
        version = struct.unpack_from("<I", data, 4)[0] if len(data) >= 8 else 0
        raise InputError(f"{path}: SPZ version {version} (uncompressed NGSP container, zstd streams) is not "
                         f"supported; versions 2 and 3 (gzip) are read")
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as e:
        raise InputError(f"{path}: not a gzip-compressed SPZ file ({e})") from None
    return decode_spz(raw, str(path))[0]
