"""The formats added for "every splat in, every splat out": SPZ version 4 (and the uncompressed legacy
stream, extension records), .ksplat, SOG and glTF (KHR_gaussian_splatting): each file's bytes against
its spec's layout (files built here from the layout, or written by our writers), round trips through the
renderer, gsply reading our SPZ 4, and the export command's new options."""
from __future__ import annotations

import gzip
import io
import json
import math
import struct
import zipfile

import numpy as np
import pytest
import torch

from ssgwarp.cli import main
from ssgwarp.errors import InputError
from ssgwarp.formats.gltf import write_glb
from ssgwarp.formats.ksplat import read_ksplat
from ssgwarp.formats.registry import detect_format, format_for_path, read_scene, write_scene
from ssgwarp.formats.sog import codebook, palette, write_sog
from ssgwarp.formats.spz import encode_spz, read_spz, read_spz_with_header, sh_flip_signs, write_spz
from ssgwarp.procedural import ring_cameras
from ssgwarp.raster.rendering import render_views
from ssgwarp.raster.scene import SH_C0, GaussianScene
from ssgwarp.core.sh import spherical_harmonics
from ssgwarp.services.losses import psnr


def _scene(degree: int = 2, density: float = 0.3) -> GaussianScene:
    from test_export import _scene as export_scene   # (the demo's scene with a trained scene's SH bands)

    return export_scene(degree, density)


def _tiny(means, quats=None, degree=0, sh_rest=None) -> GaussianScene:
    n = len(means)
    q = torch.tensor(quats, dtype=torch.float32) if quats is not None else torch.tensor([[1.0, 0, 0, 0]] * n)
    return GaussianScene(torch.tensor(means, dtype=torch.float32), torch.full((n, 3), -2.0), q, torch.zeros(n),
                         torch.zeros(n, 3), None if sh_rest is None else torch.tensor(sh_rest, dtype=torch.float32),
                         None, degree)


def _renders_close(a: GaussianScene, b: GaussianScene, db: float) -> float:
    cams = ring_cameras(3, 64, 48)
    bg = torch.ones(3)
    p = float(psnr(render_views(b, cams, bg, depth=False).rgb, render_views(a, cams, bg, depth=False).rgb))
    assert p >= db, p
    return p


# ----------------------------------------------------------------------------- SPZ version 4
def test_spz_v4_header_toc_and_streams(tmp_path):
    """Version 4: a 32-byte plaintext header, a table of contents of (compressed, uncompressed) uint64
    pairs, then one zstd frame per attribute holding exactly the legacy stream's bytes."""
    zstandard = pytest.importorskip("zstandard")
    s = _scene(1)
    n = len(s)
    data = write_spz(tmp_path / "s.spz", s).read_bytes()
    magic, version, count, deg, frac, flags, streams, toc = struct.unpack_from("<IIIBBBBI", data)
    assert (magic, version, count, deg, frac, flags, streams, toc) == (0x5053474E, 4, n, 1, 12, 0, 6, 32)
    assert data[20:32] == bytes(12)
    legacy = encode_spz(s, version=3)[16:]
    sizes = [9 * n, n, 3 * n, 3 * n, 4 * n, 9 * n]
    off, at = 32 + 16 * 6, 16
    for i, want in enumerate(sizes):
        packed, unpacked = struct.unpack_from("<QQ", data, 32 + 16 * i)
        assert unpacked == want
        frame = data[off:off + packed]
        assert frame[:4] == b"\x28\xb5\x2f\xfd"          # a zstd frame
        assert zstandard.ZstdDecompressor().decompressobj().decompress(frame) == legacy[at - 16:at - 16 + want]
        off, at = off + packed, at + want
    assert off == len(data)
    back, header = read_spz_with_header(tmp_path / "s.spz")
    assert header["container"] == "zstd" and header["version"] == 4
    torch.testing.assert_close(back.sh_rest, read_spz(write_spz(tmp_path / "v3.spz", s, version=3)).sh_rest)
    # degree 0: five streams, no SH stream
    d0 = write_spz(tmp_path / "d0.spz", _scene(0)).read_bytes()
    assert d0[15] == 5 and len(read_spz(tmp_path / "d0.spz")) == len(_scene(0))


