"""Fuzzing the splat readers: every format :func:`ssgwarp.formats.registry.read_scene` reads, from a small
valid file (written by our writers, or built from the layout for the read-only .ksplat), truncated,
bit-flipped, with its counts rewritten (to zero, one off, huge) and with NaN / inf written over its
values. Whatever the bytes, a read either returns a scene of finite values or raises the one-line
:class:`~ssgwarp.errors.InputError`: never another exception, never longer than the deadline, never
allocating more than a small multiple of the file's size (numpy's allocations, seen by tracemalloc).

Seeded (``derandomize``) and small by default; ``SSGWARP_FUZZ_EXAMPLES=N`` runs N examples per format
and mutation instead (docs/testing.md, "Fuzzing the splat readers")."""
from __future__ import annotations

import io
import json
import os
import re
import struct
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from ssgwarp.errors import InputError  # noqa: E402
from ssgwarp.formats.registry import read_scene, write_scene  # noqa: E402
from ssgwarp.formats.spz import encode_spz  # noqa: E402
from ssgwarp.raster.scene import GaussianScene  # noqa: E402

EXAMPLES = int(os.environ.get("SSGWARP_FUZZ_EXAMPLES", "8"))
FUZZ = settings(max_examples=EXAMPLES, derandomize=True, deadline=5000, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
ALLOC_FACTOR, ALLOC_SLACK = 64, 8 << 20   # peak numpy allocation <= 64 x the file's bytes + 8 MB


def _scene(n: int = 40, degree: int = 1) -> GaussianScene:
    g = torch.Generator().manual_seed(0)
    k = (degree + 1) ** 2 - 1
    return GaussianScene(torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g) * 0.3 - 2.0,
                         torch.randn(n, 4, generator=g), torch.randn(n, generator=g), torch.randn(n, 3, generator=g),
                         torch.randn(n, k, 3, generator=g) * 0.1 if k else None, None, degree)


def _ksplat(n: int = 6) -> bytes:
    """A one-section mode-1 .ksplat (two buckets of 4, the second partial), from the layout."""
    head, sec = bytearray(4096), bytearray(1024)
    head[1] = 1
    struct.pack_into("<IIIH", head, 4, 1, 0, 0, 0)
    struct.pack_into("<IH", head, 16, n, 1)
    struct.pack_into("<IIIIfHxxIxxxxIIH", sec, 0, n, n, 4, 2, 2.0, 12, 32767, 1, 1, 1)
    meta = struct.pack("<I", n - 4) + np.zeros((2, 3), "<f4").tobytes()
    rng = np.random.default_rng(0)
    rec = b"".join(rng.integers(0, 65535, 3).astype("<u2").tobytes() + np.full(3, 0.05, "<f2").tobytes()
                   + np.array([1, 0, 0, 0], "<f2").tobytes() + bytes([200, 100, 50, 255])
                   + rng.normal(0, 0.1, 9).astype("<f2").tobytes() for _ in range(n))
    return bytes(head) + bytes(sec) + meta + rec


def _seeds(tmp: Path) -> dict[str, tuple[Path, str]]:
    s = _scene()
    out = {}
    for fmt, name in (("ply", "s.ply"), ("compressed-ply", "s.compressed.ply"), ("splat", "s.splat"),
                      ("sog", "s.sog"), ("glb", "s.glb")):
        out[fmt] = (write_scene(tmp / name, s, fmt), fmt)
    out["spz4"] = (write_scene(tmp / "s4.spz", s, "spz"), "spz")
    out["spz3"] = (write_scene(tmp / "s3.spz", s, "spz", spz_version=3), "spz")
    (tmp / "raw.spz").write_bytes(encode_spz(s, version=2))
    out["spz-raw"] = (tmp / "raw.spz", "spz")
    (tmp / "s.ksplat").write_bytes(_ksplat())
    out["ksplat"] = (tmp / "s.ksplat", "ksplat")
    return out


KINDS = ["ply", "compressed-ply", "splat", "sog", "glb", "spz4", "spz3", "spz-raw", "ksplat"]


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fuzz-seeds")
    return {k: (p.read_bytes(), p.name, fmt) for k, (p, fmt) in _seeds(tmp).items()}


def _read(tmp: Path, name: str, data: bytes, fmt: str) -> None:
    """Read ``data`` as ``fmt``: a scene of finite values, or an InputError; within the allocation bound."""
    path = tmp / name
    path.write_bytes(data)
    tracemalloc.start()
    try:
        scene = read_scene(path, fmt=fmt)
    except InputError as e:
        assert "\n" not in str(e), str(e)
        scene = None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak <= ALLOC_FACTOR * len(data) + ALLOC_SLACK, f"{name}: {peak / 1e6:.1f} MB for {len(data)} bytes"
    if scene is not None:
        for t in scene.tensors().values():
            assert torch.isfinite(t).all()


