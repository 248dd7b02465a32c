"""Points from the poses a capture already has: features, matching and triangulation for known cameras.

What COLMAP's ``point_triangulator`` does for a model with known poses, in torch on the CPU:

1. **Features**: kornia's SIFT (difference-of-Gaussians keypoints, RootSIFT descriptors; no learned
   weights, nothing downloaded), upright, on grey images at most ``max_size`` pixels on their long side.
2. **Pairs** of views chosen by overlap: rays through a grid of each view's pixels, at depths spread
   over the scene's depth range, are projected into every other view; each view is matched with the
   ``neighbours`` views that see most of them.
3. **Matching**: mutual nearest neighbours of the descriptors that pass Lowe's ratio test, kept when
   the known relative pose agrees: Sampson distance to the epipolar line (``F = K_j^-T [t]x R K_i^-1``)
   at most ``max_epipolar_px`` (with no baseline, the transfer error of the rotation's homography).
4. **Tracks**: the matches joined across views (union-find); a track is one 3D point.
5. **Triangulation**: linear (DLT in normalised coordinates), the worst observation dropped while it
   reprojects more than ``max_reproj_px`` away (one observation per view), then Gauss-Newton steps on the
   reprojection error. Kept: points seen by at least two views, in front of every camera that sees them,
   reprojecting within ``max_reproj_px`` in each, with a triangulation angle of at least ``min_angle_deg``.
   Colours: the mean of the track's pixels.

Deterministic (no random sampling; CPU tensors). Images and cameras are the undistorted pinhole
frames of :class:`~ssgwarp.capture.datasets.SceneData`.

Public API:
    triangulate(cameras, images, ...) -> Triangulation(xyz [P, 3], rgb [P, 3], stats)
    select_pairs(cameras, neighbours, depth_range) -> the view pairs matched
    scene_depth_range(cameras) -> (near, far) guessed from the camera layout
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import torch
from ..core.progress import tqdm

from ..core.cameras import Cameras
from ..errors import InputError
from .loaders import focus_point, resize_images

log = logging.getLogger("ssgwarp.capture.triangulate")

MIN_SIZE = 48  # smaller images have no features


@dataclass
class Triangulation:
    """Triangulated points.

    Attributes:
        xyz: ``[P, 3]`` float32 world positions.
        rgb: ``[P, 3]`` float32 colours in [0, 1] (mean over each point's observations).
        stats: ``count`` (P), ``median_reprojection_error_px`` (in pixels of the given images; None when
            P = 0), ``tracks`` (candidate tracks), ``pairs`` (view pairs matched), ``matches`` (matches that
            passed the epipolar test), ``features`` (keypoints per view, mean), ``mean_track_length`` (views
            per kept point), ``observations_per_view`` (kept observations in each view), ``scale`` (the image
            scale the features were found at), ``seconds``.
    """

    xyz: torch.Tensor
    rgb: torch.Tensor
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


# ----------------------------------------------------------------------------- geometry helpers
def _skew(t: torch.Tensor) -> torch.Tensor:
    z = torch.zeros((), dtype=t.dtype)
    return torch.stack([torch.stack([z, -t[2], t[1]]), torch.stack([t[2], z, -t[0]]),
                        torch.stack([-t[1], t[0], z])])


def _overlap(cameras: Cameras, depths: torch.Tensor, grid: int = 8) -> torch.Tensor:
    """``[C, C]`` fraction of view i's sampled rays (``grid`` x ``grid`` pixels x ``depths``) seen by view j."""
    C, W, H = len(cameras), cameras.width, cameras.height
    Ks = cameras.Ks.double().cpu()
    vm = cameras.viewmats.double().cpu()
    c2w = torch.linalg.inv(vm)
    u = (torch.arange(grid, dtype=torch.float64) + 0.5) / grid
    uu, vv = torch.meshgrid(u * W, u * H, indexing="xy")
    pix = torch.stack([uu.reshape(-1), vv.reshape(-1), torch.ones(grid * grid, dtype=torch.float64)], 1)
    rays = pix @ torch.linalg.inv(Ks).transpose(1, 2)                       # [C, G, 3] camera, z = 1
    pts = rays[:, :, None, :] * depths.reshape(1, 1, -1, 1)                 # [C, G, D, 3]
    pts = pts.reshape(C, -1, 3)
    world = pts @ c2w[:, :3, :3].transpose(1, 2) + c2w[:, None, :3, 3]       # [C, S, 3]
    P = Ks @ vm[:, :3, :]                                                    # [C, 3, 4]
    x = torch.einsum("jab,isb->ijsa", P[:, :, :3], world) + P[None, :, None, :, 3]  # [i, j, S, 3]
    z = x[..., 2]
    uv = x[..., :2] / z.clamp_min(1e-9)[..., None]
    seen = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= W) & (uv[..., 1] >= 0) & (uv[..., 1] <= H)
    ov = seen.double().mean(-1)
    ov.fill_diagonal_(0.0)
    return torch.minimum(ov, ov.T)