def test_spz_uncompressed_legacy_stream_is_read(tmp_path):
    """"NGSP" with a version below 4 at the start of the file: the legacy stream without its gzip wrapper."""
    s = _scene(1)
    (tmp_path / "raw.spz").write_bytes(encode_spz(s, version=2))
    back, header = read_spz_with_header(tmp_path / "raw.spz")
    assert header["container"] == "uncompressed" and header["version"] == 2 and len(back) == len(s)
    torch.testing.assert_close(back.means, read_spz(write_spz(tmp_path / "g.spz", s, version=2)).means)


@pytest.mark.parametrize("frame,flips", [(4, (1, -1, -1)), (6, (1, 1, 1)), (7, (-1, -1, 1)), (1, (-1, 1, -1)),
                                         (0, (1, -1, -1))])
def test_spz_coordinate_system_record(tmp_path, frame, flips):
    """Adobe's coordinate-system record (0xADBE0003) names the frame the data is stored in; unknown
    records are skipped by their length. A scene stored in frame F reads back as the scene."""
    s = _scene(2)
    # store the scene in ``frame``: flip the axes that differ from RDF (positions, quaternions, SH parity)
    f = np.array(flips, np.float64)
    d = float(np.prod(f))
    q = s.quats.double().numpy()
    stored = s.replace(means=s.means * torch.tensor(f, dtype=torch.float32),
                       quats=torch.from_numpy(np.stack([q[:, 0], *(q[:, i + 1] * f[i] * d for i in range(3))], 1)).float(),
                       sh_rest=s.sh_rest * torch.from_numpy(sh_flip_signs(tuple(f), 8)).float()[None, :, None])
    # encode_spz converts RDF -> RUB (y, z flipped): undo that so the bytes hold ``stored`` as is
    as_is = stored.replace(means=stored.means * torch.tensor([1.0, -1, -1]),
                           quats=stored.quats * torch.tensor([1.0, 1, -1, -1]),
                           sh_rest=stored.sh_rest * torch.from_numpy(sh_flip_signs(k=8)).float()[None, :, None])
    raw = bytearray(encode_spz(as_is, version=3))
    raw[14] |= 0x2
    records = struct.pack("<II", 0x12340001, 3) + b"abc" + struct.pack("<III", 0xADBE0003, 4, frame)
    (tmp_path / "f.spz").write_bytes(gzip.compress(bytes(raw) + records))
    back, header = read_spz_with_header(tmp_path / "f.spz")
    assert header["extensions"] == [0x12340001, 0xADBE0003]
    torch.testing.assert_close(back.means, s.means, atol=2 ** -11, rtol=0)
    _renders_close(s, back, 38.0)


def test_spz_bad_records_and_rotated_frames(tmp_path):
    raw = bytearray(encode_spz(_scene(0), version=3))
    raw[14] |= 0x2
    for tail, msg in ((struct.pack("<III", 0xADBE0003, 4, 12), "rotated frames"),
                      (struct.pack("<II", 5, 1000), "past the records' end"), (b"\x01\x02", "truncated")):
        (tmp_path / "b.spz").write_bytes(gzip.compress(bytes(raw) + tail))
        with pytest.raises(InputError, match=msg):
            read_spz(tmp_path / "b.spz")


