"""Cameras for splats without a capture: an orbit fitted to the splats (``ssgwarp render FILE``,
``ssgwarp stylize FILE``, ``ssgwarp import FILE`` without ``--data``; docs/your_splats.md).

* :func:`fit_splats` -- where the splats are (:class:`SplatFit`): the inliers (splats at least
  ``min_opacity`` opaque, within ``min(q95, 3 x median)`` of the weighted median of their centres: far
  floaters and backdrops are left out), their opacity-weighted principal axes, which way is up, the centre and
  extent (the 1st-99th weighted percentiles along those axes) and the typical splat size;
* :func:`orbit_cameras` -- ``n`` cameras on a loop around the up axis looking at the centre, their elevation
  swinging ``sweep`` degrees around ``elevation`` (twice per turn), at one distance: the smallest at which
  99.5 % of the inliers fall inside ``fill`` of the frame in every view; the aspect follows the splats'
  extent seen from the side (3:4 to 16:9), the width is at most ``max_width`` and at most the width at which
  the median splat is one pixel across (finer would show the gaps between splats);
* :func:`orbit_run` -- those cameras as a capture without images, and the fit's record: what
  :func:`ssgwarp.services.runs.write_orbit_run` writes as a reconstruction-run folder (``scene.ply``,
  ``cameras.json``, ``data.json`` with the record under ``orbit``) that every later stage takes as it takes a
  reconstruction.

Up: the normal of the ground (or table) when the splats have one: of 256 planes through random triples of
kept centres, the one holding the largest opacity-weighted share of them within :data:`PLANE_TOL` x their largest
principal deviation, when that share is at least :data:`PLANE_SHARE` (else, when the smallest principal variance is
below :data:`FLAT_RATIO` x the middle one, that thinnest axis). Its side: when the normal is within 60 degrees of the
file's y axis, the file's ``-y`` side (the OpenCV / COLMAP convention of 3DGS files: y down); otherwise the side the
splats stand out to (the third moment along it: things stand on the ground). Without a ground or layer, up is the
file's ``-y``. An up within :data:`SNAP_DEG` degrees of one of the file's axes is taken to be that axis. ``up``
overrides it all (an axis like ``+z`` or ``x,y,z``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..core.cameras import Cameras, intrinsics, look_at
from ..errors import InputError
from ..raster.scene import GaussianScene

__all__ = ["SplatFit", "fit_splats", "orbit_cameras", "parse_up", "orbit_run", "FLAT_RATIO"]

PLANE_TOL = 0.02        # a splat lies on a plane within this x the splats' largest principal deviation
PLANE_SHARE = 0.12      # a plane holding this opacity-weighted share of the splats is the ground (or a table)
PLANE_TRIES = 256       # random triples of splats tried as planes
FLAT_RATIO = 0.3        # else: smallest / middle principal variance below which the splats form a layer
FILE_UP_COS = 0.5       # a layer whose normal is this close to the file's y axis: up is on its -y side; else up
                        # is the side the splats stand out to (things stand on the ground)
MIN_OPACITY = 0.05      # splats less opaque than this are left out of the fit
KEEP_QUANTILE = 0.95    # inliers: distance to the median centre at most this weighted quantile ...
KEEP_MEDIANS = 3.0      # ... and at most this many times the weighted median distance
BOX_QUANTILES = (0.01, 0.99)
SNAP_DEG = 5.0          # an up found within this many degrees of one of the file's axes becomes that axis
FILE_UP = np.array([0.0, -1.0, 0.0])   # up in the OpenCV / COLMAP convention of 3DGS files
_AXES = {"x": 0, "y": 1, "z": 2}
VIEWS = 24              # cameras made around a splat file by default (stylize FILE, import FILE)
MAX_WIDTH = 512         # their width at most by default (and at most the splats' own resolution)


def parse_up(text: Optional[str]) -> Optional[np.ndarray]:
    """``--up``: ``auto``/None, an axis (``+z``, ``-y``, ``x``) or a vector ``x,y,z``; a unit vector or None."""
    if text is None or str(text).strip().lower() in ("", "auto"):
        return None
    t = str(text).strip().lower()
    if len(t) in (1, 2) and t[-1] in _AXES and (len(t) == 1 or t[0] in "+-"):
        v = np.zeros(3)
        v[_AXES[t[-1]]] = -1.0 if t[0] == "-" else 1.0
        return v
    try:
        v = np.array([float(s) for s in t.split(",")], dtype=np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-12:
        raise InputError(f"--up {text}: expected auto, an axis (+z, -y, x ...) or a vector x,y,z")
    return v / np.linalg.norm(v)


def _wquantile(x: np.ndarray, w: np.ndarray, q) -> np.ndarray:
    """Weighted quantiles ``q`` of ``x`` (1-D)."""
    o = np.argsort(x, kind="stable")
    cw = np.cumsum(w[o])
    cw = (cw - 0.5 * w[o]) / cw[-1]
    return np.interp(q, cw, x[o])


@dataclass
class SplatFit:
    """Where the splats are (see the module docs): ``centre [3]``, ``axes [3, 3]`` (rows: the horizontal
    principal axis, the other horizontal axis, up), ``half_extent [3]`` along them, ``up_rule`` (how up was
    chosen), the inliers ``points [M, 3]`` with their opacities ``weights [M]``, ``splat_size`` (the median
    inlier's geometric-mean size of its two larger axes), ``total``/``kept`` counts and ``variances`` (the
    principal variances, ascending)."""

    centre: np.ndarray
    axes: np.ndarray
    half_extent: np.ndarray
    up_rule: str
    points: np.ndarray
    weights: np.ndarray
    splat_size: float
    total: int
    kept: int
    variances: np.ndarray

    @property
    def up(self) -> np.ndarray:
        return self.axes[2]

    def record(self) -> dict:
        r = lambda a: [round(float(v), 6) for v in np.asarray(a).ravel()]  # noqa: E731
        return {"centre": r(self.centre), "up": r(self.up), "up_rule": self.up_rule,
                "horizontal_axes": [r(self.axes[0]), r(self.axes[1])], "half_extent": r(self.half_extent),
                "principal_variances": r(self.variances), "splats": self.total, "inliers": self.kept,
                "splat_size": round(float(self.splat_size), 6),
                "inlier_rule": f"opacity >= {MIN_OPACITY}, distance to the weighted median centre <= "
                               f"min(weighted q{KEEP_QUANTILE:g}, {KEEP_MEDIANS:g} x weighted median)",
                "box": f"weighted percentiles {BOX_QUANTILES[0]:g}-{BOX_QUANTILES[1]:g} along the axes"}


def _dominant_plane(x: np.ndarray, w: np.ndarray, scale: float, seed: int) -> Optional[tuple[np.ndarray, float]]:
    """The ground (or table) plane of the splat centres ``x``: of :data:`PLANE_TRIES` planes through random triples,
    the one holding the largest opacity-weighted share of the centres within :data:`PLANE_TOL` x ``scale``, when
    that share is at least :data:`PLANE_SHARE`, refined by a weighted principal-axis fit of its points:
    ``(unit normal, share)``, or None."""
    if len(x) < 20 or scale <= 0:
        return None
    rng = np.random.default_rng(seed)
    if len(x) > 20_000:
        pick = rng.choice(len(x), 20_000, replace=False)
        x, w = x[pick], w[pick]
    tol, total = PLANE_TOL * scale, float(w.sum())
    tri = x[rng.choice(len(x), (PLANE_TRIES, 3), p=w / total)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ok = np.linalg.norm(n, axis=1) > 1e-12 * scale ** 2
    if not ok.any():
        return None
    n, a = n[ok] / np.linalg.norm(n[ok], axis=1, keepdims=True), tri[ok, 0]
    shares = ((np.abs((x[None] - a[:, None]) @ n[..., None])[..., 0] < tol) * w).sum(axis=1) / total
    best = int(np.argmax(shares))
    if shares[best] < PLANE_SHARE:
        return None
    on = np.abs((x - a[best]) @ n[best]) < tol
    c = np.average(x[on], axis=0, weights=w[on])
    normal = np.linalg.eigh(np.cov((x[on] - c).T, aweights=w[on], bias=True))[1][:, 0]
    return normal, float(w[np.abs((x - c) @ normal) < tol].sum() / total)


def _choose_up(x: np.ndarray, w: np.ndarray, vecs: np.ndarray, lam: np.ndarray,
               up: Optional[np.ndarray], seed: int) -> tuple[np.ndarray, str]:
    if up is not None:
        return up, "given (--up)"
    plane = _dominant_plane(x, w, math.sqrt(float(lam[-1])), seed)
    if plane is not None:
        v, what = plane[0], f"the normal of the plane holding {plane[1]:.0%} of the splats (a ground or table)"
    elif lam[1] > 0 and lam[0] / lam[1] < FLAT_RATIO:
        v, what = vecs[:, 0], f"the splats' thinnest axis (a layer: variance ratio {lam[0] / lam[1]:.2f})"
    else:
        return FILE_UP.copy(), "the file's -y (OpenCV / COLMAP convention; the splats form no layer)"
    h = (x - np.average(x, axis=0, weights=w)) @ v
    sd = math.sqrt(max(float(np.average(h ** 2, weights=w)), 1e-300))
    skew = float(np.average((h / sd) ** 3, weights=w))
    towards = float(v @ FILE_UP)
    if abs(towards) < FILE_UP_COS and skew != 0:
        return (v if skew > 0 else -v), (f"{what}, towards the side the splats stand out to (skewness {abs(skew):.2f}; "
                                         f"the layer does not face the file's y axis)")
    return (v if towards >= 0 else -v), f"{what}, on the file's -y side (OpenCV / COLMAP convention)"


def fit_splats(scene: GaussianScene, *, up: Optional[np.ndarray] = None, max_points: int = 200_000,
               seed: int = 0) -> SplatFit:
    """Fit centre, axes and extent to the splats of ``scene`` (module docs); ``up`` overrides the up rule."""
    x = scene.means.detach().double().cpu().numpy()
    w = torch.sigmoid(scene.logit_opacities.detach().double().cpu()).numpy()
    size = torch.exp(scene.log_scales.detach().double().cpu()).sort(dim=1).values[:, 1:].prod(dim=1).sqrt().numpy()
    ok = np.isfinite(x).all(axis=1) & np.isfinite(w) & np.isfinite(size)
    if ok.sum() < 1:
        raise InputError("the splats have no finite positions")
    opaque = ok & (w >= MIN_OPACITY)
    sel = np.flatnonzero(opaque if opaque.sum() >= max(4, 0.01 * ok.sum()) else ok)
    if len(sel) > max_points:
        sel = np.sort(np.random.default_rng(seed).choice(sel, max_points, replace=False))
    x, w, size = x[sel], np.maximum(w[sel], 1e-6), size[sel]
    med = np.array([_wquantile(x[:, i], w, 0.5) for i in range(3)])
    r = np.linalg.norm(x - med, axis=1)
    cut = min(float(_wquantile(r, w, KEEP_QUANTILE)), KEEP_MEDIANS * float(_wquantile(r, w, 0.5)))
    keep = r <= max(cut, 1e-12)
    if keep.sum() < min(4, len(x)):
        keep = np.ones(len(x), dtype=bool)
    x, w, size = x[keep], w[keep], size[keep]
    mean = np.average(x, axis=0, weights=w)
    cov = np.cov((x - mean).T, aweights=w, bias=True) if len(x) > 1 else np.zeros((3, 3))
    lam, vecs = np.linalg.eigh(np.atleast_2d(cov))
    lam = np.maximum(lam, 0.0)
    up_v, rule = _choose_up(x, w, vecs, lam, up, seed)
    axis = int(np.argmax(np.abs(up_v)))
    if up is None and abs(up_v[axis]) > math.cos(math.radians(SNAP_DEG)) and abs(up_v[axis]) < 1:
        snapped = np.zeros(3)
        snapped[axis] = np.sign(up_v[axis])
        off = math.degrees(math.acos(min(1.0, abs(up_v[axis]))))
        rule += f"; snapped to the file's {'+-'[int(up_v[axis] < 0)]}{'xyz'[axis]} axis ({off:.1f} deg away)"
        up_v = snapped
    # the horizontal axes: the larger remaining principal axis, made perpendicular to up
    rest = [vecs[:, i] for i in (2, 1, 0)]
    e1 = next((v - (v @ up_v) * up_v for v in rest if np.linalg.norm(v - (v @ up_v) * up_v) > 0.3), None)
    if e1 is None:
        e1 = np.cross(up_v, [1.0, 0.0, 0.0] if abs(up_v[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(up_v, e1)
    axes = np.stack([e1, e2, up_v])
    proj = x @ axes.T
    lo = np.array([_wquantile(proj[:, i], w, BOX_QUANTILES[0]) for i in range(3)])
    hi = np.array([_wquantile(proj[:, i], w, BOX_QUANTILES[1]) for i in range(3)])
    centre = axes.T @ ((lo + hi) / 2)
    half = np.maximum((hi - lo) / 2, 1e-9)
    return SplatFit(centre, axes, half, rule, x, w, float(np.median(size)) if len(size) else 0.0,
                    len(scene), int(keep.sum()), lam)


def _directions(fit: SplatFit, n: int, elevation: float, sweep: float) -> np.ndarray:
    """``[n, 3]`` unit vectors from the centre to the cameras: azimuths evenly around up (the first camera
    on the second horizontal axis, looking across the first), elevation ``elevation + sweep sin(2 azimuth)``
    (degrees)."""
    a = np.arange(n) / n * 2 * math.pi
    el = np.radians(elevation + sweep * np.sin(2 * a))
    e1, e2, up = fit.axes
    h = np.cos(a)[:, None] * e2 + np.sin(a)[:, None] * e1
    return np.cos(el)[:, None] * h + np.sin(el)[:, None] * up


def _distance(fit: SplatFit, dirs: np.ndarray, tx: float, ty: float) -> float:
    """The smallest distance from the centre at which 99.5 % of the inliers fall inside the frame's
    ``tx``, ``ty`` (half-size over focal) in every direction of ``dirs``."""
    q = fit.points - fit.centre
    rng = np.random.default_rng(0)
    if len(q) > 20_000:
        pick = rng.choice(len(q), 20_000, replace=False)
        q, w = q[pick], fit.weights[pick]
    else:
        w = fit.weights
    radius = float(np.linalg.norm(fit.half_extent))
    best = 0.0
    for d in dirs:
        f = -d
        right = np.cross(f, fit.up)
        right /= max(np.linalg.norm(right), 1e-12)
        down = np.cross(f, right)
        x, y, z = q @ right, q @ down, q @ f
        need = np.maximum(np.abs(x) / tx - z, np.abs(y) / ty - z)
        best = max(best, float(_wquantile(need, w, 0.995)), float(np.max(-z)) + 0.05 * radius)
    return max(best, 1e-6)


def orbit_cameras(fit: SplatFit, n: int, *, max_width: int = 512, width: Optional[int] = None,
                  elevation: float = 20.0, sweep: float = 10.0, fov_x: float = 60.0, fill: float = 0.9,
                  names: Optional[Sequence[str]] = None, prefix: str = "orbit_") -> tuple[Cameras, dict]:
    """``(cameras, record)``: ``n`` cameras around the splats of ``fit`` (module docs). ``width``: exactly this
    width (else at most ``max_width``); ``fov_x``: horizontal field of view (degrees); ``fill``: the part of the
    frame (each direction) the splats may take."""
    if n < 1:
        raise InputError(f"orbit: the number of views must be >= 1, got {n}")
    if not 0 < fov_x < 170 or not 0 < fill <= 1:
        raise InputError(f"orbit: bad field of view {fov_x} or fill {fill}")
    if not (-89 <= elevation - abs(sweep) and elevation + abs(sweep) <= 89):
        raise InputError(f"orbit: elevation {elevation} +- {sweep} degrees must stay within +-89")
    ex = fit.half_extent
    side_h = float(max(ex[0], ex[1]))
    el = math.radians(elevation)
    side_v = float(ex[2] * math.cos(el) + min(ex[0], ex[1]) * abs(math.sin(el)))
    aspect = float(np.clip(side_h / max(side_v, 1e-12), 0.75, 16 / 9))
    t = math.tan(math.radians(fov_x) / 2)
    tx, ty = fill * t, fill * t / aspect
    dirs = _directions(fit, n, elevation, sweep)
    dist = _distance(fit, dirs, tx, ty)
    native = 2 * dist * t / fit.splat_size if fit.splat_size > 0 else float("inf")
    if width is None:
        w = int(max(32, min(max_width, native)))
        rule = (f"min(--width {max_width}, {native:.0f}: the width at which the median splat is one pixel "
                f"across), at least 32")
    else:
        w, rule = int(width), "given"
    if w < 8:
        raise InputError(f"--width {w}: must be >= 8")
    w -= w % 2
    h = max(2, int(round(w / aspect / 2)) * 2)
    f = 0.5 * w / t
    eyes = torch.from_numpy(fit.centre[None] + dist * dirs)
    centre = torch.from_numpy(fit.centre)[None].expand(n, 3)
    vm = look_at(eyes, centre, up=tuple(float(v) for v in fit.up))
    K = intrinsics(f, f * 1.0, w / 2.0, h / 2.0, n)
    names = list(names) if names else [f"{prefix}{i:03d}" for i in range(n)]
    cams = Cameras(vm.float(), K, w, h, names)
    record = {"views": n, "distance": round(dist, 6), "elevation_deg": elevation, "sweep_deg": sweep,
              "fov_x_deg": fov_x, "fill": fill, "aspect": round(aspect, 4), "width": w, "height": h,
              "width_rule": rule, "native_width": None if not math.isfinite(native) else round(native, 1),
              "distance_rule": f"smallest at which 99.5 % of the inliers fall inside {fill:g} of the frame in "
                               f"every view"}
    return cams, record


def orbit_run(scene: GaussianScene, *, source: str | Path, views: int = 24, max_width: int = 512,
              width: Optional[int] = None, up: Optional[np.ndarray] = None,
              background: Sequence[float] = (1.0, 1.0, 1.0), seed: int = 0):
    """``(SceneData, record)``: ``views`` cameras made around ``scene`` as a capture without images (all of
    them training views: there are no images to hold out) and the ``orbit`` record of how they were made
    (:func:`ssgwarp.services.runs.write_orbit_run` writes them as a run folder)."""
    from .datasets import SceneData

    fit = fit_splats(scene, up=up, seed=seed)
    cams, rec = orbit_cameras(fit, views, max_width=max_width, width=width)
    record = {"source": str(Path(source).expanduser().resolve()), "fit": fit.record(), "cameras": rec}
    bg = tuple(float(v) for v in background)
    data = SceneData(cameras=cams, images=torch.zeros(len(cams), 1, 1, 3).expand(len(cams), cams.height,
                                                                                cams.width, 3),
                     names=list(cams.names), train_ids=list(range(len(cams))), test_ids=[], background=bg,
                     data_dir=None, format="orbit", options=dict(split_every=0, background=list(bg)))
    return data, record
