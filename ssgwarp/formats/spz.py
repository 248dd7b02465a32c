"""Niantic's SPZ format (``.spz``), versions 2 to 4: the Gaussians' attributes quantised, one
attribute after the other, in one of three containers:

* **version 4** (Niantic's default since 2026): a plaintext 32-byte header (little-endian ``uint32 magic
  = 0x5053474e`` ("NGSP"), ``uint32 version = 4``, ``uint32 numPoints``, ``uint8 shDegree``, ``uint8
  fractionalBits``, ``uint8 flags``, ``uint8 numStreams``, ``uint32 tocByteOffset``, 12 reserved zero
  bytes), then extension records (flag ``0x2``) up to ``tocByteOffset``, then a table of contents
  (per stream ``uint64 compressedSize, uint64 uncompressedSize``), then each attribute as its own zstd
  frame (the SH stream absent at degree 0);
* **versions 2 and 3, gzip**: a gzip stream of a 16-byte header (``magic``, ``version``, ``numPoints``,
  ``shDegree``, ``fractionalBits``, ``flags``, one reserved byte), the attributes, then the extension
  records (flag ``0x2``);
* **versions 2 and 3, uncompressed**: the same 16-byte header and attributes without the gzip wrapper
  (files that start with "NGSP" and a version below 4; PlayCanvas reads them, Niantic's library does not).

Flags: ``0x1`` trained with antialiasing (Mip-Splatting), ``0x2`` extension records follow. An extension
record is ``uint32 type, uint32 byteLength, payload``; readers skip the types they do not know. The one
that changes the data's meaning is Adobe's coordinate system (``0xADBE0003``, a ``uint32``: 0 unspecified,
1 LDB, 2 RDB, 3 LUB, 4 RUB, 5 LDF, 6 RDF, 7 LUF, 8 RUF, 9-16 the frames rotated 90 degrees about x): the
eight axis-flip frames are read, the rotated ones refused.

The attributes, for all N Gaussians one attribute at a time:

* positions ``N x 3 x 3`` bytes: 24-bit signed fixed point, ``fractionalBits`` fractional bits;
* alphas ``N`` bytes: ``sigmoid(opacity) * 255``;
* colours ``N x 3`` bytes: ``sh_dc * 0.15 * 255 + 127.5`` (0.15 rather than SH's 0.282 leaves
  room for base colours outside [0, 1]);
* scales ``N x 3`` bytes: ``(log_scale + 10) * 16``;
* rotations: versions 3 and 4, ``N x 4`` bytes, the "smallest three" of the unit xyzw quaternion: a
  little-endian uint32 holding the largest component's index in its top 2 bits, then the other
  three in index order, 10 bits each (a sign bit, then ``511 * |q_i| / sqrt(1/2)``), the largest
  made positive; version 2, ``N x 3`` bytes: xyz as ``q * 127.5 + 127.5`` with w >= 0 implied;
* SH ``N x K x 3`` bytes (coefficient-major, colour inside; degree 4: K = 24): ``x * 128 + 128``,
  rounded to fewer significant bits to help the compressor (readers need not know how many): here 6 for
  band 1 and 5 for the higher bands by default, one more than the reference writer's 5 and 4 (:data:`SH_BITS`).

Coordinates: SPZ is RUB (x right, y up, z back, as OpenGL / three.js) where 3DGS PLY scenes are
RDF (x right, y down, z forward, as OpenCV / COLMAP). Writing and reading convert by flipping
y and z: positions ``(x, -y, -z)``, quaternions ``(w, x, -y, -z)``, and each SH coefficient
times the parity of its basis function under that flip (:func:`sh_flip_signs`).

:func:`write_spz` writes version 4 (3 or 2 on request, for older viewers); :func:`read_spz` reads
versions 2 to 4 in all three containers (degree 4 files keep their first three bands). Version 1's
float16 positions (never released) are refused with a one-line error. Counts are checked against the
file's size before anything is allocated, and decompression is bounded by the sizes the header implies.
"""
from __future__ import annotations