@pytest.mark.slow   # gsply's readers may compile with numba on first use
def test_gsply_and_ours_read_each_others_files(tmp_path, request):
    gsply = pytest.importorskip("gsply")
    threads = torch.get_num_threads()
    request.addfinalizer(lambda: torch.set_num_threads(threads))
    s = _scene(2)
    ours = read_spz(write_scene(tmp_path / "s.spz", s, "spz"))
    backend = gsply.active_backend()
    gsply.use_backend("auto")
    try:
        g = gsply.read_spz(str(tmp_path / "s.spz"))
    finally:
        gsply.use_backend(backend)
    np.testing.assert_allclose(np.asarray(g.means) * [1.0, -1.0, -1.0], ours.means.numpy(), atol=1e-5)
    np.testing.assert_allclose(np.asarray(g.sh0), ours.sh_dc.numpy(), atol=1e-4)
    np.testing.assert_allclose(np.asarray(g.opacities), ours.logit_opacities.numpy(), atol=1e-3)
    # the other way: gsply writes SPZ 4 and 3 (axes as given: we read them as RUB) and compressed PLY
    rng = np.random.default_rng(0)
    n = 300
    q = rng.normal(size=(n, 4))
    data = gsply.GSData(means=rng.uniform(-2, 2, (n, 3)).astype(np.float32),
                        scales=rng.uniform(-5, -1, (n, 3)).astype(np.float32),
                        quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                        opacities=rng.normal(size=n).astype(np.float32), sh0=rng.normal(0, 0.5, (n, 3)).astype(np.float32),
                        shN=rng.normal(0, 0.1, (n, 3, 3)).astype(np.float32))
    for version in (4, 3):
        gsply.write_spz(str(tmp_path / f"g{version}.spz"), data, version=version)
        back, header = read_spz_with_header(tmp_path / f"g{version}.spz")
        assert header["version"] == version and len(back) == n
        np.testing.assert_allclose(back.means.numpy() * [1, -1, -1], data.means, atol=2 ** -12)
        np.testing.assert_allclose(back.log_scales.numpy(), data.scales, atol=1 / 32 + 1e-6)
        np.testing.assert_allclose(back.sh_dc.numpy(), data.sh0, atol=0.5 / (0.15 * 255) + 1e-6)
    gsply.plywrite(str(tmp_path / "g.compressed.ply"), data, compressed=True)
    back = read_scene(tmp_path / "g.compressed.ply")
    assert len(back) == n and back.sh_degree == 1
    ref = gsply.plyread(str(tmp_path / "g.compressed.ply"))
    order = np.lexsort(np.asarray(ref.means).T)
    mine = np.lexsort(back.means.numpy().T)
    np.testing.assert_allclose(back.means.numpy()[mine], np.asarray(ref.means)[order], atol=1e-5)


# ----------------------------------------------------------------------------- .ksplat
def _ksplat(means, log_scales, quats, rgba, rest, mode: int, bucket_cap: int = 2) -> bytes:
    """A one-section .ksplat of the given values, built from the layout (SH degree from ``rest``'s width)."""
    n, k3 = len(means), rest.shape[1]
    deg = {0: 0, 9: 1, 24: 2, 45: 3}[k3]
    head = bytearray(4096)
    head[0], head[1] = 0, 1
    struct.pack_into("<I", head, 4, 1)
    struct.pack_into("<I", head, 16, n)
    struct.pack_into("<H", head, 20, mode)
    struct.pack_into("<ff", head, 36, -2.0, 2.0)
    # stored SH: per band, channel-major (the INRIA f_rest is channel-major over all bands)
    k = k3 // 3
    order = [ch * k + b * b - 1 + j for b in range(1, deg + 1) for ch in range(3) for j in range(2 * b + 1)]
    sh = rest[:, order]
    sec = bytearray(1024)
    block, qr = 4.0, 32767
    if mode == 0:
        buckets, full, partial, centres = 0, 0, 0, np.zeros((0, 3))
        meta = b""
        centre_b = [np.asarray(means, "<f4").tobytes()[i * 12:(i + 1) * 12] for i in range(n)]
    else:
        full, rem = divmod(n, bucket_cap)
        partial = 1 if rem else 0
        buckets = full + partial
        bucket = np.arange(n) // bucket_cap
        centres = np.stack([means[bucket == b].mean(0) for b in range(buckets)])
        meta = (np.array([rem] * partial, "<u4").tobytes() + centres.astype("<f4").tobytes())
        u = np.clip(np.round((means - centres[bucket]) / (block / 2 / qr) + qr), 0, 65535).astype("<u2")
        centre_b = [u[i].tobytes() for i in range(n)]
    struct.pack_into("<IIIIfHxxIxxxxIIH", sec, 0, n, n, bucket_cap, buckets, block, 12, 0 if mode == 0 else qr,
                     full, partial, deg)
    f = "<f4" if mode == 0 else "<f2"
    recs = []
    for i in range(n):
        shv = (np.asarray(sh[i], "<f4").tobytes() if mode == 0 else np.asarray(sh[i], "<f2").tobytes() if mode == 1
               else np.round((sh[i] + 2.0) / 4.0 * 255).astype(np.uint8).tobytes())
        recs.append(centre_b[i] + np.exp(log_scales[i]).astype(f).tobytes() + np.asarray(quats[i], f).tobytes()
                    + np.asarray(rgba[i], np.uint8).tobytes() + shv)
    return bytes(head) + bytes(sec) + meta + b"".join(recs)