def scene_depth_range(cameras: Cameras) -> tuple[float, float]:
    """A guess of the depths the cameras see, from their layout alone: 0.2x to 5x the larger of the median
    distance to the point the cameras look at and the spread of the camera centres."""
    c = cameras.centers.double().cpu()
    r = float((c - focus_point(cameras)).norm(dim=1).median())
    spread = float((c - c.mean(0)).norm(dim=1).max())
    r = max(r, spread, 1e-6)
    return 0.2 * r, 5.0 * r


def _pair_depths(cameras: Cameras, depth_range: Optional[tuple[float, float]]) -> torch.Tensor:
    if depth_range is not None and depth_range[0] and depth_range[1] and 0 < depth_range[0] < depth_range[1]:
        lo, hi = float(depth_range[0]), float(depth_range[1])
    else:
        lo, hi = scene_depth_range(cameras)
    return torch.exp(torch.linspace(math.log(lo), math.log(hi), 6, dtype=torch.float64))


def select_pairs(cameras: Cameras, neighbours: int, depth_range=None, min_overlap: float = 0.1) -> list[tuple[int, int]]:
    """View pairs ``(i, j)``, ``i < j``: each view with the ``neighbours`` views that overlap it most."""
    ov = _overlap(cameras, _pair_depths(cameras, depth_range))
    pairs = set()
    for i in range(len(cameras)):
        order = sorted(range(len(cameras)), key=lambda j: (-float(ov[i, j]), j))
        for j in order[:neighbours]:
            if j != i and ov[i, j] >= min_overlap:
                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


# ----------------------------------------------------------------------------- features and matching
def _sift(max_features: int):
    import kornia.feature as KF

    return KF.SIFTFeature(num_features=max_features, upright=True, rootsift=True, descriptor_backend="pyramid")


