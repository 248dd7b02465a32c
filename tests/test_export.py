"""ssgwarp export: each format's bytes against its spec (header, field layout, bit packing, SPZ's
RUB axes), sizes against our PLY, round trips through the renderer (PSNR >= 40 dB), gsply reading
our files, and one-line errors for bad input."""
from __future__ import annotations

import gzip
import math
import re
import struct

import numpy as np
import pytest
import torch

from ssgwarp.formats.ply import write_ply
from ssgwarp.formats.codec import morton_order
from ssgwarp.formats.compressed_ply import pack_rotation, read_compressed_ply, unpack_rotation
from ssgwarp.formats.splat import read_splat
from ssgwarp.formats.registry import detect_format, format_for_path, read_scene, write_scene
from ssgwarp.formats.spz import (encode_spz, pack_smallest_three, read_spz, sh_flip_signs,
                                 unpack_smallest_three, write_spz)
from ssgwarp.cli import main
from ssgwarp.core.fileio import write_json
from ssgwarp.errors import InputError, SsgwarpError
from ssgwarp.evaluation.export import export
from ssgwarp.procedural import build_scene, ring_cameras
from ssgwarp.raster.rendering import render_views
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.core.sh import spherical_harmonics
from ssgwarp.services.losses import psnr

FORMATS = [("ply", "s.ply"), ("compressed-ply", "s.compressed.ply"), ("spz", "s.spz"), ("splat", "s.splat")]


def _scene(degree: int = 3, density: float = 1.0) -> GaussianScene:
    """The demo's procedural scene (~2900 Gaussians) with view-dependent colour of a trained scene's
    size: SH bands 1-3 of standard deviation 0.06, 0.03, 0.015."""
    s = build_scene(density).scene
    if degree == 0:
        return s
    g = torch.Generator().manual_seed(1)
    k = (degree + 1) ** 2 - 1
    band = torch.tensor([0.06] * 3 + [0.03] * 5 + [0.015] * 7)[:k]
    return s.with_sh_degree(degree).replace(sh_rest=torch.randn(len(s), k, 3, generator=g) * band[None, :, None])


def _tiny(means, quats=None, log_scales=None, opacity=None, dc=None, sh_rest=None, degree=0) -> GaussianScene:
    n = len(means)
    f = lambda v, shape: torch.zeros(shape) if v is None else torch.tensor(v, dtype=torch.float32)  # noqa: E731
    q = f(quats, (n, 4)) if quats is not None else torch.tensor([[1.0, 0, 0, 0]] * n)
    return GaussianScene(f(means, (n, 3)), f(log_scales, (n, 3)), q, f(opacity, (n,)), f(dc, (n, 3)),
                         None if sh_rest is None else torch.tensor(sh_rest, dtype=torch.float32), None, degree)


def _run(tmp_path, scene, name="run"):
    d = tmp_path / name
    d.mkdir()
    write_ply(d / "scene.ply", scene)
    cams = ring_cameras(4, 96, 72)
    cams.save(d / "cameras.json")
    write_json(d / "data.json", {"split": {"train": cams.names[:2], "test": cams.names[2:]}, "background": [1, 1, 1]})
    return d


def _header(data: bytes) -> list[str]:
    return data[: data.index(b"end_header\n")].decode("ascii").splitlines()


# ----------------------------------------------------------------------------- compressed PLY
def test_compressed_ply_header_and_layout(tmp_path):
    s = _scene(3)
    n, c = len(s), math.ceil(len(s) / 256)
    p = write_scene(tmp_path / "s.compressed.ply", s, "compressed-ply")
    data = p.read_bytes()
    lines = [ln for ln in _header(data) if not ln.startswith("comment")]
    chunk = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"] + \
            [f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"] + [f"{m}_{a}" for m in ("min", "max") for a in "rgb"]
    assert lines == (["ply", "format binary_little_endian 1.0", f"element chunk {c}"]
                     + [f"property float {f}" for f in chunk] + [f"element vertex {n}"]
                     + [f"property uint packed_{f}" for f in ("position", "rotation", "scale", "color")]
                     + [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(45)])
    body = len(data) - data.index(b"end_header\n") - len(b"end_header\n")
    assert body == c * 18 * 4 + n * 4 * 4 + n * 45
    # every decoded position lies inside its chunk's box, and is an original position to the 11-10-11 grid
    off = data.index(b"end_header\n") + len(b"end_header\n")
    ch = np.frombuffer(data, "<f4", c * 18, off).reshape(c, 18)
    back = read_compressed_ply(p)
    rows = np.arange(n) // 256
    pts = back.means.numpy()
    assert (pts >= ch[rows, 0:3] - 1e-5).all() and (pts <= ch[rows, 3:6] + 1e-5).all()
    step = (ch[:, 3:6] - ch[:, 0:3]).max() / 1023
    assert torch.cdist(back.means, s.means).min(dim=1).values.max() <= step


