"""PlayCanvas SOG (what SuperSplat publishes), version 2: the Gaussians' attributes as lossless WebP
images, one texel per Gaussian (row-major, texture ``width = 4 * ceil(sqrt(N) / 4)``, ``height = 4 *
ceil(N / width / 4)``), described by ``meta.json``; a folder, or the same files bundled in a zip ``.sog``.

``meta.json``: ``{"version": 2, "count": N, "means": {"mins", "maxs", "files": [means_l.webp,
means_u.webp]}, "scales": {"codebook": [256], "files": [scales.webp]}, "quats": {"files": [quats.webp]},
"sh0": {"codebook": [256], "files": [sh0.webp]}, "shN": {"count", "bands", "codebook": [256], "files":
[shN_centroids.webp, shN_labels.webp]}}`` (``shN`` only at SH degree >= 1).

* means: each coordinate as ``sign(x) ln(|x| + 1)``, 16 bits between that axis's ``mins`` and ``maxs``,
  the low byte in ``means_l``'s RGB, the high byte in ``means_u``'s;
* quats: the unit ``w x y z`` quaternion's "smallest three" in RGB (the components other than the
  largest, in index order, made positive-largest: ``(v * sqrt 2 + 1) / 2 * 255``), alpha ``252 +`` the
  largest component's index;
* scales: RGB index the 256-entry codebook of log scales; sh0: RGB index the codebook of ``f_dc``,
  alpha ``sigmoid(opacity) * 255``;
* shN: a palette of up to 65536 SH vectors; ``shN_labels`` RG hold each Gaussian's palette index (low
  byte, high byte); ``shN_centroids`` (``64 * K`` wide, K coefficients per channel) holds palette entry
  ``c``'s coefficient ``j`` at row ``c // 64``, column ``(c % 64) * K + j``, its RGB indexing the codebook.

Coordinates as our PLY (no conversion). What is lost: positions to 16 bits of their log-space range,
every scale, colour and SH value to one of 256 codebook values (1D k-means), the SH vectors to the
palette (exact up to 65536 Gaussians, a balanced median-split tree of 65536 leaves beyond), rotations
to 8 bits a component.
"""
from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np

from ..core.fileio import atomic_path
from ..errors import InputError
from ..raster.scene import GaussianScene
from .codec import arrays_scene, logit, scene_arrays, sigmoid, to_u8, write_atomic

PALETTE = 65536
_SQRT2 = math.sqrt(2.0)
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
MAX_RATIO = 16     # the most Gaussians per byte of the files a reader accepts (real SOGs: under 0.1)


