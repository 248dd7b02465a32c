"""COLMAP sparse models: readers for the binary and text formats.

A model folder (usually ``DATA/sparse/0``) holds ``cameras``, ``images`` and
``points3D`` as ``.bin`` or ``.txt`` files. The readers return plain
dataclasses with numpy arrays; :mod:`ssgwarp.capture.datasets` turns them into
:class:`~ssgwarp.core.cameras.Cameras`.

Conventions (COLMAP's): an image's ``qvec`` (wxyz) and ``tvec`` map world to
camera, ``x_cam = R(qvec) @ x_world + tvec``, with camera axes x right, y down,
z forward (the same as ours). Pixel centres are at integer + 0.5.

Camera models handled (others are rejected with a clear error):
``SIMPLE_PINHOLE (f, cx, cy)``, ``PINHOLE (fx, fy, cx, cy)``,
``SIMPLE_RADIAL (f, cx, cy, k)``, ``RADIAL (f, cx, cy, k1, k2)``,
``OPENCV (fx, fy, cx, cy, k1, k2, p1, p2)``,
``FULL_OPENCV (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6)``,
``OPENCV_FISHEYE (fx, fy, cx, cy, k1, k2, k3, k4)``,
``SIMPLE_RADIAL_FISHEYE (f, cx, cy, k)``, ``RADIAL_FISHEYE (f, cx, cy, k1, k2)``;
:attr:`ColmapCamera.distortion` gives the distortion model and its coefficients (as
:class:`ssgwarp.capture.lens.Lens` takes them).

Every malformed input (truncated file, bad counts, unknown model, unparsable
text) raises :class:`~ssgwarp.errors.InputError` naming the file.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from ..core.fileio import atomic_path
from ..core.geometry import quat_to_rotmat, rotmat_to_quat

# model id -> (name, number of parameters), as in COLMAP's camera model list
MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
MODEL_IDS = {name: mid for mid, (name, _) in MODELS.items()}
_ONE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")
_TWO_FOCALS = ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
SUPPORTED = _ONE_FOCAL + _TWO_FOCALS


@dataclass
class ColmapCamera:
    """One COLMAP camera (intrinsics at ``width`` x ``height``)."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # float64 [num_params]

    def _unsupported(self) -> InputError:
        return InputError(f"COLMAP camera {self.id}: model {self.model} is not supported (supported: "
                          f"{', '.join(SUPPORTED)}); undistort the images with colmap image_undistorter and load "
                          f"its output")

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` pinhole intrinsics (float64)."""
        p = self.params
        if self.model in _ONE_FOCAL:
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        elif self.model in _TWO_FOCALS:
            fx, fy, cx, cy = p[:4]
        else:
            raise self._unsupported()
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)

    @property
    def distortion(self) -> Optional[tuple[str, tuple[float, ...]]]:
        """``(model, coefficients)`` of the distortion (None for the pinhole models)."""
        if self.model in ("SIMPLE_PINHOLE", "PINHOLE"):
            return None
        if self.model not in SUPPORTED:
            raise self._unsupported()
        return self.model, tuple(float(v) for v in self.params[3 if self.model in _ONE_FOCAL else 4:])

    @property
    def is_distorted(self) -> bool:
        """Whether the camera bends lines: a fisheye model, or a radial-tangential one with a non-zero coefficient."""
        d = self.distortion
        return d is not None and ("FISHEYE" in d[0] or any(d[1]))


@dataclass
class ColmapImage:
    """One registered image: world-to-camera pose and its 2D observations."""

    id: int
    qvec: np.ndarray  # float64 [4] wxyz
    tvec: np.ndarray  # float64 [3]
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # float64 [M, 2]
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # int64 [M], -1 = none

    @property
    def R(self) -> np.ndarray:
        return qvec_to_rotmat(self.qvec)

    @property
    def viewmat(self) -> np.ndarray:
        """``[4, 4]`` world-to-camera (float64)."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.tvec
        return m


@dataclass
class ColmapPoints:
    """The sparse point cloud."""

    ids: np.ndarray    # int64 [P]
    xyz: np.ndarray    # float64 [P, 3]
    rgb: np.ndarray    # uint8 [P, 3]
    error: np.ndarray  # float64 [P]
    track_lengths: np.ndarray  # int64 [P]

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: Optional[ColmapPoints]
    path: Path


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """``[3, 3]`` rotation of a (normalised here) wxyz quaternion (:func:`ssgwarp.core.geometry.quat_to_rotmat`)."""
    q = _unit(q)
    if q is None:
        raise InputError(f"invalid quaternion {np.asarray(q).tolist()}")
    return quat_to_rotmat(torch.from_numpy(q), normalize=False).numpy()


def _unit(q) -> Optional[np.ndarray]:
    """``q / |q|`` (scaled first, so that no finite quaternion overflows), or None for a zero or non-finite one."""
    q = np.asarray(q, dtype=np.float64)
    if not np.isfinite(q).all():
        return None
    big = np.abs(q).max(initial=0.0)
    if not big > 0:
        return None
    q = q / big
    return q / np.linalg.norm(q)


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """wxyz quaternion (w >= 0) of a rotation matrix (:func:`ssgwarp.core.geometry.rotmat_to_quat`)."""
    return rotmat_to_quat(torch.from_numpy(np.asarray(R, dtype=np.float64))).numpy()


# ----------------------------------------------------------------------------- binary
class _Reader:
    """Bounds-checked little-endian reader over a file's bytes."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except OSError as e:
            raise InputError(f"{path}: cannot read ({e.strerror})") from None
        self.pos = 0

    def _need(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > len(self.buf):
            raise InputError(f"{self.path}: truncated or corrupt COLMAP file (ran out of data reading {what} "
                             f"at byte {self.pos} of {len(self.buf)})")

    def unpack(self, fmt: str, what: str) -> tuple:
        fmt = "<" + fmt
        n = struct.calcsize(fmt)
        self._need(n, what)
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return out

    def array(self, dtype, count: int, what: str) -> np.ndarray:
        dt = np.dtype(dtype).newbyteorder("<")
        self._need(count * dt.itemsize, what)
        out = np.frombuffer(self.buf, dtype=dt, count=count, offset=self.pos).copy()
        self.pos += count * dt.itemsize
        return out

    def cstring(self, what: str) -> str:
        end = self.buf.find(b"\x00", self.pos)
        if end < 0 or end - self.pos > 4096:
            raise InputError(f"{self.path}: truncated or corrupt COLMAP file (unterminated {what})")
        s = self.buf[self.pos:end]
        self.pos = end + 1
        try:
            return s.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{self.path}: corrupt COLMAP file ({what} is not UTF-8 text)") from None

    def count(self, what: str, min_bytes_each: int) -> int:
        (n,) = self.unpack("Q", what)
        if n * min_bytes_each > len(self.buf) - self.pos:
            raise InputError(f"{self.path}: truncated or corrupt COLMAP file ({what} = {n} does not fit "
                             f"in the {len(self.buf) - self.pos} bytes left)")
        return int(n)

    def finish(self) -> None:
        if self.pos != len(self.buf):
            raise InputError(f"{self.path}: corrupt COLMAP file ({len(self.buf) - self.pos} unexpected bytes "
                             f"after the last record)")


def read_cameras_binary(path: str | Path) -> dict[int, ColmapCamera]:
    r = _Reader(Path(path))
    n = r.count("number of cameras", 24)
    cams = {}
    for _ in range(n):
        cid, mid, w, h = r.unpack("iiQQ", "a camera record")
        if mid not in MODELS:
            raise InputError(f"{path}: corrupt COLMAP file (camera {cid} has unknown model id {mid})")
        name, npar = MODELS[mid]
        params = r.array(np.float64, npar, f"camera {cid} parameters")
        cams[cid] = _check_camera(ColmapCamera(cid, name, int(w), int(h), params), path)
    r.finish()
    return cams


def read_images_binary(path: str | Path) -> dict[int, ColmapImage]:
    r = _Reader(Path(path))
    n = r.count("number of images", 64)
    images = {}
    for _ in range(n):
        vals = r.unpack("idddddddi", "an image record")
        iid, q, t, cid = vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8]
        name = r.cstring(f"image {iid} name")
        m = r.count(f"image {iid} number of 2D points", 24)
        raw = r.array(np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), m, f"image {iid} 2D points")
        xys = np.stack([raw["x"], raw["y"]], axis=1) if m else np.zeros((0, 2))
        images[iid] = _check_image(ColmapImage(iid, q, t, cid, name, xys, raw["id"].astype(np.int64)), path)
    r.finish()
    return images


def read_points3d_binary(path: str | Path) -> ColmapPoints:
    r = _Reader(Path(path))
    n = r.count("number of points", 51)
    ids = np.empty(n, np.int64)
    xyz = np.empty((n, 3), np.float64)
    rgb = np.empty((n, 3), np.uint8)
    err = np.empty(n, np.float64)
    tl = np.empty(n, np.int64)
    rec = struct.Struct("<qdddBBBdQ")   # (the id read as int64: COLMAP ids are far below 2^63)
    buf, size = r.buf, len(r.buf)
    pos = r.pos
    for i in range(n):
        if pos + rec.size > size:
            r.pos = pos
            r._need(rec.size, f"point record {i}")
        pid, x, y, z, cr, cg, cb, e, t = rec.unpack_from(buf, pos)
        pos += rec.size + 8 * t
        if pos > size:
            raise InputError(f"{path}: truncated or corrupt COLMAP file (track of point {pid} runs past the end)")
        ids[i], xyz[i], rgb[i], err[i], tl[i] = pid, (x, y, z), (cr, cg, cb), e, t
    r.pos = pos
    r.finish()
    return _check_points(ColmapPoints(ids, xyz, rgb, err, tl), path)


# ----------------------------------------------------------------------------- text
def _text_lines(path: Path) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a COLMAP text file (not UTF-8 text)") from None
    return [(i + 1, ln.split()) for i, ln in enumerate(text.splitlines())]


def _parse(path: Path, lineno: int, fn, what: str):
    try:
        return fn()
    except (ValueError, IndexError, KeyError):
        raise InputError(f"{path}:{lineno}: cannot parse {what}") from None


def _int(tok: str) -> int:
    """An integer token of a COLMAP text file (an id, a size, a colour) in int64's range, else ValueError."""
    v = int(tok)
    if not -(1 << 63) <= v < 1 << 63:
        raise ValueError(tok)
    return v


def read_cameras_text(path: str | Path) -> dict[int, ColmapCamera]:
    path = Path(path)
    cams = {}
    for lineno, tok in _text_lines(path):
        if not tok or tok[0].startswith("#"):
            continue

        def cam():
            model = tok[1]
            if model not in MODEL_IDS:
                raise ValueError
            npar = MODELS[MODEL_IDS[model]][1]
            if len(tok) != 4 + npar:
                raise ValueError
            return ColmapCamera(_int(tok[0]), model, _int(tok[2]), _int(tok[3]),
                                np.array([float(v) for v in tok[4:]], dtype=np.float64))

        c = _parse(path, lineno, cam, "camera line (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...)")
        cams[c.id] = _check_camera(c, path)
    return cams


def read_images_text(path: str | Path) -> dict[int, ColmapImage]:
    path = Path(path)
    lines = [(n, t) for n, t in _text_lines(path) if not (t and t[0].startswith("#"))]
    # images come in pairs of lines (the second, the 2D points, may be empty)
    while lines and not lines[-1][1]:
        lines.pop()
    images = {}
    i = 0
    while i < len(lines):
        lineno, tok = lines[i]
        if not tok:  # a stray empty line between records
            i += 1
            continue

        def img():
            if len(tok) < 10:
                raise ValueError
            return ColmapImage(_int(tok[0]), np.array([float(v) for v in tok[1:5]]),
                               np.array([float(v) for v in tok[5:8]]), _int(tok[8]), " ".join(tok[9:]))

        im = _parse(path, lineno, img, "image line (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
        pts = lines[i + 1][1] if i + 1 < len(lines) else []
        if pts and len(pts) >= 10 and not _looks_like_points(pts):
            pts = []  # no points line: the next token list is the next image
            i += 1
        else:
            i += 2
        if pts:
            if len(pts) % 3:
                raise InputError(f"{path}:{lines[i - 1][0]}: cannot parse 2D points (expected X Y POINT3D_ID triples)")
            arr = _parse(path, lines[i - 1][0], lambda: np.array([float(v) for v in pts]).reshape(-1, 3),
                         "2D points")
            ids = _parse(path, lines[i - 1][0], lambda: np.array([_int(v) for v in pts[2::3]], np.int64),
                         "2D points (POINT3D_ID must be a whole number)")
            im.xys, im.point3d_ids = arr[:, :2], ids
        images[im.id] = _check_image(im, path)
    return images


def _looks_like_points(tok: list[str]) -> bool:
    if len(tok) % 3:
        return False
    try:
        float(tok[-1]), int(float(tok[-1]))
        return True
    except ValueError:
        return False


def read_points3d_text(path: str | Path) -> ColmapPoints:
    path = Path(path)
    ids, xyz, rgb, err, tl = [], [], [], [], []
    for lineno, tok in _text_lines(path):
        if not tok or tok[0].startswith("#"):
            continue

        def pt():
            if len(tok) < 8 or (len(tok) - 8) % 2:
                raise ValueError
            c = [int(v) for v in tok[4:7]]
            if any(not 0 <= v <= 255 for v in c):
                raise ValueError
            return _int(tok[0]), [float(v) for v in tok[1:4]], c, float(tok[7]), (len(tok) - 8) // 2

        p = _parse(path, lineno, pt, "point line (POINT3D_ID X Y Z R G B ERROR TRACK...)")
        ids.append(p[0]), xyz.append(p[1]), rgb.append(p[2]), err.append(p[3]), tl.append(p[4])
    pts = ColmapPoints(np.array(ids, np.int64), np.array(xyz, np.float64).reshape(-1, 3),
                       np.array(rgb, np.uint8).reshape(-1, 3), np.array(err, np.float64), np.array(tl, np.int64))
    return _check_points(pts, path)


# ----------------------------------------------------------------------------- checks
def _check_camera(c: ColmapCamera, path) -> ColmapCamera:
    if c.width <= 0 or c.height <= 0 or c.width > 1 << 20 or c.height > 1 << 20:
        raise InputError(f"{path}: corrupt COLMAP file (camera {c.id} has size {c.width}x{c.height})")
    if not np.all(np.isfinite(c.params)):
        raise InputError(f"{path}: corrupt COLMAP file (camera {c.id} has non-finite parameters)")
    if c.model in SUPPORTED and c.params[0] <= 0:
        raise InputError(f"{path}: corrupt COLMAP file (camera {c.id} has focal length {c.params[0]})")
    return c


def _check_image(im: ColmapImage, path) -> ColmapImage:
    if not np.all(np.isfinite(im.tvec)) or _unit(im.qvec) is None:
        raise InputError(f"{path}: corrupt COLMAP file (image {im.id} '{im.name}' has an invalid pose)")
    if not im.name:
        raise InputError(f"{path}: corrupt COLMAP file (image {im.id} has no name)")
    return im


def _check_points(p: ColmapPoints, path) -> ColmapPoints:
    bad = ~np.all(np.isfinite(p.xyz), axis=1)
    if bad.any():
        raise InputError(f"{path}: corrupt COLMAP file ({int(bad.sum())} points with non-finite coordinates)")
    return p


# ----------------------------------------------------------------------------- model
def _pick(folder: Path, stem: str) -> Optional[Path]:
    for ext in (".bin", ".txt"):
        p = folder / f"{stem}{ext}"
        if p.is_file():
            return p
    return None


def read_cameras(path: str | Path) -> dict[int, ColmapCamera]:
    path = Path(path)
    return read_cameras_binary(path) if path.suffix == ".bin" else read_cameras_text(path)


def read_images(path: str | Path) -> dict[int, ColmapImage]:
    path = Path(path)
    return read_images_binary(path) if path.suffix == ".bin" else read_images_text(path)


def read_points3d(path: str | Path) -> ColmapPoints:
    path = Path(path)
    return read_points3d_binary(path) if path.suffix == ".bin" else read_points3d_text(path)


def find_model(folder: str | Path) -> Optional[Path]:
    """The model folder under ``folder`` (itself, ``sparse/0`` or ``sparse``) holding cameras and images."""
    folder = Path(folder)
    for cand in (folder, folder / "sparse" / "0", folder / "sparse"):
        if _pick(cand, "cameras") and _pick(cand, "images"):
            return cand
    return None


def read_model(folder: str | Path, points: bool = True) -> ColmapModel:
    """Read a COLMAP model folder (``.bin`` preferred over ``.txt`` when both exist).

    ``points3D`` is optional (``model.points`` is None when absent or when
    ``points=False``). Images whose camera id is missing raise InputError.
    """
    folder = Path(folder)
    cam_p, img_p = _pick(folder, "cameras"), _pick(folder, "images")
    if cam_p is None or img_p is None:
        missing = [s for s, p in (("cameras", cam_p), ("images", img_p)) if p is None]
        raise InputError(f"{folder}: not a COLMAP model folder (no {' or '.join(m + '.bin/.txt' for m in missing)})")
    cams = read_cameras(cam_p)
    images = read_images(img_p)
    for im in images.values():
        if im.camera_id not in cams:
            raise InputError(f"{img_p}: image '{im.name}' refers to camera {im.camera_id}, "
                             f"which {cam_p.name} does not define")
    pts_p = _pick(folder, "points3D") if points else None
    pts = read_points3d(pts_p) if pts_p is not None else None
    return ColmapModel(cams, images, pts, folder)


# ----------------------------------------------------------------------------- writers (text; for tests and export)
def write_model_text(folder: str | Path, cameras: dict[int, ColmapCamera], images: dict[int, ColmapImage],
                     points: Optional[ColmapPoints] = None) -> None:
    """Write a model in COLMAP's text format (atomically, file by file)."""
    folder = Path(folder)
    lines = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for c in cameras.values():
        lines.append(" ".join([str(c.id), c.model, str(c.width), str(c.height)] + [repr(float(v)) for v in c.params]))
    with atomic_path(folder / "cameras.txt") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    lines = ["# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for im in images.values():
        lines.append(" ".join([str(im.id)] + [repr(float(v)) for v in (*im.qvec, *im.tvec)] + [str(im.camera_id), im.name]))
        lines.append(" ".join(f"{x!r} {y!r} {int(p)}" for (x, y), p in zip(im.xys.tolist(), im.point3d_ids.tolist())))
    with atomic_path(folder / "images.txt") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    if points is not None:
        lines = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
        for i in range(len(points)):
            x, y, z = points.xyz[i].tolist()
            r, g, b = points.rgb[i].tolist()
            lines.append(f"{int(points.ids[i])} {x!r} {y!r} {z!r} {r} {g} {b} {float(points.error[i])!r}")
        with atomic_path(folder / "points3D.txt") as tmp:
            tmp.write_text("\n".join(lines) + "\n")