@pytest.mark.parametrize("mode", [0, 1, 2])
def test_ksplat_modes_from_the_layout(tmp_path, mode):
    rng = np.random.default_rng(mode)
    n = 5
    means = rng.uniform(-1, 1, (n, 3))
    log_scales = rng.uniform(-4, -1, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rgba = rng.integers(0, 256, (n, 4))
    rest = rng.uniform(-0.5, 0.5, (n, 24))
    (tmp_path / "s.ksplat").write_bytes(_ksplat(means, log_scales, q, rgba, rest, mode))
    assert detect_format(tmp_path / "s.ksplat") == "ksplat"
    s = read_scene(tmp_path / "s.ksplat")
    tol = {0: 1e-6, 1: 2e-3, 2: 1e-2}[mode]
    np.testing.assert_allclose(s.means.numpy(), means, atol=tol * 10)
    np.testing.assert_allclose(s.log_scales.numpy(), log_scales, atol=tol)
    np.testing.assert_allclose(np.abs((s.quats.double().numpy() * q).sum(1)), 1.0, atol=tol)
    np.testing.assert_allclose(s.sh_dc.numpy(), (rgba[:, :3] / 255.0 - 0.5) / SH_C0, atol=1e-5)
    np.testing.assert_allclose(torch.sigmoid(s.logit_opacities).numpy(), np.clip(rgba[:, 3] / 255.0, 1e-6, 1 - 1e-6),
                               atol=1e-6)
    assert s.sh_degree == 2
    np.testing.assert_allclose(s.sh_rest.transpose(1, 2).reshape(n, 24).numpy(), rest, atol=tol * 2)


def test_ksplat_bad_files(tmp_path):
    good = _ksplat(np.zeros((3, 3)), np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)), np.full((3, 4), 128),
                   np.zeros((3, 0)), 1)
    cases = {"short": (good[:100], "header alone"), "cut": (good[:-5], "past the file's end"),
             "mode": (good[:20] + b"\x07\x00" + good[22:], "compression mode 7"),
             "count": (good[:16] + struct.pack("<I", 10 ** 9) + good[20:], "claims"),
             "version": (b"\x01" + good[1:], "version 1.1"),
             "buckets": (good[:4096 + 32] + struct.pack("<I", 2 ** 31) + good[4096 + 36:], "buckets")}
    for name, (data, msg) in cases.items():
        (tmp_path / f"{name}.ksplat").write_bytes(data)
        with pytest.raises(InputError, match=msg):
            read_ksplat(tmp_path / f"{name}.ksplat")