import gzip
import io
import math
import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..raster.scene import GaussianScene
from .codec import OTHER_COMPONENTS, arrays_scene, logit, scene_arrays, sigmoid, to_u8, write_atomic

MAGIC = 0x5053474E
HEADER = struct.Struct("<IIIBBBB")            # versions 1-3 (inside the gzip stream, or bare)
HEADER_V4 = struct.Struct("<IIIBBBBI12s")     # version 4: 32 bytes, plaintext
TOC_ENTRY = struct.Struct("<QQ")
EXT_RECORD = struct.Struct("<II")
EXT_COORDINATE_SYSTEM = 0xADBE0003            # Adobe's coordinate system record: a uint32 frame
_FRAMES = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}
MAX_RATIO = 1032                               # the most a deflate / zstd stream of ours expands: bounds counts
ZSTD_LEVEL = 12
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
def _attribute_streams(scene: GaussianScene, version: int, sh_bits: tuple[int, int]) -> tuple[int, list[bytes]]:
    """``(fractional bits, [positions, alphas, colours, scales, rotations, SH])`` of ``scene`` (RDF) in
    SPZ's RUB frame; the SH stream is empty at degree 0."""
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
    if version >= 3:
        rotations = pack_smallest_three(q_xyzw).astype("<u4").view(np.uint8)
    else:
        q_xyzw = np.where(q_xyzw[:, 3:4] < 0, -q_xyzw, q_xyzw)
        rotations = to_u8(q_xyzw[:, :3] * 127.5 + 127.5)
    sh = b""
    if deg:
        k = (deg + 1) ** 2 - 1
        rest = a["sh_rest"].astype(np.float64) * sh_flip_signs(RDF_TO_RUB, k)[None, :, None]
        q8 = np.sign(rest) * np.floor(np.abs(rest) * 128.0 + 0.5) + 128.0
        bucket = np.where(np.arange(k) < 3, 1 << (8 - sh_bits[0]), 1 << (8 - sh_bits[1]))[None, :, None]
        q8 = np.floor((q8 + bucket // 2) / bucket) * bucket
        sh = np.clip(q8, 0, 255).astype(np.uint8).tobytes()
    return frac, [positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), rotations.tobytes(), sh]


def encode_spz(scene: GaussianScene, *, version: int = 3, antialiased: bool = False,
               sh_bits: tuple[int, int] = SH_BITS) -> bytes:
    """The uncompressed legacy SPZ stream (16-byte header + attributes, versions 2 and 3) of ``scene``
    (RDF), in SPZ's RUB frame; ``sh_bits``: the significant bits of the SH of band 1 and of the higher bands."""
    if version not in (2, 3):
        raise InputError(f"SPZ version {version}: the legacy stream is versions 2 and 3")
    frac, streams = _attribute_streams(scene, version, tuple(sh_bits))
    flags = FLAG_ANTIALIASED if antialiased else 0
    return HEADER.pack(MAGIC, version, len(scene), scene.sh_degree, frac, flags, 0) + b"".join(streams)


def encode_spz_v4(scene: GaussianScene, *, antialiased: bool = False, sh_bits: tuple[int, int] = SH_BITS,
                  level: int = ZSTD_LEVEL) -> bytes:
    """The SPZ version 4 file of ``scene``: 32-byte header, table of contents, one zstd frame per attribute."""
    import zstandard

    frac, streams = _attribute_streams(scene, 4, tuple(sh_bits))
    streams = [st for st in streams if st]
    cctx = zstandard.ZstdCompressor(level=level)
    frames = [cctx.compress(st) for st in streams]
    header = HEADER_V4.pack(MAGIC, 4, len(scene), scene.sh_degree, frac, FLAG_ANTIALIASED if antialiased else 0,
                            len(frames), HEADER_V4.size, bytes(12))
    toc = b"".join(TOC_ENTRY.pack(len(f), len(st)) for f, st in zip(frames, streams))
    return header + toc + b"".join(frames)


def write_spz(path: str | Path, scene: GaussianScene, *, version: int = 4, antialiased: bool = False,
              sh_bits: tuple[int, int] = SH_BITS) -> Path:
    """Write ``scene`` (RDF, as our PLY) to ``path`` as SPZ (RUB), atomically: version 4 (zstd streams),
    or 3 / 2 (gzip) for viewers that predate version 4."""
    if version == 4:
        return write_atomic(path, encode_spz_v4(scene, antialiased=antialiased, sh_bits=tuple(sh_bits)))
    if version not in (2, 3):
        raise InputError(f"SPZ version {version}: versions 2, 3 and 4 are written")
    raw = encode_spz(scene, version=version, antialiased=antialiased, sh_bits=tuple(sh_bits))
    return write_atomic(path, gzip.compress(raw, compresslevel=6, mtime=0))


# ----------------------------------------------------------------------------- reading
def _sizes(n: int, deg: int, version: int) -> list[int]:
    k = (deg + 1) ** 2 - 1
    return [9 * n, n, 3 * n, 3 * n, (4 if version >= 3 else 3) * n, 3 * k * n]


def _check_header(name: str, version: int, n: int, deg: int, frac: int, budget: int) -> None:
    """The header's values, and its count against ``budget`` bytes (what the file can hold at most)."""
    if version == 1:
        raise InputError(f"{name}: SPZ version 1 (float16 positions, never released) is not read; versions 2-4 are")
    if version not in (2, 3, 4):
        raise InputError(f"{name}: SPZ version {version} is not supported (versions 2, 3 and 4 are read)")
    if deg > 4:
        raise InputError(f"{name}: SPZ SH degree {deg} is invalid (0..4)")
    if n == 0:
        raise InputError(f"{name}: SPZ file holds no Gaussians")
    if 9 * n > budget:
        raise InputError(f"{name}: SPZ header claims {n} Gaussians, more than the file's {budget} bytes can hold "
                         f"(truncated or corrupt)")
    if frac > 23:
        raise InputError(f"{name}: SPZ fractional bits {frac} are invalid (0..23)")


def _frame_flips(records: bytes, name: str) -> tuple[tuple[float, float, float], list[int]]:
    """The axis flips from the file's frame to ours (RDF) and the extension types in ``records``."""
    flips, types, off = RDF_TO_RUB, [], 0
    while off < len(records):
        if len(records) - off < EXT_RECORD.size:
            raise InputError(f"{name}: SPZ extension records are truncated")
        t, length = EXT_RECORD.unpack_from(records, off)
        off += EXT_RECORD.size
        if length > len(records) - off:
            raise InputError(f"{name}: SPZ extension record {t:#010x} claims {length} bytes, past the records' end")
        payload = records[off:off + length]
        off += length
        types.append(t)
        if t == EXT_COORDINATE_SYSTEM:
            frame = struct.unpack_from("<I", payload)[0] if length >= 4 else 0
            if frame == 0:
                continue   # unspecified: RUB
            if frame not in _FRAMES:
                raise InputError(f"{name}: SPZ coordinate system {frame} is one of the rotated frames (or unknown); "
                                 f"only the axis-flip frames 1-8 (LDB..RUF) are read")
            flips = tuple(1.0 if a == b else -1.0 for a, b in zip(_FRAMES[frame], "RDF"))
    return flips, types


def _decode_attributes(chunks: list[np.ndarray], n: int, deg: int, frac: int, version: int,
                       flips=RDF_TO_RUB) -> GaussianScene:
    pos_b, alpha_b, color_b, scale_b, rot_b, sh_b = chunks
    flip = np.array(flips, np.float64)
    det = float(np.prod(flip))
    p = pos_b.reshape(-1, 3).astype(np.int64)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.reshape(n, 3).astype(np.float64) / 2 ** frac * flip
    opacity = logit(alpha_b.astype(np.float64) / 255.0)
    sh_dc = (color_b.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE
    log_scales = scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 10.0
    if version >= 3:
        q = unpack_smallest_three(np.frombuffer(rot_b.tobytes(), "<u4"))
    else:
        xyz = rot_b.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        q = np.concatenate([xyz, np.sqrt(np.clip(1.0 - (xyz ** 2).sum(1, keepdims=True), 0.0, None))], 1)
    # a diagonal flip F turns rotation R into F R F: the quaternion's vector part times det(F) * F
    quats = np.stack([q[:, 3], q[:, 0] * flip[0] * det, q[:, 1] * flip[1] * det, q[:, 2] * flip[2] * det], 1)
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(norm > 0, quats / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    sh_rest = None
    if deg:
        k_file = (deg + 1) ** 2 - 1
        k = min(k_file, 15)   # a degree-4 file keeps bands 1-3
        sh = (sh_b.reshape(n, k_file, 3)[:, :k].astype(np.float64) - 128.0) / 128.0
        sh_rest = sh * sh_flip_signs(flips, k)[None, :, None]
    return arrays_scene(means, log_scales, quats, opacity, sh_dc, sh_rest)


def _split(raw: bytes, off: int, sizes: list[int]) -> list[np.ndarray]:
    out = []
    for s in sizes:
        out.append(np.frombuffer(raw, np.uint8, s, off))
        off += s
    return out


def decode_spz(raw: bytes, name: str = "SPZ") -> tuple[GaussianScene, dict]:
    """Decode a legacy SPZ stream (16-byte header, attributes, extension records; versions 2 and 3, as
    inside the gzip or bare): ``(scene in RDF, header dict)``."""
    if len(raw) < HEADER.size:
        raise InputError(f"{name}: truncated SPZ (no header)")
    magic, version, n, deg, frac, flags, _ = HEADER.unpack_from(raw)
    if magic != MAGIC:
        raise InputError(f"{name}: not an SPZ file (magic {magic:#010x}, expected {MAGIC:#010x})")
    if version == 4:
        raise InputError(f"{name}: a version 4 header inside a legacy SPZ stream (corrupt)")
    _check_header(name, version, n, deg, frac, len(raw))
    sizes = _sizes(n, deg, version)
    end = HEADER.size + sum(sizes)
    if len(raw) < end or (len(raw) > end and not flags & FLAG_EXTENSIONS):
        raise InputError(f"{name}: SPZ payload is {len(raw) - HEADER.size} bytes, {sum(sizes)} expected for "
                         f"{n} Gaussians at SH degree {deg} (truncated or corrupt)")
    flips, types = _frame_flips(raw[end:], name) if flags & FLAG_EXTENSIONS else (RDF_TO_RUB, [])
    scene = _decode_attributes(_split(raw, HEADER.size, sizes), n, deg, frac, version, flips)
    return scene, {"version": version, "num_points": n, "sh_degree": deg, "fractional_bits": frac,
                   "antialiased": bool(flags & FLAG_ANTIALIASED), "extensions": types}


def decode_spz_v4(data: bytes, name: str = "SPZ") -> tuple[GaussianScene, dict]:
    """Decode an SPZ version 4 file (header, extension records, table of contents, zstd streams)."""
    import zstandard

    if len(data) < HEADER_V4.size:
        raise InputError(f"{name}: truncated SPZ version 4 header ({len(data)} of 32 bytes)")
    magic, version, n, deg, frac, flags, n_streams, toc_at, _ = HEADER_V4.unpack_from(data)
    _check_header(name, version, n, deg, frac, len(data) * MAX_RATIO)
    sizes = [s for s in _sizes(n, deg, version) if s]
    if n_streams != len(sizes):
        raise InputError(f"{name}: SPZ header names {n_streams} streams, {len(sizes)} expected at SH degree {deg}")
    toc_end = toc_at + TOC_ENTRY.size * n_streams
    if toc_at < HEADER_V4.size or toc_end > len(data):
        raise InputError(f"{name}: SPZ table of contents at byte {toc_at} lies outside the file (truncated or corrupt)")
    flips, types = _frame_flips(data[HEADER_V4.size:toc_at], name) if flags & FLAG_EXTENSIONS else (RDF_TO_RUB, [])
    off, chunks = toc_end, []
    dctx = zstandard.ZstdDecompressor()
    for i, want in enumerate(sizes):
        packed, unpacked = TOC_ENTRY.unpack_from(data, toc_at + TOC_ENTRY.size * i)
        if unpacked != want or packed > len(data) - off:
            raise InputError(f"{name}: SPZ stream {i} is {unpacked} bytes ({packed} packed), {want} expected for "
                             f"{n} Gaussians (truncated or corrupt)")
        try:
            with dctx.stream_reader(io.BytesIO(data[off:off + packed])) as r:
                parts, got = [], 0
                while got <= want:   # in pieces: memory follows what the stream holds, not what the header claims
                    piece = r.read(min(1 << 20, want + 1 - got))
                    if not piece:
                        break
                    parts.append(piece)
                    got += len(piece)
                out = b"".join(parts)
        except zstandard.ZstdError as e:
            raise InputError(f"{name}: SPZ stream {i} is not valid zstd ({e})") from None
        if len(out) != want:
            raise InputError(f"{name}: SPZ stream {i} unpacks to {len(out)} bytes, {want} expected (corrupt)")
        chunks.append(np.frombuffer(out, np.uint8))
        off += packed
    if off != len(data):
        raise InputError(f"{name}: {len(data) - off} bytes after the SPZ streams (corrupt)")
    if not deg:
        chunks.append(np.zeros(0, np.uint8))
    scene = _decode_attributes(chunks, n, deg, frac, version, flips)
    return scene, {"version": version, "num_points": n, "sh_degree": deg, "fractional_bits": frac,
                   "antialiased": bool(flags & FLAG_ANTIALIASED), "extensions": types}


def _gunzip(data: bytes, name: str) -> bytes:
    """The gzip stream's content, never more than its SPZ header says (plus extension records)."""
    d = zlib.decompressobj(wbits=31)
    try:
        head = d.decompress(data, HEADER.size)
        if len(head) < HEADER.size:
            raise InputError(f"{name}: truncated SPZ (no header)")
        magic, version, n, deg, frac, flags, _ = HEADER.unpack_from(head)
        if magic != MAGIC:
            raise InputError(f"{name}: not an SPZ file (magic {magic:#010x}, expected {MAGIC:#010x})")
        _check_header(name, version, n, deg, frac, len(data) * MAX_RATIO)
        room = sum(_sizes(n, deg, version)) + (len(data) * MAX_RATIO if flags & FLAG_EXTENSIONS else 0)
        body = d.decompress(d.unconsumed_tail, room + 1)
    except zlib.error as e:
        raise InputError(f"{name}: not a gzip-compressed SPZ file ({e})") from None
    return head + body


def read_spz(path: str | Path) -> GaussianScene:
    """Read an SPZ file (versions 2-4: zstd, gzip or uncompressed) into a scene in our (RDF) frame."""
    return read_spz_with_header(path)[0]


def read_spz_with_header(path: str | Path) -> tuple[GaussianScene, dict]:
    """:func:`read_spz` and the header's values (version, count, degree, flags, extension types, container)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: SPZ file not found")
    data = path.read_bytes()
    if data[:4] == struct.pack("<I", MAGIC):
        version = struct.unpack_from("<I", data, 4)[0] if len(data) >= 8 else 0
        if version >= 4:
            scene, header = decode_spz_v4(data, str(path))
            return scene, {**header, "container": "zstd"}
        scene, header = decode_spz(data, str(path))
        return scene, {**header, "container": "uncompressed"}
    if data[:2] != b"\x1f\x8b":
        raise InputError(f"{path}: not an SPZ file (neither gzip nor an NGSP header)")
    scene, header = decode_spz(_gunzip(data, str(path)), str(path))
    return scene, {**header, "container": "gzip"}
