"""Lens distortion: the models captures use, and their removal into a pinhole crop.

:class:`Lens` is one distortion model with its coefficients, acting on normalised
camera coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)`` (pixel centres at
integer + 0.5, as everywhere in ssgwarp). Models (COLMAP's names and parameter
orders; OpenCV's formulas):

* ``SIMPLE_RADIAL (k)``, ``RADIAL (k1, k2)``, ``OPENCV (k1, k2, p1, p2)``,
  ``FULL_OPENCV (k1, k2, p1, p2, k3, k4, k5, k6)``: radial factor
  ``(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`` plus the
  tangential terms ``2 p1 x y + p2 (r^2 + 2 x^2)``, ``p1 (r^2 + 2 y^2) + 2 p2 x y``;
* ``OPENCV_FISHEYE (k1, k2, k3, k4)``, ``RADIAL_FISHEYE (k1, k2)``,
  ``SIMPLE_RADIAL_FISHEYE (k)``: equidistant fisheye, ``theta = atan(r)``,
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, the
  distorted point at radius ``theta_d`` in the direction of ``(x, y)``.

:func:`plan_undistortion` turns the distorted cameras of a capture into pinhole
cameras whose every pixel has a source ("alpha = 0", as COLMAP's
``image_undistorter`` with ``blank_pixels = 0``): each camera keeps its focal
length (pixels near the principal point keep their size: no upsampling, no
loss of resolution), and the output image is the largest axis-aligned rectangle
of the undistorted image plane whose every pixel centre maps, through the
forward distortion, inside the source image's pixel centres
``[0.5, W - 0.5] x [0.5, H - 0.5]`` -- so bilinear resampling never reads
padding and never extrapolates. The valid region is found per pixel on the
undistorted grid (forward map inside the source and Jacobian determinant
positive, i.e. before any fold of the lens map, connected to the principal
point); its bounds come from inverting the source border with Newton's method.
All cameras of a capture share one output size (the largest that fits every
camera's region); each camera gets its own principal point. A rectangle
smaller than ``min_area`` (default half) of the source image is refused with an
:class:`~ssgwarp.errors.InputError` naming the camera.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import torch

from ..core.imaging import resize_nearest
from ..errors import InputError

# model -> parameter names (COLMAP's order, after fx/fy/cx/cy)
MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_RADIAL": ("k",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
    "RADIAL_FISHEYE": ("k1", "k2"),
    "SIMPLE_RADIAL_FISHEYE": ("k",),
}
FISHEYE = ("OPENCV_FISHEYE", "RADIAL_FISHEYE", "SIMPLE_RADIAL_FISHEYE")
MIN_AREA = 0.5          # smallest usable crop, as a share of the source image's area
_MAX_GROW = 1.0         # the undistorted frame is searched up to this x the source size beyond each side of the
                        # principal point (2x the source size in all, as COLMAP's max_scale)
_CHUNK = 1 << 20        # grid points per block when scanning the undistorted frame


@dataclass(frozen=True)
class Lens:
    """A distortion model and its coefficients (COLMAP's order, see :data:`MODELS`)."""

    model: str
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise InputError(f"lens model {self.model} is not supported (supported: {', '.join(MODELS)})")
        p = tuple(float(v) for v in self.params)
        if len(p) != len(MODELS[self.model]):
            raise InputError(f"lens model {self.model} takes {len(MODELS[self.model])} coefficients "
                             f"({' '.join(MODELS[self.model])}), got {len(p)}")
        if not np.all(np.isfinite(p)):
            raise InputError(f"lens model {self.model}: non-finite coefficients {list(p)}")
        object.__setattr__(self, "params", p)

    @property
    def is_pinhole(self) -> bool:
        """True when the model maps every point to itself (a radial-tangential model with zero coefficients)."""
        return self.model not in FISHEYE and not any(self.params)

    def to_json(self) -> dict:
        return {"model": self.model, "params": dict(zip(MODELS[self.model], self.params))}

    def describe(self) -> str:
        return f"{self.model} " + " ".join(f"{k}={v:g}" for k, v in zip(MODELS[self.model], self.params))

    def _opencv(self) -> tuple[float, ...]:
        """``k1 k2 p1 p2 k3 k4 k5 k6`` of a radial-tangential model."""
        p = self.params
        if self.model == "SIMPLE_RADIAL":
            return (p[0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if self.model == "RADIAL":
            return (p[0], p[1], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if self.model == "OPENCV":
            return p + (0.0,) * 4
        return p

    def _fisheye(self) -> tuple[float, ...]:
        return self.params + (0.0,) * (4 - len(self.params))

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward map of normalised coordinates (float64 numpy); NaN where the model is undefined
        (a rational model's denominator <= 0)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.model in FISHEYE:
            k1, k2, k3, k4 = self._fisheye()
            r = np.hypot(x, y)
            th = np.arctan(r)
            t2 = th * th
            thd = th * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            tiny = r < 1e-12
            s = np.where(tiny, 1.0, thd / np.where(tiny, 1.0, r))  # theta_d / r -> 1 at the centre
            return x * s, y * s
        k1, k2, p1, p2, k3, k4, k5, k6 = self._opencv()
        r2 = x * x + y * y
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / np.where(den > 0, den, np.nan)
        xy = x * y
        return (x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy)

    def jacobian_det(self, x: np.ndarray, y: np.ndarray, eps: float = 1e-6) -> np.ndarray:
        """Determinant of the forward map's Jacobian (central differences); <= 0 past a fold of the lens map."""
        xa, ya = self.distort(x + eps, y)
        xb, yb = self.distort(x - eps, y)
        xc, yc = self.distort(x, y + eps)
        xd, yd = self.distort(x, y - eps)
        return ((xa - xb) * (yc - yd) - (ya - yb) * (xc - xd)) / (4.0 * eps * eps)

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iters: int = 40,
                  tol: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
        """Inverse map by Newton's method from ``(xd, yd)``; NaN where it does not converge (points
        the lens cannot produce, e.g. past the largest radius of a folding model)."""
        xd = np.asarray(xd, dtype=np.float64)
        yd = np.asarray(yd, dtype=np.float64)
        x, y = xd.copy(), yd.copy()
        eps = 1e-7
        for _ in range(iters):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            ax, ay = self.distort(x + eps, y)
            bx, by = self.distort(x, y + eps)
            j11, j21 = (ax - fx) / eps, (ay - fy) / eps
            j12, j22 = (bx - fx) / eps, (by - fy) / eps
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) > 1e-12, det, np.nan)
            dx = (j22 * ex - j12 * ey) / det
            dy = (-j21 * ex + j11 * ey) / det
            step = np.hypot(dx, dy)
            cap = np.maximum(0.5 * (1.0 + np.hypot(x, y)), 1e-3)   # damped: never jump across the plane
            scale = np.where(step > cap, cap / np.where(step > 0, step, 1.0), 1.0)
            x, y = x - dx * scale, y - dy * scale
        fx, fy = self.distort(x, y)
        bad = ~(np.hypot(fx - xd, fy - yd) < tol * 1e3) | ~(self.jacobian_det(x, y) > 0)
        return np.where(bad, np.nan, x), np.where(bad, np.nan, y)


# ----------------------------------------------------------------------------- the pinhole crop
@dataclass
class _Camera:
    """One distinct (intrinsics, lens) of a capture and the images that use it."""

    K: np.ndarray                  # [3, 3] at the source images' size
    lens: Optional[Lens]
    label: str
    images: list[int] = field(default_factory=list)
    rows: Optional[tuple[int, np.ndarray, np.ndarray]] = None  # (first row, L, R) of the valid runs
    crop: Optional[tuple[int, int]] = None                     # top-left pixel (x0, y0) in the undistorted frame
    grid: Optional[torch.Tensor] = None                        # [1, H, W, 2] grid_sample coordinates


def _source_map(cam: _Camera, u: np.ndarray, v: np.ndarray, fold: bool = True):
    """Source pixel coordinates of undistorted-frame pixel positions ``(u, v)``, and (``fold``) where the
    lens map has not folded over (positive Jacobian determinant)."""
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    if cam.lens is None or cam.lens.is_pinhole:
        return u, v, np.ones(np.broadcast(u, v).shape, dtype=bool) if fold else None
    x, y = (u - cx) / fx, (v - cy) / fy
    xd, yd = cam.lens.distort(x, y)
    return xd * fx + cx, yd * fy + cy, cam.lens.jacobian_det(x, y) > 0 if fold else None


def _inside(su: np.ndarray, sv: np.ndarray, W0: int, H0: int) -> np.ndarray:
    """Positions among the source's pixel centres, where bilinear sampling reads only real pixels."""
    return (su >= 0.5) & (su <= W0 - 0.5) & (sv >= 0.5) & (sv <= H0 - 0.5)


def _search_box(cam: _Camera, W0: int, H0: int) -> tuple[int, int, int, int]:
    """Pixel index range ``[i0, i1) x [j0, j1)`` of the undistorted frame that can hold valid pixels:
    the bounding box of the source border mapped back through the lens, at most ``_MAX_GROW`` x the
    source size beyond the principal point."""
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    lim = (cx - _MAX_GROW * W0, cx + _MAX_GROW * W0, cy - _MAX_GROW * H0, cy + _MAX_GROW * H0)
    if cam.lens is None or cam.lens.is_pinhole:
        box = (0.0, float(W0), 0.0, float(H0))
    else:
        n = max(64, 2 * max(W0, H0))
        t = np.linspace(0.0, 1.0, n)
        us = np.concatenate([0.5 + t * (W0 - 1), np.full(n, W0 - 0.5), 0.5 + t * (W0 - 1), np.full(n, 0.5)])
        vs = np.concatenate([np.full(n, 0.5), 0.5 + t * (H0 - 1), np.full(n, H0 - 0.5), 0.5 + t * (H0 - 1)])
        x, y = cam.lens.undistort((us - cx) / fx, (vs - cy) / fy)
        u, v = x * fx + cx, y * fy + cy
        if np.all(np.isfinite(u)):
            box = (u.min() - 2.0, u.max() + 2.0, v.min() - 2.0, v.max() + 2.0)
        else:  # part of the border is beyond what the lens can reach: search the whole allowed frame
            box = lim
    b = (max(box[0], lim[0]), min(box[1], lim[1]), max(box[2], lim[2]), min(box[3], lim[3]))
    return int(np.floor(b[0])), int(np.ceil(b[1])), int(np.floor(b[2])), int(np.ceil(b[3]))


def _valid_rows(cam: _Camera, W0: int, H0: int) -> tuple[int, np.ndarray, np.ndarray]:
    """Per row of the undistorted frame, the run ``[L, R)`` of valid pixels through the principal point's
    column; the rows kept are the contiguous block through the principal point's row."""
    i0, i1, j0, j1 = _search_box(cam, W0, H0)
    ci, cj = int(np.floor(cam.K[0, 2])), int(np.floor(cam.K[1, 2]))
    if not (i0 <= ci < i1 and j0 <= cj < j1):
        raise InputError(f"{cam.label}: the principal point ({cam.K[0, 2]:.1f}, {cam.K[1, 2]:.1f}) is outside "
                         f"the {W0}x{H0} image; check the intrinsics")
    cols = np.arange(i0, i1, dtype=np.float64) + 0.5
    c = ci - i0
    L = np.empty(j1 - j0, dtype=np.int64)
    R = np.empty(j1 - j0, dtype=np.int64)
    step = max(1, _CHUNK // len(cols))
    for a in range(j0, j1, step):
        rows = np.arange(a, min(a + step, j1), dtype=np.float64) + 0.5
        u, v = np.broadcast_arrays(cols[None, :], rows[:, None])
        su, sv, fold_free = _source_map(cam, u, v)
        ok = fold_free & _inside(su, sv, W0, H0)
        left = np.cumprod(ok[:, c::-1], axis=1).sum(axis=1)    # valid pixels from the centre column leftwards
        right = np.cumprod(ok[:, c:], axis=1).sum(axis=1)      # ... and rightwards (both count the centre)
        sl = slice(a - j0, a - j0 + len(rows))
        L[sl] = np.where(left > 0, ci - left + 1, ci)
        R[sl] = np.where(left > 0, ci + right, ci)             # empty run [ci, ci) when the centre is invalid
    has = R > L
    k = cj - j0
    if not has[k]:
        raise InputError(f"{cam.label}: the principal point does not map inside the {W0}x{H0} image through "
                         f"the lens ({cam.lens.describe() if cam.lens else 'pinhole'}); check the calibration")
    top = k
    while top > 0 and has[top - 1]:
        top -= 1
    bot = k
    while bot + 1 < len(has) and has[bot + 1]:
        bot += 1
    return j0 + top, L[top:bot + 1], R[top:bot + 1]


def _widest(L: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``best[h - 1]``: the widest rectangle of ``h`` consecutive rows inside the runs ``[L, R)``."""
    n = len(L)
    best = np.zeros(n, dtype=np.int64)
    for a in range(n):
        w = np.minimum.accumulate(R[a:]) - np.maximum.accumulate(L[a:])
        np.maximum(best[:n - a], w, out=best[:n - a])
    return best


def _place(cam: _Camera, W: int, H: int) -> tuple[int, int]:
    """Top-left pixel of a ``W x H`` window inside ``cam``'s valid region, as centred on the principal
    point as the region allows."""
    top, L, R = cam.rows
    cx, cy = cam.K[0, 2], cam.K[1, 2]
    best = None
    for a in range(len(L) - H + 1):
        lo, hi = int(L[a:a + H].max()), int(R[a:a + H].min()) - W
        if hi < lo:
            continue
        y0 = top + a
        x0 = int(min(max(round(cx - W / 2.0), lo), hi))
        cost = abs(y0 + H / 2.0 - cy) + abs(x0 + W / 2.0 - cx)
        if best is None or cost < best[0]:
            best = (cost, x0, y0)
    assert best is not None, "a window that fits every camera was chosen"
    return best[1], best[2]


@dataclass
class Undistortion:
    """The pinhole crop of a capture's images (see the module docstring).

    Attributes:
        source_size: ``(W0, H0)`` of the source images.
        size: ``(W, H)`` of the undistorted images (one size for all).
        Ks: ``[C, 3, 3]`` float64 pinhole intrinsics of the undistorted images.
    """

    source_size: tuple[int, int]
    size: tuple[int, int]
    Ks: np.ndarray
    cameras: list[_Camera]
    camera_of: list[int]

    def grid(self, i: int) -> Optional[torch.Tensor]:
        """``[1, H, W, 2]`` ``grid_sample`` coordinates (align_corners=False) of image ``i``'s output
        pixels in its source, or None when the image is a plain crop of its source (a pinhole camera)."""
        cam = self.cameras[self.camera_of[i]]
        if cam.lens is None or cam.lens.is_pinhole:
            return None
        if cam.grid is None:
            (W0, H0), (W, H) = self.source_size, self.size
            x0, y0 = cam.crop
            cols = np.arange(W, dtype=np.float64) + x0 + 0.5
            grid = torch.empty(1, H, W, 2)
            step = max(1, _CHUNK // W)
            for a in range(0, H, step):  # in blocks of rows: bounded memory on large images
                rows = np.arange(a, min(a + step, H), dtype=np.float64) + y0 + 0.5
                su, sv, _ = _source_map(cam, *np.broadcast_arrays(cols[None, :], rows[:, None]), fold=False)
                assert bool(_inside(su, sv, W0, H0).all()), "every output pixel of the crop has a source"
                grid[0, a:a + len(rows), :, 0] = torch.from_numpy(2.0 * su / W0 - 1.0)
                grid[0, a:a + len(rows), :, 1] = torch.from_numpy(2.0 * sv / H0 - 1.0)
            cam.grid = grid
        return cam.grid

    def __call__(self, i: int, image: torch.Tensor) -> torch.Tensor:
        """Image ``i`` (``[H0, W0, C]`` float) undistorted: ``[H, W, C]``."""
        (W0, H0), (W, H) = self.source_size, self.size
        if tuple(image.shape[:2]) != (H0, W0):
            raise InputError(f"image {i}: size {image.shape[1]}x{image.shape[0]}, expected {W0}x{H0}")
        g = self.grid(i)
        if g is None:
            x0, y0 = self.cameras[self.camera_of[i]].crop
            return image[y0:y0 + H, x0:x0 + W].contiguous()
        x = image.permute(2, 0, 1)[None].float()
        out = torch.nn.functional.grid_sample(x, g.to(x.device), mode="bilinear", padding_mode="border",
                                              align_corners=False)
        return out[0].permute(1, 2, 0).contiguous()

    def record(self) -> dict:
        """What was done, for ``data.json``: per distinct camera its lens, the crop box in the undistorted
        frame of the source intrinsics (pixels), the intrinsics before and after."""
        (W0, H0), (W, H) = self.source_size, self.size
        cams = []
        for cam in self.cameras:
            x0, y0 = cam.crop
            K = cam.K.copy()
            K[0, 2] -= x0
            K[1, 2] -= y0
            cams.append({
                "camera": cam.label, "images": len(cam.images), "image_ids": [int(i) for i in cam.images],
                **(cam.lens.to_json() if cam.lens is not None else {"model": "PINHOLE", "params": {}}),
                "K_source": cam.K.tolist(), "crop": [int(x0), int(y0), int(x0 + W), int(y0 + H)], "K": K.tolist(),
            })
        return {"method": "pinhole crop: every pixel has a source (alpha = 0), bilinear resampling",
                "source_size": [W0, H0], "size": [W, H], "area": round(W * H / (W0 * H0), 4), "cameras": cams}


def undistort_labels(record: dict, i: int, labels: np.ndarray, what: str = "mask") -> np.ndarray:
    """Integer label image ``labels [h, w]`` of source image ``i`` (in the frame of the distorted source,
    at its size or any size of the same aspect), brought into the run's undistorted pinhole crop by
    nearest-neighbour sampling with the lens map of ``record`` (an :meth:`Undistortion.record`, as
    ``data.json``'s ``undistortion``), then to its ``resized_to`` size when there is one.

    Used for masks drawn on the original images (Gaussian Grouping's ``object_mask/``, a tracker's
    output): every output pixel takes the label of the source pixel its colour came from, so masks and
    images stay registered and no mask pixel lies outside the source."""
    (W0, H0), (W, H) = record["source_size"], record["size"]
    cams = record["cameras"]
    cam = None
    for c in cams:
        if "image_ids" in c and i in c["image_ids"]:
            cam = c
    if cam is None:
        if len(cams) != 1:
            raise InputError(f"{what}: the run's undistortion record does not say which camera image {i} used "
                             f"(a run made by an older ssgwarp); run `ssgwarp reconstruct` again")
        cam = cams[0]
    h, w = labels.shape[:2]
    if abs((w / h) / (W0 / H0) - 1.0) > 0.02:
        raise InputError(f"{what}: {w}x{h} does not have the aspect of the capture's {W0}x{H0} images")
    names = MODELS[cam["model"]] if cam["model"] in MODELS else ()
    lens = None if cam["model"] == "PINHOLE" else Lens(cam["model"], tuple(cam["params"][k] for k in names))
    x0, y0 = cam["crop"][:2]
    u = np.arange(W, dtype=np.float64) + x0 + 0.5
    v = np.arange(H, dtype=np.float64) + y0 + 0.5
    su, sv, _ = _source_map(_Camera(np.asarray(cam["K_source"], dtype=np.float64), lens, cam["camera"]),
                            *np.broadcast_arrays(u[None, :], v[:, None]), fold=False)
    cols = np.clip(np.floor(su * (w / W0)).astype(np.int64), 0, w - 1)
    rows = np.clip(np.floor(sv * (h / H0)).astype(np.int64), 0, h - 1)
    out = labels[rows, cols]
    size = record.get("resized_to")
    if size is not None:
        out = resize_nearest(out, *size)
    return np.ascontiguousarray(out)


def plan_undistortion(Ks: np.ndarray, lenses: Sequence[Optional[Lens]], width: int, height: int,
                      labels: Sequence[str], min_area: float = MIN_AREA) -> Optional[Undistortion]:
    """The pinhole crop for images of ``width`` x ``height`` taken with intrinsics ``Ks [C, 3, 3]`` and
    ``lenses`` (None or a pinhole lens: no distortion); ``labels`` name each image's camera in errors.
    Returns None when no image is distorted (the images stay as they are)."""
    Ks = np.asarray(Ks, dtype=np.float64)
    if all(ln is None or ln.is_pinhole for ln in lenses):
        return None
    index: dict[tuple, int] = {}
    cameras: list[_Camera] = []
    camera_of = []
    for i, (K, ln, lab) in enumerate(zip(Ks, lenses, labels)):
        ln = None if ln is None or ln.is_pinhole else ln
        key = (tuple(np.round(K, 9).ravel().tolist()), ln)
        if key not in index:
            index[key] = len(cameras)
            cameras.append(_Camera(K.copy(), ln, lab))
        cameras[index[key]].images.append(i)
        camera_of.append(index[key])
    need = min_area * width * height
    widths = []
    for cam in cameras:
        cam.rows = _valid_rows(cam, width, height)
        best = _widest(cam.rows[1], cam.rows[2])
        h = np.arange(1, len(best) + 1)
        area = int((h * best).max())
        if area < need:
            raise InputError(
                f"{cam.label} ({cam.lens.describe()}): lens distortion too strong for a pinhole crop: the largest "
                f"undistorted rectangle in which every pixel has a source covers {area / (width * height):.0%} of "
                f"the {width}x{height} image (at least {min_area:.0%} needed); check the calibration's distortion "
                f"coefficients, or undistort and crop the images with another tool (e.g. colmap "
                f"image_undistorter) and load its output as a pinhole capture")
        widths.append(best)
    n = min(len(b) for b in widths)
    common = np.min(np.stack([b[:n] for b in widths]), axis=0)
    h = np.arange(1, n + 1)
    H = int(np.argmax(h * common)) + 1
    W = int(common[H - 1])
    if W * H < need:
        worst = cameras[int(np.argmin([len(b) for b in widths]))]
        raise InputError(f"the cameras' undistorted regions share only {W * H / (width * height):.0%} of the "
                         f"{width}x{height} image (at least {min_area:.0%} needed; {worst.label} and others "
                         f"differ too much); load the cameras as separate captures")
    out = np.empty((len(Ks), 3, 3))
    for cam in cameras:
        cam.crop = _place(cam, W, H)
        K = cam.K.copy()
        K[0, 2] -= cam.crop[0]
        K[1, 2] -= cam.crop[1]
        out[cam.images] = K
    return Undistortion((int(width), int(height)), (W, H), out, cameras, camera_of)