# ----------------------------------------------------------------------------- SOG
def test_sog_layout(tmp_path):
    from PIL import Image

    s = _scene(1)
    n = len(s)
    p = write_sog(tmp_path / "s.sog", s)
    z = zipfile.ZipFile(p)
    meta = json.loads(z.read("meta.json"))
    assert meta["version"] == 2 and meta["count"] == n and meta["shN"]["bands"] == 1 and meta["shN"]["count"] == n
    w = math.ceil(math.sqrt(n) / 4) * 4
    h = math.ceil(n / w / 4) * 4
    for name in ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp", "shN_labels.webp"):
        im = Image.open(io.BytesIO(z.read(name)))
        assert im.format == "WEBP" and im.size == (w, h), name
    cent = Image.open(io.BytesIO(z.read("shN_centroids.webp")))
    assert cent.size == (64 * 3, math.ceil(n / 64))
    quats = np.asarray(Image.open(io.BytesIO(z.read("quats.webp"))).convert("RGBA")).reshape(-1, 4)[:n]
    assert set(np.unique(quats[:, 3])) <= {252, 253, 254, 255}
    # the means: 16 bits of sign(x) ln(|x| + 1) between mins and maxs
    lo_t = np.asarray(Image.open(io.BytesIO(z.read("means_l.webp"))).convert("RGBA")).reshape(-1, 4)[:n, :3]
    hi_t = np.asarray(Image.open(io.BytesIO(z.read("means_u.webp"))).convert("RGBA")).reshape(-1, 4)[:n, :3]
    m = s.means.double().numpy()
    lm = np.sign(m) * np.log1p(np.abs(m))
    lo, hi = np.array(meta["means"]["mins"]), np.array(meta["means"]["maxs"])
    np.testing.assert_allclose(lo, lm.min(0), rtol=1e-6)
    q = (lo_t.astype(np.int64) + 256 * hi_t.astype(np.int64))
    np.testing.assert_array_equal(q, np.floor((lm - lo) / (hi - lo) * 65535 + 0.5).astype(np.int64))
    sh0 = np.asarray(Image.open(io.BytesIO(z.read("sh0.webp"))).convert("RGBA")).reshape(-1, 4)[:n]
    np.testing.assert_array_equal(sh0[:, 3], np.floor(torch.sigmoid(s.logit_opacities).double().numpy() * 255 + 0.5))


def test_sog_round_trip_folder_and_bundle(tmp_path):
    s = _scene(2)
    b = read_scene(write_scene(tmp_path / "s.sog", s, "sog"))
    f = read_scene(write_scene(tmp_path / "d" / "meta.json", s, "sog").parent)
    assert detect_format(tmp_path / "s.sog") == "sog" and detect_format(tmp_path / "d") == "sog"
    assert format_for_path("x/meta.json") == "sog" and format_for_path("x.sog") == "sog"
    assert len(b) == len(s) and b.sh_degree == 2
    torch.testing.assert_close(b.means, f.means) and torch.testing.assert_close(b.sh_rest, f.sh_rest)
    np.testing.assert_allclose(b.means.numpy(), s.means.numpy(), atol=2e-4)
    _renders_close(s, b, 35.0)


def test_sog_quantisers():
    v = np.random.default_rng(0).normal(size=20000)
    book, lab = codebook(v)
    assert book.shape == (256,) and (np.diff(book) >= 0).all()
    assert np.abs(book[lab] - v).mean() < 0.01                # 256 levels: mean error well under 1 % of sigma
    x = np.random.default_rng(1).normal(size=(3000, 9))
    cent, labels = palette(x, size=512)
    assert len(cent) == 512 and labels.max() == 511
    err = np.linalg.norm(cent[labels] - x, axis=1).mean()
    assert err < 0.8 * np.linalg.norm(x - x.mean(0), axis=1).mean()   # better than one centroid
    same, lab2 = palette(x[:100], size=512)
    np.testing.assert_array_equal(same, x[:100])