def test_compressed_ply_bit_packing():
    """Two Gaussians spanning the chunk: the packed words per the spec, bit by bit."""
    from ssgwarp.formats.compressed_ply import compressed_ply_bytes

    s = _tiny([[0, 0, 0], [1, 2, 3]], log_scales=[[-3, -3, -3], [-1, -2, -3]], opacity=[0.0, 10.0],
              dc=[[0, 0, 0], [1, 1, 1]])
    data = compressed_ply_bytes(s)
    off = data.index(b"end_header\n") + len(b"end_header\n")
    ch = np.frombuffer(data, "<f4", 18, off)
    np.testing.assert_allclose(ch[:12], [0, 0, 0, 1, 2, 3, -3, -3, -3, -1, -2, -3])
    v = np.frombuffer(data, "<u4", 8, off + 72).reshape(2, 4)
    assert v[0, 0] == 0 and v[1, 0] == 0xFFFFFFFF                     # 11-10-11 at the chunk's min and max
    assert v[0, 1] == v[1, 1] == (512 << 20) | (512 << 10) | 512       # identity: index 0, others at 0.5
    assert v[0, 2] == 0 and v[1, 2] == (2047 << 21) | (1023 << 11) | 0   # z: no range, 0
    assert v[0, 3] & 0xFF == 128 and v[1, 3] & 0xFF == 255             # sigmoid(0), sigmoid(10) on 8 bits
    assert v[0, 3] >> 8 == 0 and v[1, 3] >> 8 == 0xFFFFFF              # colours at the chunk's colour range


def test_compressed_ply_without_chunk_colours(tmp_path):
    """SuperSplat's older files: 12-field chunks, colours as plain 8-bit values in [0, 1]."""
    from plyfile import PlyData, PlyElement

    from ssgwarp.formats.compressed_ply import CHUNK_FIELDS

    chunk = np.zeros(1, [(f, "<f4") for f in CHUNK_FIELDS[:12]])
    for f, v in zip(CHUNK_FIELDS[:12], [0, 0, 0, 1, 1, 1, -4, -4, -4, -2, -2, -2]):
        chunk[f] = v
    vert = np.zeros(2, [(f, "<u4") for f in ("packed_position", "packed_rotation", "packed_scale", "packed_color")])
    vert["packed_position"] = [0, 0xFFFFFFFF]
    vert["packed_rotation"] = (512 << 20) | (512 << 10) | 512
    vert["packed_color"] = [(255 << 24) | (0 << 16) | (51 << 8) | 255, (128 << 24) | (128 << 16) | (128 << 8) | 0]
    PlyData([PlyElement.describe(chunk, "chunk"), PlyElement.describe(vert, "vertex")]).write(str(tmp_path / "o.ply"))
    assert detect_format(tmp_path / "o.ply") == "compressed-ply"
    s = read_scene(tmp_path / "o.ply")
    np.testing.assert_allclose(s.means.numpy(), [[0, 0, 0], [1, 1, 1]], atol=1e-6)
    np.testing.assert_allclose(s.base_colors.numpy(), [[1, 0, 0.2], [128 / 255] * 3], atol=1e-6)
    np.testing.assert_allclose(s.log_scales.numpy(), [[-4] * 3, [-4] * 3], atol=1e-6)
    assert s.opacities[0] > 0.999 and s.opacities[1] < 1e-5