def _features(sift, gray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Keypoints ``[N, 2]`` (pixel coordinates, pixel centres at +0.5) and descriptors ``[N, 128]`` of ``[H, W]``
    (none in images under ``MIN_SIZE`` pixels: the scale pyramid needs room)."""
    if min(gray.shape) < MIN_SIZE:
        return torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, 128)
    with torch.no_grad():
        lafs, resp, desc = sift(gray[None, None])
    kp = lafs[0, :, :, 2].double() + 0.5
    ok = torch.isfinite(desc[0]).all(1) & (resp[0] > 0) & torch.isfinite(kp).all(1)
    return kp[ok], torch.nn.functional.normalize(desc[0][ok].float(), dim=1)


def _match(da: torch.Tensor, db: torch.Tensor, ratio: float) -> torch.Tensor:
    """``[M, 2]`` mutual nearest neighbours passing the ratio test."""
    if len(da) < 2 or len(db) < 2:
        return torch.zeros(0, 2, dtype=torch.long)
    # unit descriptors: distance^2 = 2 - 2 similarity
    sim = da @ db.T
    best2, idx2 = sim.topk(2, dim=1)
    back = sim.T.contiguous().argmax(dim=1)
    dist = (2.0 - 2.0 * best2).clamp_min(0.0).sqrt()
    a = torch.arange(len(da))
    ok = (dist[:, 0] < ratio * dist[:, 1]) & (back[idx2[:, 0]] == a)
    return torch.stack([a[ok], idx2[ok, 0]], 1)


def _epipolar_error(Ka, Kb, Ra, ta, Rb, tb, xa: torch.Tensor, xb: torch.Tensor) -> torch.Tensor:
    """Per match the pixel distance from the epipolar constraint of the known relative pose (Sampson)."""
    R = Rb @ Ra.T
    t = tb - R @ ta
    ha = torch.cat([xa, torch.ones_like(xa[:, :1])], 1)
    hb = torch.cat([xb, torch.ones_like(xb[:, :1])], 1)
    scale = float(torch.linalg.norm(ta - Ra @ (Rb.T @ tb)))  # baseline (distance between the centres)
    if scale < 1e-9 * max(1.0, float(ta.norm()) + float(tb.norm())):
        # no baseline: the views are related by the homography Kb R Ka^-1
        Hm = Kb @ R @ torch.linalg.inv(Ka)
        p = ha @ Hm.T
        return (p[:, :2] / p[:, 2:3] - xb).norm(dim=1)
    F = torch.linalg.inv(Kb).T @ _skew(t / t.norm()) @ R @ torch.linalg.inv(Ka)
    Fa = ha @ F.T          # epipolar lines in b
    Fb = hb @ F            # epipolar lines in a
    num = (hb * Fa).sum(1) ** 2
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2
    return (num / den.clamp_min(1e-30)).sqrt()


def _tracks(edges: np.ndarray, n_nodes: int) -> np.ndarray:
    """Connected-component label per node (the smallest node id of its component) from ``edges [E, 2]``."""
    lab = np.arange(n_nodes)
    if len(edges) == 0:
        return lab
    a, b = edges[:, 0], edges[:, 1]
    while True:
        m = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        while not np.array_equal(new, new[new]):
            new = new[new]
        if np.array_equal(new, lab):
            return lab
        lab = new


# ----------------------------------------------------------------------------- triangulation
def _dlt(Pn: torch.Tensor, xn: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear triangulation of ``T`` tracks: ``Pn [T, L, 3, 4]`` normalised projections, ``xn [T, L, 2]``
    normalised image points, ``mask [T, L]``. Returns ``X [T, 3]`` and a validity flag ``[T]``."""
    r1 = xn[..., 0:1] * Pn[..., 2, :] - Pn[..., 0, :]
    r2 = xn[..., 1:2] * Pn[..., 2, :] - Pn[..., 1, :]
    A = torch.cat([r1, r2], 1) * torch.cat([mask, mask], 1)[..., None].double()   # [T, 2L, 4]
    A = A / A.norm(dim=2, keepdim=True).clamp_min(1e-30)
    _, vecs = torch.linalg.eigh(A.transpose(1, 2) @ A)
    v = vecs[..., 0]
    w = v[:, 3]
    ok = w.abs() > 1e-12
    X = v[:, :3] / torch.where(ok, w, torch.ones_like(w))[:, None]
    return X, ok & torch.isfinite(X).all(1)


def _reproject(P: torch.Tensor, X: torch.Tensor, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel reprojection errors ``[T, L]`` and depths ``[T, L]`` of ``X [T, 3]`` in ``P [T, L, 3, 4]``."""
    x = (P[..., :3] @ X[:, None, :, None])[..., 0] + P[..., 3]
    z = x[..., 2]
    proj = x[..., :2] / torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))[..., None]
    return (proj - uv).norm(dim=-1), z


def _gauss_newton(P: torch.Tensor, X: torch.Tensor, uv: torch.Tensor, mask: torch.Tensor, iters: int) -> torch.Tensor:
    """A few Gauss-Newton steps on the squared pixel reprojection error of each track (masked observations)."""
    m = mask.double()[..., None]
    for _ in range(iters):
        x = (P[..., :3] @ X[:, None, :, None])[..., 0] + P[..., 3]         # [T, L, 3]
        z = torch.where(x[..., 2].abs() > 1e-12, x[..., 2], torch.full_like(x[..., 2], 1e-12))
        r = (x[..., :2] / z[..., None] - uv) * m                            # [T, L, 2]
        # d(x/z)/dX = (P[:2,:3] - (x/z) P[2,:3]) / z
        J = (P[..., :2, :3] - (x[..., :2] / z[..., None])[..., None] * P[..., 2:3, :3]) / z[..., None, None]
        J = J * m[..., None]
        JtJ = torch.einsum("tlai,tlaj->tij", J, J) + 1e-9 * torch.eye(3, dtype=X.dtype)
        Jtr = torch.einsum("tlai,tla->ti", J, r)
        step, info = torch.linalg.solve_ex(JtJ, Jtr[..., None])
        step = step[..., 0]
        X = X - torch.where(torch.isfinite(step) & (info == 0)[:, None], step, torch.zeros_like(step))
    return X


def _sample(images: torch.Tensor, cam: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear colours ``[N, 3]`` of ``images [C, H, W, 3]`` at pixels ``uv [N, 2]`` (centres at +0.5) of views ``cam``."""
    C, H, W, _ = images.shape
    x = (uv[:, 0] - 0.5).clamp(0, W - 1)
    y = (uv[:, 1] - 0.5).clamp(0, H - 1)
    x0, y0 = x.floor().long().clamp(max=W - 2 if W > 1 else 0), y.floor().long().clamp(max=H - 2 if H > 1 else 0)
    fx, fy = (x - x0).float()[:, None], (y - y0).float()[:, None]
    x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
    c00, c01 = images[cam, y0, x0], images[cam, y0, x1]
    c10, c11 = images[cam, y1, x0], images[cam, y1, x1]
    return (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy


def _match_views(imgs, Ks, R, tvec, pairs, max_features: int, ratio: float, max_epipolar_px: float, bar):
    """Features of every view and the matches of ``pairs`` that pass the epipolar test: ``(keypoints per view,
    edges [E, 2] between global keypoint ids (views' keypoints numbered one after the other), match count)``."""
    gray = (imgs * torch.tensor([0.299, 0.587, 0.114])).sum(-1)
    kps, descs = [], []
    sift = _sift(max_features)
    for i in range(len(imgs)):
        kp, d = _features(sift, gray[i])
        kps.append(kp)
        descs.append(d)
        bar.update(1)
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])])
    bar.set_description("triangulating: matching")
    edges, n_matches = [], 0
    for i, j in pairs:
        m = _match(descs[i], descs[j], ratio)
        if len(m):
            err = _epipolar_error(Ks[i], Ks[j], R[i], tvec[i], R[j], tvec[j], kps[i][m[:, 0]], kps[j][m[:, 1]])
            m = m[err <= max_epipolar_px]
        n_matches += len(m)
        if len(m):
            edges.append(np.stack([m[:, 0].numpy() + offsets[i], m[:, 1].numpy() + offsets[j]], 1))
        bar.update(1)
    return kps, (np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)), n_matches