def test_sog_bad_files(tmp_path):
    s = _scene(1)
    good = write_sog(tmp_path / "s.sog", s).read_bytes()
    z = zipfile.ZipFile(io.BytesIO(good))
    files = {n: z.read(n) for n in z.namelist()}

    def bundle(name, **change):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as out:
            for n, d in {**files, **change}.items():
                if d is not None:
                    out.writestr(n, d)
        (tmp_path / name).write_bytes(buf.getvalue())
        return tmp_path / name

    meta = json.loads(files["meta.json"])
    cases = [(bundle("v1.sog", **{"meta.json": json.dumps({k: v for k, v in meta.items() if k != "version"})}),
              "no version"),
             (bundle("count.sog", **{"meta.json": json.dumps({**meta, "count": 10 ** 9})}), "count"),
             (bundle("miss.sog", **{"quats.webp": None}), "missing"),
             (bundle("img.sog", **{"quats.webp": b"RIFF0000WEBPjunk"}), "WebP"),
             (bundle("out.sog", **{"meta.json": json.dumps({**meta, "sh0": {**meta["sh0"], "files": ["../x"]}})}),
              "outside")]
    (tmp_path / "nozip.sog").write_bytes(b"PK\x03\x04junk")
    cases.append((tmp_path / "nozip.sog", "not a readable zip"))
    central = bytearray(good)
    at = good.index(b"PK\x01\x02")             # the first central-directory entry: "version needed" at +6
    central[at + 6:at + 8] = struct.pack("<H", 192)   # 19.2, which zipfile meets with NotImplementedError
    (tmp_path / "zipver.sog").write_bytes(bytes(central))
    cases.append((tmp_path / "zipver.sog", "not a readable zip"))
    for p, msg in cases:
        with pytest.raises(InputError, match=msg):
            read_scene(p)


# ----------------------------------------------------------------------------- glTF
def test_glb_layout_and_round_trip(tmp_path):
    c, sn = math.cos(math.radians(30)), math.sin(math.radians(30))
    one = _tiny([[1, 2, 3]], quats=[[c, 0, sn, 0]], degree=1, sh_rest=[[[0.5, 0, 0], [0, 0.25, 0], [0, 0, 0.125]]])
    data = write_glb(tmp_path / "o.glb", one).read_bytes()
    magic, version, total = struct.unpack_from("<III", data)
    assert (magic, version, total) == (0x46546C67, 2, len(data))
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942
    blob = data[28 + jlen:28 + jlen + blen]
    assert doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0 and prim["extensions"]["KHR_gaussian_splatting"]["kernel"] == "ellipse"
    assert prim["extensions"]["KHR_gaussian_splatting"]["colorSpace"] == "srgb_rec709_display"

    def attr(name):
        acc = doc["accessors"][prim["attributes"][name]]
        view = doc["bufferViews"][acc["bufferView"]]
        dt = "<f4" if acc["componentType"] == 5126 else "u1"
        return np.frombuffer(blob, dt, acc["count"] * {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]],
                             view["byteOffset"])

    np.testing.assert_allclose(attr("POSITION"), [-1, -2, 3])                 # RDF -> glTF's LUF
    np.testing.assert_allclose(attr("KHR_gaussian_splatting:ROTATION"), [0, -sn, 0, c], atol=1e-7)   # x y z w
    np.testing.assert_allclose(attr("KHR_gaussian_splatting:SCALE"), [math.exp(-2)] * 3, rtol=1e-6)
    np.testing.assert_allclose(attr("KHR_gaussian_splatting:OPACITY"), [0.5])
    # degree 1 (y, z, x): a 180-degree turn about z flips the y- and x-odd coefficients
    np.testing.assert_allclose(attr("KHR_gaussian_splatting:SH_DEGREE_1_COEF_0"), [-0.5, 0, 0])
    np.testing.assert_allclose(attr("KHR_gaussian_splatting:SH_DEGREE_1_COEF_1"), [0, 0.25, 0])
    np.testing.assert_allclose(attr("KHR_gaussian_splatting:SH_DEGREE_1_COEF_2"), [0, 0, -0.125])
    assert doc["accessors"][prim["attributes"]["POSITION"]]["min"] == [-1, -2, 3]
    s = _scene(3)
    back = read_scene(write_scene(tmp_path / "s.glb", s, "glb"))
    assert detect_format(tmp_path / "s.glb") == "glb"
    torch.testing.assert_close(back.means, s.means)
    torch.testing.assert_close(back.sh_rest, s.sh_rest)
    torch.testing.assert_close(back.log_scales, s.log_scales, atol=1e-5, rtol=0)