def test_rotation_packings_round_trip():
    q = torch.nn.functional.normalize(torch.randn(500, 4, generator=torch.Generator().manual_seed(0)), dim=1)
    q = q.double().numpy()
    for back, tol in ((unpack_rotation(pack_rotation(q)), 2e-3), (unpack_smallest_three(pack_smallest_three(q)), 2e-3)):
        dots = np.abs((back * q).sum(1))   # q and -q are one rotation
        assert (1 - dots).max() < tol
        np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-6)


# ----------------------------------------------------------------------------- SPZ
def test_spz_header_layout_and_rub_axes(tmp_path):
    """A point at (1, 2, 3) in our (RDF) frame is stored at (1, -2, -3) in 24-bit fixed point with 12
    fractional bits; a 60 degree turn about y is stored as its RUB quaternion (0, -0.5, 0, 0.866)."""
    c, sn = math.cos(math.radians(30)), math.sin(math.radians(30))
    s = _tiny([[1, 2, 3]], quats=[[c, 0, sn, 0]], sh_rest=[[[0.5, 0, 0], [0, 0, 0], [0.5, 0, 0]]], degree=1)
    p = write_spz(tmp_path / "s.spz", s, version=3)
    raw = gzip.decompress(p.read_bytes())
    assert raw[:4] == b"NGSP"
    magic, version, n, deg, frac, flags, reserved = struct.unpack_from("<IIIBBBB", raw)
    assert (magic, version, n, deg, frac, flags, reserved) == (0x5053474E, 3, 1, 1, 12, 0, 0)
    assert len(raw) == 16 + 9 + 1 + 3 + 3 + 4 + 9
    fixed = [int.from_bytes(raw[16 + 3 * i: 19 + 3 * i], "little", signed=True) for i in range(3)]
    assert fixed == [4096, -8192, -12288]
    assert raw[25] == 128 and list(raw[26:29]) == [128, 128, 128]          # sigmoid(0) * 255, dc 0
    assert list(raw[29:32]) == [160, 160, 160]                             # (0 + 10) * 16
    comp = struct.unpack_from("<I", raw, 32)[0]
    assert comp >> 30 == 3                                                 # w is the largest
    assert (comp >> 10) & 0x3FF == (1 << 9) | round(511 * sn / math.sqrt(0.5))   # y: negative in RUB
    assert (comp >> 20) & 0x3FF == 0 and comp & 0x3FF == 0
    # SH: the y-odd coefficient changes sign, the x-odd one does not; x * 128 + 128 on 5 bits
    assert list(raw[36:45:3]) == [64, 128, 192]
    back = read_spz(p)
    np.testing.assert_allclose(back.means.numpy(), [[1, 2, 3]], atol=2 ** -12)
    np.testing.assert_allclose(back.sh_rest[0, :, 0].numpy(), [0.5, 0, 0.5], atol=1e-6)
    assert abs(float((back.quats[0] * torch.tensor([c, 0, sn, 0])).sum())) > 1 - 1e-5


def test_spz_sh_bits():
    """SH rounded to the given significant bits (buckets of 2^(8 - bits) around 128); more bits, closer."""
    s = _scene(2, density=0.3)
    n, k = len(s), 8
    errs = []
    for bits in ((5, 4), (6, 5), (8, 8)):
        raw = encode_spz(s, sh_bits=bits)
        sh = np.frombuffer(raw, np.uint8, n * k * 3, len(raw) - n * k * 3).reshape(n, k, 3).astype(int)
        assert (sh[:, :3] % (1 << (8 - bits[0])) == 0).all() and (sh[:, 3:] % (1 << (8 - bits[1])) == 0).all()
        back = np.asarray(sh, np.float64) / 128 - 1
        true = s.sh_rest.double().numpy() * sh_flip_signs(k=k)[None, :, None]
        errs.append(np.abs(back - true).max())
        assert errs[-1] <= 2.0 ** -bits[1] + 1 / 256 + 1e-9   # half a bucket, plus the rounding to 1/128
    assert errs[0] > errs[1] > errs[2]


def test_sh_flip_signs_follow_the_basis():
    """Coefficients times :func:`sh_flip_signs` seen along y- and z-flipped directions give the colours
    the originals give along the directions themselves."""
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(64, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.randn(64, 3, generator=g, dtype=torch.float64)
    flipped = coeffs.clone()
    flipped[:, 1:] *= torch.from_numpy(sh_flip_signs()).double()[None, :, None]
    a = spherical_harmonics(3, dirs, coeffs)
    b = spherical_harmonics(3, dirs * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64), flipped)
    torch.testing.assert_close(a, b)