# ----------------------------------------------------------------------------- quantisers
def codebook(values: np.ndarray, size: int = 256, iters: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """1D k-means of ``values`` into ``size`` levels: ``(codebook [size] float32 ascending, labels uint8)``."""
    v = np.asarray(values, np.float64).reshape(-1)
    sample = v if len(v) <= 200_000 else np.concatenate(
        [np.random.default_rng(0).choice(v, 200_000, replace=False), [v.min(), v.max()]])
    # half the levels at the quantiles, half evenly over the range: the sparse tails (a scene's few very
    # large Gaussians) keep levels near them
    half = size // 2
    c = np.unique(np.concatenate([np.quantile(sample, (np.arange(size - half) + 0.5) / (size - half)),
                                  np.linspace(sample.min(), sample.max(), half)]))
    for _ in range(iters):
        lab = _nearest(sample, c)
        sums, counts = np.bincount(lab, sample, len(c)), np.bincount(lab, minlength=len(c))
        c = np.unique(np.where(counts > 0, sums / np.maximum(counts, 1), c))
    c = np.concatenate([c, np.repeat(c[-1:], size - len(c))]).astype(np.float32)
    return c, _nearest(v, c.astype(np.float64)).astype(np.uint8)


def _nearest(v: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Index of the nearest of the ascending ``c`` for each of ``v``."""
    mid = (c[1:] + c[:-1]) / 2.0
    return np.searchsorted(mid, v).astype(np.int64)


def palette(x: np.ndarray, size: int = PALETTE) -> tuple[np.ndarray, np.ndarray]:
    """``(centroids [M, D], labels [N])`` with ``M <= size``: every row its own entry when ``N <= size``,
    else a balanced tree of median splits, ``floor(log2(size))`` levels deep, each group split at the median
    of its widest dimension (the centroids: the leaves' means)."""
    n = len(x)
    if n <= size:
        return x.copy(), np.arange(n)
    perm = np.arange(n)                 # x[perm] holds each group's rows together, groups in label order
    gid = np.zeros(n, np.int64)         # the group of each row of x[perm]
    for _ in range(int(math.log2(size))):
        xs = x[perm]
        starts = np.flatnonzero(np.r_[True, gid[1:] != gid[:-1]])
        count = np.diff(np.r_[starts, n])
        mean = np.add.reduceat(xs, starts, axis=0) / count[:, None]
        var = np.add.reduceat(xs * xs, starts, axis=0) / count[:, None] - mean ** 2
        key = xs[np.arange(n), np.argmax(var, axis=1)[gid]]
        o = np.lexsort((key, gid))      # inside each group, along its widest dimension
        perm = perm[o]
        upper = np.arange(n) - starts[gid] >= count[gid] // 2
        new = 2 * gid + upper
        gid = np.cumsum(np.r_[0, new[1:] != new[:-1]])
    starts = np.flatnonzero(np.r_[True, gid[1:] != gid[:-1]])
    cent = np.add.reduceat(x[perm], starts, axis=0) / np.diff(np.r_[starts, n])[:, None]
    labels = np.empty(n, np.int64)
    labels[perm] = gid
    return cent, labels


# ----------------------------------------------------------------------------- WebP
def _webp(rgba: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba, np.uint8), "RGBA").save(buf, "WEBP", lossless=True, quality=100,
                                                                         method=4, exact=True)
    return buf.getvalue()


def _unwebp(data: bytes, max_texels: int, what: str) -> np.ndarray:
    """``[H*W, 4]`` uint8 texels of a WebP image, refused before decoding when over ``max_texels``."""
    from PIL import Image

    try:
        im = Image.open(io.BytesIO(data))
        if im.format != "WEBP":
            raise InputError(f"{what} is not a WebP image ({im.format})")
        w, h = im.size
        if w * h > max_texels:
            raise InputError(f"{what} is {w}x{h}, more texels than the Gaussians need (corrupt)")
        arr = np.asarray(im.convert("RGBA"))
    except InputError:
        raise
    except Exception as e:   # PIL raises many types on bad images
        raise InputError(f"{what} is not a readable WebP image ({str(e).splitlines()[0] if str(e) else e})") from None
    return arr.reshape(-1, 4)


def _size(n: int) -> tuple[int, int]:
    w = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    return w, max(4, math.ceil(n / w / 4) * 4)


def _texture(cols: np.ndarray, n: int, alpha=255) -> np.ndarray:
    w, h = _size(n)
    t = np.zeros((h * w, 4), np.uint8)
    t[:n, :cols.shape[1]] = cols
    t[:n, 3] = alpha
    return t.reshape(h, w, 4)


# ----------------------------------------------------------------------------- writing
def sog_files(scene: GaussianScene) -> dict[str, bytes]:
    """``{file name: bytes}`` of the SOG of ``scene`` (``meta.json`` and its WebP textures)."""
    a = scene_arrays(scene)
    n, deg = len(scene), scene.sh_degree
    files: dict[str, bytes] = {}
    m = a["means"].astype(np.float64)
    lm = np.sign(m) * np.log1p(np.abs(m))
    lo, hi = lm.min(0), lm.max(0)
    q16 = np.clip(np.floor((lm - lo) / np.where(hi > lo, hi - lo, 1.0) * 65535.0 + 0.5), 0, 65535).astype(np.uint32)
    files["means_l.webp"] = _webp(_texture((q16 & 0xFF).astype(np.uint8), n))
    files["means_u.webp"] = _webp(_texture((q16 >> 8).astype(np.uint8), n))
    q = a["quats"]
    big = np.argmax(np.abs(q), axis=1)
    q = q * np.where(q[np.arange(n), big] < 0, -1.0, 1.0)[:, None]
    small = np.take_along_axis(q, _OTHERS[big], axis=1)
    files["quats.webp"] = _webp(_texture(to_u8((small * _SQRT2 + 1.0) / 2.0 * 255.0), n, (252 + big).astype(np.uint8)))
    sc_book, sc_lab = codebook(a["log_scales"])
    files["scales.webp"] = _webp(_texture(sc_lab.reshape(n, 3), n))
    dc_book, dc_lab = codebook(a["sh_dc"])
    files["sh0.webp"] = _webp(_texture(dc_lab.reshape(n, 3), n, to_u8(sigmoid(a["opacity"]) * 255.0)))
    meta = {"version": 2, "asset": {"generator": "ssgwarp"}, "count": n,
            "means": {"mins": lo.tolist(), "maxs": hi.tolist(), "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": sc_book.tolist(), "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": dc_book.tolist(), "files": ["sh0.webp"]}}
    if deg:
        k = (deg + 1) ** 2 - 1
        rest = a["sh_rest"].astype(np.float64).transpose(0, 2, 1).reshape(n, 3 * k)   # channel-major
        cent, labels = palette(rest)
        sh_book, sh_lab = codebook(cent)
        m_rows = math.ceil(len(cent) / 64)
        tex = np.zeros((m_rows * 64, k, 4), np.uint8)
        tex[:len(cent), :, :3] = sh_lab.reshape(len(cent), 3, k).transpose(0, 2, 1)
        tex[:, :, 3] = 255
        files["shN_centroids.webp"] = _webp(tex.reshape(m_rows, 64 * k, 4))
        lab = np.stack([labels & 0xFF, labels >> 8], 1).astype(np.uint8)
        files["shN_labels.webp"] = _webp(_texture(lab, n))
        meta["shN"] = {"count": len(cent), "bands": deg, "codebook": sh_book.tolist(),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}
    files["meta.json"] = json.dumps(meta).encode()
    return files


def sog_names(degree: int = 3) -> list[str]:
    """The files of a SOG folder (``meta.json`` last)."""
    return (["means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"]
            + (["shN_centroids.webp", "shN_labels.webp"] if degree else []) + ["meta.json"])


def write_sog(path: str | Path, scene: GaussianScene) -> Path:
    """Write ``scene`` as SOG: a ``.sog`` bundle (zip), or a folder when ``path`` is its ``meta.json``
    (the textures next to it; meta.json written last, so a finished folder is a complete one)."""
    path = Path(path)
    files = sog_files(scene)
    if path.name.lower() == "meta.json":
        meta = files.pop("meta.json")
        for name, data in files.items():
            write_atomic(path.parent / name, data)
        return write_atomic(path, meta)
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as z:
            for name in ["meta.json", *sorted(set(files) - {"meta.json"})]:
                z.writestr(zipfile.ZipInfo(name, (2026, 1, 1, 0, 0, 0)), files[name])
    return path


# ----------------------------------------------------------------------------- reading
class _Files:
    """The files of a SOG folder or bundle, each read with a size limit."""

    def __init__(self, path: Path):
        self.path, self.zip = path, None
        if path.is_dir():
            self.root = path
        elif path.name.lower() == "meta.json":
            self.root = path.parent
        else:
            try:
                self.zip = zipfile.ZipFile(path)
            except Exception as e:   # zipfile raises BadZipFile, OSError, ValueError, NotImplementedError...
                raise InputError(f"{path}: not a SOG bundle (not a readable zip file: {e})") from None
        self.budget = path.stat().st_size if self.zip else sum(
            f.stat().st_size for f in self.root.iterdir() if f.is_file())

    def read(self, name: str, limit: int) -> bytes:
        where = f"{self.path}: {name}"
        if not isinstance(name, str) or "/" in name or "\\" in name or name.startswith("."):
            raise InputError(f"{self.path}: meta.json names a file {name!r} outside the SOG")
        if self.zip is not None:
            try:
                info = self.zip.getinfo(name)
            except KeyError:
                raise InputError(f"{where} is missing from the bundle") from None
            if info.file_size > limit:
                raise InputError(f"{where} is {info.file_size} bytes, more than a SOG of this size holds (corrupt)")
            try:
                return self.zip.read(info)
            except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
                raise InputError(f"{where}: corrupt zip entry ({e})") from None
            except Exception as e:   # zlib errors of a damaged entry
                raise InputError(f"{where}: corrupt zip entry ({type(e).__name__}: {e})") from None
        f = self.root / name
        if not f.is_file():
            raise InputError(f"{where} not found (the SOG folder is incomplete)")
        if f.stat().st_size > limit:
            raise InputError(f"{where} is larger than a SOG of this size holds (corrupt)")
        return f.read_bytes()


def _meta(files: _Files) -> dict:
    try:
        meta = json.loads(files.read("meta.json", 1 << 24))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{files.path}: meta.json is not JSON ({e})") from None
    where = f"{files.path}: meta.json"
    if not isinstance(meta, dict):
        raise InputError(f"{where} is not a JSON object")
    if "version" not in meta:
        raise InputError(f"{where} has no version: the first SOG layout (2025) is not read; re-save it with "
                         f"SuperSplat or splat-transform")
    if meta.get("version") != 2:
        raise InputError(f"{where}: SOG version {meta.get('version')!r} is not supported (version 2 is read)")
    try:
        n = int(meta["count"])
        books = {k: np.asarray(meta[k]["codebook"], np.float64) for k in ("scales", "sh0")}
        lo, hi = np.asarray(meta["means"]["mins"], np.float64), np.asarray(meta["means"]["maxs"], np.float64)
        names = [meta["means"]["files"][0], meta["means"]["files"][1], meta["quats"]["files"][0],
                 meta["scales"]["files"][0], meta["sh0"]["files"][0]]
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise InputError(f"{where}: missing or malformed entry ({type(e).__name__}: {e}); expected SOG version 2's "
                         f"count, means, scales, quats and sh0") from None
    if n <= 0 or n > files.budget * MAX_RATIO:
        raise InputError(f"{where}: count {n} is not a Gaussian count its files can hold")
    if lo.shape != (3,) or hi.shape != (3,) or any(b.shape != (256,) for b in books.values()):
        raise InputError(f"{where}: means needs 3 mins and 3 maxs, each codebook 256 values")
    for v in (lo, hi, *books.values()):
        if not np.isfinite(v).all():
            raise InputError(f"{where}: NaN/inf in its ranges or codebooks")
    return {"n": n, "lo": lo, "hi": hi, "books": books, "names": names, "shN": meta.get("shN")}


def read_sog(path: str | Path) -> GaussianScene:
    """Read a SOG (version 2): a ``.sog`` bundle, a folder holding ``meta.json``, or that ``meta.json``."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: SOG file or folder not found")
    files = _Files(path)
    m = _meta(files)
    n = m["n"]
    limit = files.budget
    tex = 4 * n + 64 * 64 + 16 * int(math.sqrt(n) + 16)
    ml, mu, qt, sc, s0 = (_unwebp(files.read(nm, limit), tex, f"{path}: {nm}")[:n] for nm in m["names"])
    if min(len(t) for t in (ml, mu, qt, sc, s0)) < n:
        raise InputError(f"{path}: textures hold fewer texels than count {n} (corrupt)")
    v = (ml[:, :3].astype(np.float64) + 256.0 * mu[:, :3]) / 65535.0
    lm = m["lo"] + (m["hi"] - m["lo"]) * v
    means = np.sign(lm) * np.expm1(np.abs(lm))
    tag = qt[:, 3].astype(np.int64) - 252
    if ((tag < 0) | (tag > 3)).any():
        raise InputError(f"{path}: quats.webp alpha {int(qt[:, 3].min())}..{int(qt[:, 3].max())} outside 252..255 (corrupt)")
    small = (qt[:, :3].astype(np.float64) / 255.0 * 2.0 - 1.0) / _SQRT2
    quats = np.zeros((n, 4))
    np.put_along_axis(quats, _OTHERS[tag], small, axis=1)
    quats[np.arange(n), tag] = np.sqrt(np.clip(1.0 - (small ** 2).sum(1), 0.0, None))
    log_scales = m["books"]["scales"][sc[:, :3]]
    sh_dc = m["books"]["sh0"][s0[:, :3]]
    opacity = logit(s0[:, 3] / 255.0)
    sh_rest = None
    sh = m["shN"]
    if sh:
        try:
            bands, count = int(sh["bands"]), int(sh["count"])
            book = np.asarray(sh["codebook"], np.float64)
            cname, lname = sh["files"][0], sh["files"][1]
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise InputError(f"{path}: meta.json shN is malformed ({type(e).__name__}: {e})") from None
        if bands not in (1, 2, 3) or not 0 < count <= PALETTE or book.shape != (256,) or not np.isfinite(book).all():
            raise InputError(f"{path}: meta.json shN needs bands 1..3, count 1..65536 and a 256-value codebook")
        k = (bands + 1) ** 2 - 1
        rows = math.ceil(count / 64)
        cent = _unwebp(files.read(cname, limit), rows * 64 * k + 64 * k * 4, f"{path}: {cname}")
        if len(cent) < rows * 64 * k:
            raise InputError(f"{path}: {cname} holds {len(cent)} texels, {rows * 64 * k} expected for {count} entries")
        cent = cent[:rows * 64 * k].reshape(rows * 64, k, 4)[:count, :, :3]     # [entry, coefficient, rgb]
        lab = _unwebp(files.read(lname, limit), tex, f"{path}: {lname}")[:n]
        if len(lab) < n:
            raise InputError(f"{path}: {lname} holds fewer texels than count {n} (corrupt)")
        labels = lab[:, 0].astype(np.int64) | (lab[:, 1].astype(np.int64) << 8)
        if (labels >= count).any():
            raise InputError(f"{path}: {lname} names palette entries past its {count} (corrupt)")
        sh_rest = book[cent[labels]]        # [N, K, 3]
    return arrays_scene(means, log_scales, quats, opacity, sh_dc, sh_rest)