def _sog_with_meta(data: bytes, edit) -> bytes:
    """The .sog bundle ``data`` with its meta.json changed by ``edit``."""
    z = zipfile.ZipFile(io.BytesIO(data))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as out:
        for name in z.namelist():
            body = z.read(name)
            out.writestr(name, edit(body) if name == "meta.json" else body)
    return buf.getvalue()


def _counts(kind: str, data: bytes, value: int) -> bytes:
    """``data`` with its Gaussian count(s) set to ``value``, where the format keeps them."""
    b = bytearray(data)
    v32 = value & 0xFFFFFFFF
    if kind in ("spz4", "spz-raw"):
        struct.pack_into("<I", b, 8, v32)
    elif kind == "spz3":
        import gzip
        raw = bytearray(gzip.decompress(data))
        struct.pack_into("<I", raw, 8, v32)
        return gzip.compress(bytes(raw))
    elif kind == "ksplat":
        if value % 3 == 0:
            struct.pack_into("<I", b, 16, v32)
            struct.pack_into("<I", b, 4096, v32 % 4096)
        struct.pack_into("<I", b, 4096 + 32 if value % 2 else 4096 + 36, v32)   # full or partial buckets
    elif kind in ("ply", "compressed-ply"):
        return re.sub(rb"element (vertex|chunk|sh) \d+", lambda m: b"element " + m.group(1) + b" %d" % value,
                      data, count=1 if kind == "ply" else 3)
    elif kind == "sog":
        return _sog_with_meta(data, lambda m: json.dumps({**json.loads(m), "count": value}).encode())
    elif kind == "glb":
        js_len = struct.unpack_from("<I", data, 12)[0]
        js = re.sub(rb'"count":\d+', b'"count":%d' % value, data[20:20 + js_len])
        js += b" " * (-len(js) % 4)
        rest = data[20 + js_len:]
        return struct.pack("<III", 0x46546C67, 2, 20 + len(js) + len(rest)) + struct.pack("<II", len(js), 0x4E4F534A) \
            + js + rest
    elif kind == "splat":
        return data[: max(0, min(len(data), 32 * value))] if value < len(data) // 32 else data + bytes(32)
    return bytes(b)


@pytest.mark.parametrize("kind", KINDS)
def test_truncated(kind, seeds, tmp_path):
    data, name, fmt = seeds[kind]

    @FUZZ
    @given(st.integers(0, len(data) - 1))
    def run(cut):
        _read(tmp_path, name, data[:cut], fmt)

    run()


@pytest.mark.parametrize("kind", KINDS)
def test_bit_flips(kind, seeds, tmp_path):
    data, name, fmt = seeds[kind]

    @FUZZ
    @given(st.lists(st.integers(0, 8 * len(data) - 1), min_size=1, max_size=8))
    def run(bits):
        b = bytearray(data)
        for bit in bits:
            b[bit // 8] ^= 1 << (bit % 8)
        _read(tmp_path, name, bytes(b), fmt)

    run()


@pytest.mark.parametrize("kind", KINDS)
def test_wrong_and_huge_counts(kind, seeds, tmp_path):
    data, name, fmt = seeds[kind]

    @FUZZ
    @given(st.sampled_from([0, 1, 39, 41, 257, 10 ** 6, 2 ** 31 - 1, 2 ** 32 - 1]) | st.integers(0, 2 ** 32 - 1))
    def run(count):
        _read(tmp_path, name, _counts(kind, data, count), fmt)

    run()


@pytest.mark.parametrize("kind", KINDS)
def test_nan_and_inf_values(kind, seeds, tmp_path):
    """NaN / inf float32 (and float16) patterns written over the body (past any header)."""
    data, name, fmt = seeds[kind]
    start = {"ply": data.find(b"end_header") + 11, "compressed-ply": data.find(b"end_header") + 11,
             "ksplat": 4096 + 1024, "glb": 20 + struct.unpack_from("<I", data, 12)[0] + 8}.get(kind, 0)
    patterns = [struct.pack("<f", v) for v in (float("nan"), float("inf"), -float("inf"), 3e38)] + \
               [struct.pack("<e", v) for v in (float("nan"), float("inf"))]

    @FUZZ
    @given(st.lists(st.tuples(st.integers(start, len(data) - 4), st.sampled_from(patterns)), min_size=1, max_size=6))
    def run(writes):
        b = bytearray(data)
        for off, pat in writes:
            b[off:off + len(pat)] = pat
        _read(tmp_path, name, bytes(b), fmt)

    run()