def _track_chunks(kps: list, edges: np.ndarray, C: int, budget: int = 2_000_000):
    """Tracks from the matches (tracks longer than ``2 C`` are chains of wrong matches and left out), sorted by
    length, in chunks padded to their longest track with at most ``budget`` observation pairs each:
    yields ``(view [T, L], pixel [T, L, 2], mask [T, L])``."""
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])])
    n_nodes = int(offsets[-1])
    lab = _tracks(edges, n_nodes)
    used = np.zeros(n_nodes, bool)
    used[edges.reshape(-1)] = True
    nodes = np.nonzero(used)[0]
    roots = lab[nodes]
    order = np.lexsort((nodes, roots))
    nodes, roots = nodes[order], roots[order]
    _, start, counts = np.unique(roots, return_index=True, return_counts=True)
    keep = (counts >= 2) & (counts <= 2 * C)
    start, counts = start[keep], counts[keep]
    by_len = np.argsort(counts, kind="stable")
    start, counts = start[by_len], counts[by_len]
    all_kp = torch.cat(kps) if kps else torch.zeros(0, 2, dtype=torch.float64)
    i = 0
    while i < len(start):
        j = i + 1
        while j < len(start) and (j + 1 - i) * int(counts[j]) ** 2 <= budget:
            j += 1
        L = int(counts[j - 1])
        pos = start[i:j, None] + np.arange(L)[None]
        valid = np.arange(L)[None] < counts[i:j, None]
        node = nodes[np.where(valid, pos, start[i:j, None])]
        cam = torch.from_numpy(np.searchsorted(offsets, node, side="right") - 1)
        yield cam, all_kp[torch.from_numpy(node)], torch.from_numpy(valid)
        i = j