def test_sh_flips_of_the_gltf_frame():
    """The LUF flip's SH signs give, along flipped directions, the colours of the originals."""
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(32, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.randn(32, 3, generator=g, dtype=torch.float64)
    flipped = coeffs.clone()
    flipped[:, 1:] *= torch.from_numpy(sh_flip_signs((-1.0, -1.0, 1.0))).double()[None, :, None]
    torch.testing.assert_close(spherical_harmonics(3, dirs, coeffs),
                               spherical_harmonics(3, dirs * torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64),
                                                   flipped))


def _reglb(data: bytes, edit) -> bytes:
    """The GLB ``data`` with its JSON changed by ``edit`` (chunk and file lengths rewritten)."""
    jlen = struct.unpack_from("<I", data, 12)[0]
    js = json.dumps(edit(json.loads(data[20:20 + jlen]))).encode()
    js += b" " * (-len(js) % 4)
    rest = data[20 + jlen:]
    return struct.pack("<III", 0x46546C67, 2, 20 + len(js) + len(rest)) + struct.pack("<II", len(js), 0x4E4F534A) + js + rest


def test_glb_bad_files(tmp_path):
    good = write_glb(tmp_path / "g.glb", _scene(0)).read_bytes()
    cases = {"short": (good[:10], "too short"), "cut": (good[:-40], "at most the file's"),
             "magic": (b"glTX" + good[4:], "not a GLB"),
             "plain": (good.replace(b"KHR_gaussian_splatting", b"KHR_gaussian_splattinX"), "no mesh primitive"),
             "node": (_reglb(good, lambda d: {**d, "nodes": [{"mesh": 0, "scale": [2, 2, 2]}]}), "transform")}
    for name, (data, msg) in cases.items():
        (tmp_path / f"{name}.glb").write_bytes(data)
        with pytest.raises(InputError, match=msg):
            read_scene(tmp_path / f"{name}.glb", fmt="glb")


# ----------------------------------------------------------------------------- the export command
def test_export_new_formats(tmp_path, capsys):
    s = _scene(1)
    from ssgwarp.formats.ply import write_ply

    src = write_ply(tmp_path / "scene.ply", s)
    for out, extra in (("o.spz", []), ("o3.spz", ["--spz-version", "3"]), ("o.sog", []), ("o.glb", []),
                       ("d/meta.json", [])):
        assert main(["export", str(src), "--out", str(tmp_path / out), *extra]) == 0
    assert read_spz_with_header(tmp_path / "o3.spz")[1]["version"] == 3
    assert read_spz_with_header(tmp_path / "o.spz")[1]["version"] == 4
    assert len(read_scene(tmp_path / "d")) == len(s)
    out = capsys.readouterr().out
    assert "sog" in out and "glb" in out
    capsys.readouterr()
    assert main(["export", str(src), "--out", str(tmp_path / "o.ksplat")]) == 2
    assert "read, not written" in capsys.readouterr().err
    assert main(["export", str(src), "--out", str(tmp_path / "x.spz"), "--spz-version", "5"]) == 2
    assert main(["export", str(src), "--out", str(tmp_path / "x.glb"), "--spz-version", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--spz-version 5" in err[0] and "option of the spz format" in err[1]