def test_spz_version_2_and_large_scenes(tmp_path):
    s = _scene(1)
    p = write_spz(tmp_path / "v2.spz", s, version=2)
    raw = gzip.decompress(p.read_bytes())
    assert struct.unpack_from("<I", raw, 4)[0] == 2 and len(raw) == 16 + len(s) * (9 + 1 + 3 + 3 + 3 + 9)
    back = read_spz(p)
    assert (1 - (back.quats * torch.nn.functional.normalize(s.quats, dim=1)).sum(1).abs()).max() < 1e-3
    big = s.replace(means=s.means * 5000.0)   # beyond 24 bits at 12 fractional bits: fewer of them
    raw = encode_spz(big)
    assert raw[13] < 12
    torch.testing.assert_close(read_scene(write_spz(tmp_path / "big.spz", big)).means, big.means, atol=0.5, rtol=1e-4)


def test_spz_degree_4_keeps_three_bands(tmp_path):
    s = _scene(3, density=0.3)
    n = len(s)
    raw = encode_spz(s)
    sh3 = np.frombuffer(raw, np.uint8, n * 45, len(raw) - n * 45).reshape(n, 45)
    sh4 = np.concatenate([sh3, np.full((n, 27), 200, np.uint8)], 1)   # band 4: 8 more coefficients
    raw4 = raw[:12] + bytes([4]) + raw[13:len(raw) - n * 45] + sh4.tobytes()
    (tmp_path / "d4.spz").write_bytes(gzip.compress(raw4))
    back, ref = read_spz(tmp_path / "d4.spz"), read_spz(write_spz(tmp_path / "d3.spz", s))
    assert back.sh_degree == 3
    torch.testing.assert_close(back.sh_rest, ref.sh_rest)


# ----------------------------------------------------------------------------- .splat
def test_splat_record_layout(tmp_path):
    s = _tiny([[1, 2, 3], [4, 5, 6]], log_scales=[[-2, -2, -2], [0, 0, 0]], opacity=[0.0, 0.0],
              dc=[[0, 0, 0], [1, 0, -1]])
    data = write_scene(tmp_path / "s.splat", s, "splat").read_bytes()
    assert len(data) == 64
    pos, scale = np.frombuffer(data, "<f4", 3, 0), np.frombuffer(data, "<f4", 3, 12)
    np.testing.assert_allclose(pos, [4, 5, 6])                    # the larger Gaussian first
    np.testing.assert_allclose(scale, [1, 1, 1])                  # linear scales
    c0 = 0.28209479177387814
    assert list(data[24:28]) == [round((0.5 + c0) * 255), 128, round((0.5 - c0) * 255), 128]
    assert list(data[28:32]) == [255, 128, 128, 128]              # identity wxyz * 128 + 128
    np.testing.assert_allclose(np.frombuffer(data, "<f4", 3, 32 + 12), [math.exp(-2)] * 3, rtol=1e-6)
    back = read_splat(tmp_path / "s.splat")
    assert back.sh_degree == 0 and len(back) == 2


# ----------------------------------------------------------------------------- sizes and round trips
def test_sizes_against_our_ply(tmp_path):
    """Degree-3 source scene (our PLY, 248 bytes a Gaussian), exported with --sh-degree 0: compressed
    PLY and SPZ at least 8x smaller."""
    run = _run(tmp_path, _scene(3))
    src = (run / "scene.ply").stat().st_size
    ratios = {}
    for fmt, name in FORMATS:
        r = export(run, tmp_path / name, fmt, sh_degree=0, views=0)
        ratios[fmt] = src / r["bytes"]
        assert r["sh_degree"] == 0 and r["psnr"] == []
    assert ratios["compressed-ply"] >= 8 and ratios["spz"] >= 8, ratios
    assert ratios["splat"] == pytest.approx(248 / 32, rel=0.02)