def _solve_tracks(P, Pn, Kinv, cam, uv, mask, max_reproj_px: float, refine_iters: int):
    """Triangulate the tracks: linear, dropping each track's worst observation while it is more than
    ``max_reproj_px`` off (one observation per view: the others of a view go first), then Gauss-Newton.
    Returns ``(X [T, 3], valid [T], mask [T, L] of the observations used)``."""
    L = mask.shape[1]
    xn = (Kinv[cam] @ torch.cat([uv, torch.ones_like(uv[..., :1])], -1)[..., None])[..., :2, 0]
    Pt, Pnt = P[cam], Pn[cam]
    X, ok = _dlt(Pnt, xn, mask)
    earlier = (torch.arange(L)[None, :] < torch.arange(L)[:, None])[None]
    for _ in range(min(L, 6)):
        err, z = _reproject(Pt, X, uv)
        err = torch.where(mask & (z > 0), err, torch.full_like(err, float("inf")))
        same = (cam[:, :, None] == cam[:, None, :]) & mask[:, :, None] & mask[:, None, :]
        better = same & ((err[:, None, :] < err[:, :, None]) | ((err[:, None, :] == err[:, :, None]) & earlier))
        dup = better.any(2)
        err_m = torch.where(mask, err, torch.full_like(err, -1.0))
        err_m = torch.where(dup & mask, torch.full_like(err, float("inf")), err_m)
        worst_e, worst = err_m.max(1)
        drop = (worst_e > max_reproj_px) & (mask.sum(1) > 2)
        if not bool(drop.any()):
            break
        mask = mask.clone()
        mask[torch.nonzero(drop)[:, 0], worst[drop]] = False
        X, ok = _dlt(Pnt, xn, mask)
    return _gauss_newton(Pt, X, uv, mask, refine_iters), ok, mask


def _keep_points(P, centres, imgs, cam, uv, mask, X, ok, max_reproj_px: float, min_angle_deg: float):
    """The filters and colours of solved tracks: ``(X [K, 3], rgb [K, 3], mean reprojection error [K],
    observations [K], the views of the kept observations [M])`` of the points seen by at least two views, in front
    of every view that sees them, within ``max_reproj_px`` in each, at a triangulation angle of ``min_angle_deg``."""
    err, z = _reproject(P[cam], X, uv)
    obs = mask & (err <= max_reproj_px)
    in_front = ~(mask & (z <= 0)).any(1)
    # triangulation angle: the largest angle between two rays of the point
    rays = torch.nn.functional.normalize(X[:, None, :] - centres[cam], dim=-1)
    cos = rays @ rays.transpose(1, 2)
    pair_ok = obs[:, :, None] & obs[:, None, :]
    min_cos = torch.where(pair_ok, cos, torch.ones_like(cos)).flatten(1).min(1).values
    good = (ok & torch.isfinite(X).all(1) & (obs.sum(1) >= 2) & in_front
            & (min_cos <= math.cos(math.radians(min_angle_deg))))
    X, obs, err, cam, uv = X[good], obs[good], err[good], cam[good], uv[good]
    flat = obs.reshape(-1)
    cols = _sample(imgs, cam.reshape(-1)[flat], uv.reshape(-1, 2)[flat])
    owner = torch.arange(len(X))[:, None].expand_as(obs).reshape(-1)[flat]
    n = obs.sum(1)
    rgb = torch.zeros(len(X), 3).index_add_(0, owner, cols) / n[:, None].clamp_min(1).float()
    per_point = torch.where(obs, err, torch.zeros_like(err)).sum(1) / n.clamp_min(1)
    return X, rgb, per_point, n, cam[obs]


def triangulate(cameras: Cameras, images: torch.Tensor, *, names: Optional[Sequence[str]] = None,
                progress: bool = True, max_features: int = 4000, max_size: int = 1024, neighbours: int = 8,
                ratio: float = 0.8, max_epipolar_px: float = 2.0, max_reproj_px: float = 2.0,
                min_angle_deg: float = 1.0, refine_iters: int = 3,
                depth_range: Optional[tuple[float, float]] = None,
                pairs: Optional[Sequence[tuple[int, int]]] = None) -> Triangulation:
    """Triangulate points seen by the ``cameras`` in ``images`` (module docstring: the method).

    Args:
        cameras: C pinhole cameras (world-to-camera, OpenCV axes) of the images.
        images: ``[C, H, W, 3]`` float in [0, 1], matching ``cameras``' size.
        names: view names for messages (default ``cameras.names``).
        progress: show a progress bar.
        max_features: keypoints per view.
        max_size: features are found on images shrunk to at most this many pixels on their long side
            (thresholds in pixels are at that size; reported errors are in pixels of ``images``).
        neighbours: views each view is matched with (the ones that overlap it most).
        ratio: Lowe's ratio test (best / second-best descriptor distance).
        max_epipolar_px: largest Sampson distance from the known epipolar geometry, pixels.
        max_reproj_px: largest reprojection error of a kept observation, pixels.
        min_angle_deg: smallest triangulation angle (largest angle between two rays of a point), degrees
            (default 1. Fern ``images_8`` without ``sparse/``: the median distance to COLMAP's points, in % of
            their spread, 5.46 at 1 degree, 5.16 at 1.5, 4.85 at 2, keeping 3,929 / 3,692 / 3,375 points,
            ``benchmarks/captures.py --triangulation --min-angle 1 1.5 2``; but the fewer points cost training:
            bird_360 at 160 px, 500 steps, held-out 26.70 / 26.15 / 25.30 dB, docs/reconstruction.md).
        refine_iters: Gauss-Newton steps per point.
        depth_range: ``(near, far)`` of the scene seen from the cameras, for choosing pairs (default: from
            the camera layout).
        pairs: view pairs to match instead of choosing them.
    """
    t0 = time.perf_counter()
    C = len(cameras)
    if images.ndim != 4 or images.shape[0] != C or images.shape[-1] != 3:
        raise InputError(f"triangulate: images {tuple(images.shape)} do not match {C} cameras ([C, H, W, 3])")
    if (images.shape[2], images.shape[1]) != (cameras.width, cameras.height):
        raise InputError(f"triangulate: images are {images.shape[2]}x{images.shape[1]}, cameras "
                         f"{cameras.width}x{cameras.height}")
    names = list(names) if names is not None else list(cameras.names)
    cams = cameras.to("cpu")
    imgs = images.detach().to("cpu", torch.float32)
    s = min(1.0, float(max_size) / max(cams.width, cams.height))
    if s < 1.0:
        w, h = max(1, round(cams.width * s)), max(1, round(cams.height * s))
        cams = cams.rescaled(w, h)
        imgs = resize_images(imgs, h, w)
    Ks = cams.Ks.double()
    vm = cams.viewmats.double()
    R, tvec = vm[:, :3, :3], vm[:, :3, 3]
    Pn = vm[:, :3, :]                         # normalised projections [C, 3, 4]
    P = Ks @ Pn                               # pixel projections
    stats = dict(count=0, median_reprojection_error_px=None, tracks=0, pairs=0, matches=0, features=0.0,
                 mean_track_length=0.0, observations_per_view={}, scale=s, seconds=0.0)
    if C < 2:
        stats["seconds"] = time.perf_counter() - t0
        return Triangulation(torch.zeros(0, 3), torch.zeros(0, 3), stats)

    if pairs is None:
        pairs = select_pairs(cams, neighbours, depth_range)
    pairs = sorted({(min(int(i), int(j)), max(int(i), int(j))) for i, j in pairs if int(i) != int(j)})
    bar = tqdm(total=C + len(pairs), desc="triangulating: features", unit="step", leave=False,
               disable=not progress)
    kps, edges, n_matches = _match_views(imgs, Ks, R, tvec, pairs, max_features, ratio, max_epipolar_px, bar)
    bar.close()
    stats.update(pairs=len(pairs), matches=int(n_matches), features=float(np.mean([len(k) for k in kps])))
    centres = torch.linalg.inv(vm)[:, :3, 3]
    Kinv = torch.linalg.inv(Ks)
    parts = []
    for cam, uv, mask in _track_chunks(kps, edges, C):
        stats["tracks"] += int(cam.shape[0])
        X, ok, mask = _solve_tracks(P, Pn, Kinv, cam, uv, mask, max_reproj_px, refine_iters)
        parts.append(_keep_points(P, centres, imgs, cam, uv, mask, X, ok, max_reproj_px, min_angle_deg))
    X = torch.cat([p[0] for p in parts]) if parts else torch.zeros(0, 3, dtype=torch.float64)
    rgb = torch.cat([p[1] for p in parts]) if parts else torch.zeros(0, 3)
    if len(X):
        per_point = torch.cat([p[2] for p in parts])
        n_obs = torch.cat([p[3] for p in parts])
        per_view = sum(torch.bincount(p[4], minlength=C) for p in parts)
        stats.update(count=int(len(X)), median_reprojection_error_px=float(per_point.median()) / s,
                     mean_track_length=float(n_obs.double().mean()),
                     observations_per_view={names[i]: int(per_view[i]) for i in range(C)})
    stats["seconds"] = time.perf_counter() - t0
    log.info("triangulated %d points from %d views (%d pairs, %d matches, %d tracks; median reprojection "
             "error %s px) in %.1f s", stats["count"], C, stats["pairs"], stats["matches"], stats["tracks"],
             "-" if stats["median_reprojection_error_px"] is None else f"{stats['median_reprojection_error_px']:.2f}",
             stats["seconds"])
    return Triangulation(X.float().contiguous(), rgb.clamp(0, 1).float().contiguous(), stats)