@pytest.mark.parametrize("degree", [0, 3])
def test_round_trip_renders(tmp_path, degree):
    """Renders of each file read back against renders of the scene at the exported degree: >= 40 dB."""
    s = _scene(degree)
    cams = ring_cameras(3, 96, 72)
    for fmt, name in FORMATS:
        if fmt == "splat" and degree:
            continue
        back = read_scene(write_scene(tmp_path / name, s, fmt))
        assert detect_format(tmp_path / name) == fmt and back.sh_degree == s.sh_degree and len(back) == len(s)
        a = render_views(s, cams, [1, 1, 1], depth=False).rgb
        b = render_views(back, cams, [1, 1, 1], depth=False).rgb
        assert float(psnr(b, a)) >= (100 if fmt == "ply" else 40), fmt
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temporary files left


def test_export_command_reports_psnr(tmp_path, capsys):
    run = _run(tmp_path, _scene(3))
    assert main(["export", str(run), "--out", str(tmp_path / "o.spz"), "--check-views", "2"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"o\.spz: spz, \d+ Gaussians, SH degree 3, .*x smaller", out), out
    worst = float(re.search(r"PSNR ([\d.]+) dB \(worst of 2 view", out).group(1))
    assert worst >= 40
    # truncated SH and the identity-free PLY
    r = export(run, tmp_path / "o1.ply", sh_degree=1, views=1)
    assert r["format"] == "ply" and r["sh_degree"] == 1 and read_scene(tmp_path / "o1.ply").sh_degree == 1


# ----------------------------------------------------------------------------- gsply reads our files
@pytest.mark.slow   # gsply compiles its compressed-PLY reader with numba on first use (about 5-8 s, then cached)
def test_gsply_reads_our_files(tmp_path, request):
    """gsply (an independent implementation) decodes our compressed PLY and SPZ to what our readers do."""
    gsply = pytest.importorskip("gsply")
    # numba's threading layer (gsply's readers) changes torch's intra-op thread count: give it back after
    threads = torch.get_num_threads()
    request.addfinalizer(lambda: torch.set_num_threads(threads))
    s = _scene(1, density=0.5)
    n = len(s)
    ours = read_compressed_ply(write_scene(tmp_path / "s.compressed.ply", s, "compressed-ply"))
    g = gsply.plyread(str(tmp_path / "s.compressed.ply"))
    np.testing.assert_allclose(np.asarray(g.means), ours.means.numpy(), atol=1e-5)
    np.testing.assert_allclose(np.asarray(g.scales), ours.log_scales.numpy(), atol=1e-4)
    np.testing.assert_allclose(np.asarray(g.sh0), ours.sh_dc.numpy(), atol=1e-4)
    np.testing.assert_allclose(np.asarray(g.shN).reshape(n, 3, 3), ours.sh_rest.numpy(), atol=1e-5)
    ours = read_spz(write_scene(tmp_path / "s.spz", s, "spz"))
    backend = gsply.active_backend()
    gsply.use_backend("auto")   # its C++ SPZ reader where the wheel has it (no JIT)
    try:
        g = gsply.read_spz(str(tmp_path / "s.spz"))
    finally:
        gsply.use_backend(backend)
    flip = np.array([1.0, -1.0, -1.0])   # gsply hands SPZ's RUB axes over unconverted
    np.testing.assert_allclose(np.asarray(g.means) * flip, ours.means.numpy(), atol=1e-5)
    np.testing.assert_allclose(np.asarray(g.sh0), ours.sh_dc.numpy(), atol=1e-4)
    np.testing.assert_allclose(np.asarray(g.shN).reshape(n, 3, 3) * [[-1], [-1], [1]], ours.sh_rest.numpy(),
                               atol=1e-5)
    dots = np.abs((np.asarray(g.quats, np.float64) * [1, 1, -1, -1] * ours.quats.double().numpy()).sum(1))
    assert (1 - dots).max() < 1e-5


# ----------------------------------------------------------------------------- bad input
def test_errors(tmp_path, capsys):
    run = _run(tmp_path, _scene(1))

    def fails(argv, *fragments):
        capsys.readouterr()
        assert main([str(a) for a in argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ssgwarp: error: "), err
        for f in fragments:
            assert f in err[0], err[0]

    fails(["export", run, "--format", "spx", "--out", tmp_path / "o.spz"], "unknown format 'spx'", "'spz'")
    fails(["export", run, "--out", tmp_path / "o.xyz"], "cannot tell the format", "--format")
    (tmp_path / "empty").mkdir()
    fails(["export", tmp_path / "empty", "--out", tmp_path / "o.spz"], "no scene.ply")
    fails(["export", run, "--out", tmp_path / "o.spz", "--sh-degree", "2"], "carries SH degree 1", "0..1")
    fails(["export", run, "--out", tmp_path / "o.splat", "--sh-degree", "1"], "splat format holds SH up to degree 0")
    fails(["export", run, "--out", run / "scene.ply", "--force"], "is the scene being exported")
    fails(["export", run, "--out", tmp_path], "is a folder")
    (tmp_path / "o.spz").write_bytes(b"keep")
    fails(["export", run, "--out", tmp_path / "o.spz"], "already holds", "--force")
    assert (tmp_path / "o.spz").read_bytes() == b"keep"
    fails(["export", run, "--out", tmp_path / "o2.spz", "--check-views", "-1"], "--check-views")
    fails(["export", run, "--out", tmp_path / "o2.spz", "--spz-sh-bits", "9,1"], "--spz-sh-bits 9,1", "1..8")
    fails(["export", run, "--out", tmp_path / "o2.splat", "--spz-sh-bits", "8,8"], "option of the spz format")
    assert main(["export", str(run), "--out", str(tmp_path / "o.spz"), "--force", "--check-views", "0"]) == 0
    assert detect_format(tmp_path / "o.spz") == "spz"
    # a file in any format converts to another (SPZ -> .splat here)
    assert main(["export", str(tmp_path / "o.spz"), "--out", str(tmp_path / "o.splat"), "--sh-degree", "0"]) == 0
    assert len(read_splat(tmp_path / "o.splat")) == len(read_spz(tmp_path / "o.spz"))
    assert format_for_path("a.compressed.ply") == "compressed-ply" and format_for_path("a.PLY") == "ply"


def test_corrupt_files_are_refused(tmp_path):
    s = _scene(1, density=0.3)
    spz = write_spz(tmp_path / "s.spz", s, version=3)
    raw = gzip.decompress(spz.read_bytes())
    cases = {
        "cut.spz": (gzip.compress(raw[:-10]), "truncated or corrupt"),
        "magic.spz": (gzip.compress(b"XXXX" + raw[4:]), "not an SPZ file"),
        "v9.spz": (gzip.compress(raw[:4] + struct.pack("<I", 9) + raw[8:]), "version 9"),
        "ext.spz": (gzip.compress(raw[:14] + bytes([2]) + raw[15:] + struct.pack("<II", 7, 99)), "extension record"),
        "v1.spz": (gzip.compress(raw[:4] + struct.pack("<I", 1) + raw[8:]), "version 1"),
        "v4.spz": (raw[:4] + struct.pack("<I", 4) + bytes(24), "no Gaussians"),
        "gz.spz": (b"\x1f\x8b" + b"junk" * 4, "not a gzip-compressed SPZ"),
        "odd.splat": (bytes(33), "multiple of 32"),
    }
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match=msg):
            read_scene(tmp_path / name)
    cply = write_scene(tmp_path / "c.compressed.ply", s, "compressed-ply").read_bytes()
    bad = cply.replace(b"element chunk 4", b"element chunk 3", 1)
    assert bad != cply
    (tmp_path / "bad.compressed.ply").write_bytes(bad)
    with pytest.raises(InputError, match="chunk"):
        read_scene(tmp_path / "bad.compressed.ply")
    (tmp_path / "x.bin").write_bytes(b"hello")
    with pytest.raises(InputError, match="not a splat file"):
        read_scene(tmp_path / "x.bin")
    with pytest.raises(SsgwarpError):
        write_scene(tmp_path / "o.x", s, "jpeg")


def test_morton_order_groups_neighbours():
    pts = np.random.default_rng(0).random((4096, 3))
    o = morton_order(pts)
    assert sorted(o.tolist()) == list(range(4096))
    extent = np.ptp(pts[o].reshape(16, 256, 3), axis=1).max(axis=1)   # chunks of 256 in that order
    assert extent.mean() < 0.75   # random chunks would each span nearly the whole unit cube
